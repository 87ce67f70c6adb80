#include <algorithm>
#include <cmath>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include "core/lk_tracker.h"
#include "geometry.h"
#include "photos.h"

namespace keyframed {
namespace {

// A 640 x 360 view of an aerial photograph: the analysis image of a survey.
cv::Mat ground() {
  const cv::Mat p = test::photo("aero3.jpg");
  if (p.empty()) return {};
  cv::Mat r;
  cv::resize(p, r, cv::Size(640, 360), 0, 0, cv::INTER_AREA);
  return r;
}

cv::Mat warped(const cv::Mat& src, const cv::Matx33d& h) {
  cv::Mat out;
  cv::warpPerspective(src, out, h, src.size(), cv::INTER_CUBIC, cv::BORDER_REFLECT_101);
  return out;
}

std::vector<cv::Point2f> corners(const cv::Mat& img, int margin = 20) {
  std::vector<cv::Point2f> pts;
  cv::goodFeaturesToTrack(img, pts, 200, 0.01, 12);
  std::erase_if(pts, [&](cv::Point2f p) {
    return p.x < margin || p.y < margin || p.x > img.cols - margin || p.y > img.rows - margin;
  });
  return pts;
}

struct Errors {
  double median = 0;
  double p90 = 0;
  double tracked = 0;  // fraction
};

Errors errors(const std::vector<cv::Point2f>& prev, const std::vector<cv::Point2f>& next,
              const std::vector<unsigned char>& status, const cv::Matx33d& h) {
  std::vector<double> e;
  for (std::size_t i = 0; i < prev.size(); ++i)
    if (status[i]) e.push_back(cv::norm(next[i] - test::applyHomography(h, prev[i])));
  if (e.empty()) return {};
  std::sort(e.begin(), e.end());
  return {e[e.size() / 2], e[e.size() * 9 / 10],
          static_cast<double>(e.size()) / static_cast<double>(prev.size())};
}

Errors ours(const cv::Mat& a, const cv::Mat& b, const std::vector<cv::Point2f>& pts,
            const cv::Matx33d& h) {
  LkPyramid pa, pb;
  pa.build(GrayView::of(a), 3, 13);
  pb.build(GrayView::of(b), 3, 13);
  LkTracker lk{LkConfig{}};
  std::vector<cv::Point2f> next;
  std::vector<unsigned char> status;
  lk.track(pa, pb, pts, next, status);
  return errors(pts, next, status, h);
}

Errors opencv(const cv::Mat& a, const cv::Mat& b, const std::vector<cv::Point2f>& pts,
              const cv::Matx33d& h) {
  std::vector<cv::Point2f> next;
  std::vector<unsigned char> status;
  std::vector<float> err;
  cv::calcOpticalFlowPyrLK(
      a, b, pts, next, status, err, cv::Size(13, 13), 3,
      cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 20, 0.03));
  return errors(pts, next, status, h);
}

TEST(LkPyramid, LevelsAreGaussianHalvings) {
  const cv::Mat g = ground();
  ASSERT_FALSE(g.empty());
  LkPyramid p;
  p.build(GrayView::of(g), 3, 13);
  ASSERT_EQ(p.levels(), 4);
  cv::Mat expected = g;
  for (int l = 1; l < 4; ++l) {
    cv::pyrDown(expected, expected);
    const cv::Mat ours = p.level(l).mat();
    ASSERT_EQ(ours.size(), expected.size()) << "level " << l;
    double m = 0;
    cv::minMaxLoc(cv::abs(ours - expected) + cv::abs(expected - ours), nullptr, &m);
    EXPECT_LE(m, 1.0) << "level " << l;
  }
  // The border mirrors the image (BORDER_REFLECT_101).
  const GrayView l0 = p.level(0);
  EXPECT_EQ(l0.row(0)[-1], l0.row(0)[1]);
  EXPECT_EQ(l0.row(-2)[5], l0.row(2)[5]);
  EXPECT_EQ(l0.row(10)[l0.width + 1], l0.row(10)[l0.width - 3]);
}

TEST(LkPyramid, StopsBeforeALevelNoLargerThanTheWindow) {
  const cv::Mat small(60, 100, CV_8UC1, cv::Scalar(7));
  LkPyramid p;
  p.build(GrayView::of(small), 5, 13);
  EXPECT_EQ(p.levels(), 3);  // 100x60, 50x30, 25x15; 13x8 would be too small
}

TEST(LkTracker, SubPixelShift) {
  const cv::Mat a = ground();
  ASSERT_FALSE(a.empty());
  const cv::Matx33d h(1, 0, 3.3, 0, 1, -1.7, 0, 0, 1);
  const cv::Mat b = warped(a, h);
  const auto pts = corners(a);
  ASSERT_GT(pts.size(), 100u);
  const Errors e = ours(a, b, pts, h);
  const Errors cv = opencv(a, b, pts, h);
  EXPECT_LT(e.median, 0.1);
  EXPECT_GT(e.tracked, 0.95);
  EXPECT_LE(e.p90, std::max(0.15, 1.5 * cv.p90)) << "OpenCV p90 " << cv.p90;
}

TEST(LkTracker, LargeMotionThroughThePyramid) {
  const cv::Mat a = ground();
  const cv::Matx33d h(1, 0, -22.6, 0, 1, 14.2, 0, 0, 1);
  const cv::Mat b = warped(a, h);
  const auto pts = corners(a, 40);
  const Errors e = ours(a, b, pts, h);
  EXPECT_LT(e.median, 0.1);
  EXPECT_GT(e.tracked, 0.9);
}

TEST(LkTracker, HomographyAsAccurateAsOpenCv) {
  const cv::Mat a = ground();
  // A yaw of 2 degrees, 3 % closer, a little perspective and a drift.
  const double c = std::cos(0.035) * 1.03, s = std::sin(0.035) * 1.03;
  const cv::Matx33d t1(1, 0, -320, 0, 1, -180, 0, 0, 1), t2(1, 0, 324, 0, 1, 177, 0, 0, 1);
  const cv::Matx33d h = t2 * cv::Matx33d(c, -s, 0, s, c, 0, 2e-5, -1e-5, 1) * t1;
  const cv::Mat b = warped(a, h);
  const auto pts = corners(a, 30);
  const Errors e = ours(a, b, pts, h);
  const Errors cv = opencv(a, b, pts, h);
  EXPECT_LT(e.median, 0.15);
  EXPECT_LE(e.median, std::max(0.05, 1.5 * cv.median)) << "OpenCV median " << cv.median;
  EXPECT_GT(e.tracked, 0.9 * cv.tracked);
}

TEST(LkTracker, FlatWindowsAndLostPointsFail) {
  cv::Mat a(360, 640, CV_8UC1, cv::Scalar(100));
  cv::rectangle(a, cv::Rect(300, 150, 60, 60), cv::Scalar(200), cv::FILLED);
  const cv::Matx33d h(1, 0, 2.0, 0, 1, 1.0, 0, 0, 1);
  const cv::Mat b = warped(a, h);
  LkPyramid pa, pb;
  pa.build(GrayView::of(a), 3, 13);
  pb.build(GrayView::of(b), 3, 13);
  LkTracker lk{LkConfig{}};
  const std::vector<cv::Point2f> pts = {{100, 100}, {300, 150}, {330, 150}, {-40, 10}};
  std::vector<cv::Point2f> next;
  std::vector<unsigned char> status;
  lk.track(pa, pb, pts, next, status);
  ASSERT_EQ(status.size(), pts.size());
  EXPECT_FALSE(status[0]);  // flat: no gradient at all
  EXPECT_TRUE(status[1]);   // a corner
  EXPECT_NEAR(next[1].x, 302.0, 0.2);
  EXPECT_NEAR(next[1].y, 151.0, 0.2);
  EXPECT_FALSE(status[2]);  // an edge: the aperture problem
  EXPECT_FALSE(status[3]);  // outside the image
}

TEST(LkTracker, ReusedOutputsKeepTheirMemory) {
  const cv::Mat a = ground();
  const cv::Matx33d h(1, 0, 1.5, 0, 1, 0.5, 0, 0, 1);
  const cv::Mat b = warped(a, h);
  const auto pts = corners(a);
  LkPyramid pa, pb;
  pa.build(GrayView::of(a), 3, 13);
  pb.build(GrayView::of(b), 3, 13);
  const std::uint8_t* level0 = pb.level(0).data;
  pb.build(GrayView::of(a), 3, 13);
  EXPECT_EQ(pb.level(0).data, level0);
  LkTracker lk{LkConfig{}};
  std::vector<cv::Point2f> next;
  std::vector<unsigned char> status;
  next.reserve(pts.size());
  status.reserve(pts.size());
  const cv::Point2f* buf = next.data();
  lk.track(pa, pb, pts, next, status);
  EXPECT_EQ(next.data(), buf);
}

}  // namespace
}  // namespace keyframed
