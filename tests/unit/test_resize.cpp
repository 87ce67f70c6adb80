#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "core/resize.h"
#include "photos.h"

namespace keyframed {
namespace {

// Uniform noise: every pixel differs from its neighbours, the hardest case
// for rounding.
cv::Mat noise(int w, int h, int seed) {
  cv::Mat m(h, w, CV_8UC1);
  cv::RNG rng(static_cast<std::uint64_t>(seed));
  rng.fill(m, cv::RNG::UNIFORM, 0, 256);
  return m;
}

double maxDiff(const cv::Mat& a, const cv::Mat& b) {
  double m = 0;
  cv::minMaxLoc(cv::abs(a - b) + cv::abs(b - a), nullptr, &m);
  return m;
}

TEST(Resize, HalvingIsInterAreaExactly) {
  // Even sizes: INTER_AREA takes its exact 2x path. (With an odd size the
  // factor is not 2 for cv::resize; halveArea drops the last row or column.)
  for (const cv::Size s : {cv::Size(1920, 1080), cv::Size(640, 362), cv::Size(38, 6)}) {
    const cv::Mat src = noise(s.width, s.height, s.width);
    cv::Mat ours, theirs;
    halveArea(GrayView::of(src), ours);
    cv::resize(src, theirs, cv::Size(s.width / 2, s.height / 2), 0, 0, cv::INTER_AREA);
    ASSERT_EQ(ours.size(), theirs.size());
    EXPECT_EQ(maxDiff(ours, theirs), 0.0) << s;
  }
}

TEST(Resize, HalvingReadsAStridedView) {
  const cv::Mat big = noise(300, 200, 7);
  const cv::Mat roi = big(cv::Rect(3, 5, 250, 150));
  cv::Mat ours, theirs;
  halveArea(GrayView::of(roi), ours);
  cv::resize(roi, theirs, cv::Size(125, 75), 0, 0, cv::INTER_AREA);
  EXPECT_EQ(maxDiff(ours, theirs), 0.0);
}

// cv::resize's 8-bit INTER_LINEAR itself rounds with up to ~1.5 grey levels of
// error (fixed-point, truncating vector path in OpenCV 4.6); its float path is
// the exact bilinear value. Ours: within half a level of it where the weights
// are exact in fixed point (1.5x: quarters), within one level otherwise.
TEST(Resize, BilinearMatchesInterLinear) {
  const cv::Mat photo = test::photo("aero1.jpg");
  ASSERT_FALSE(photo.empty());
  struct Case {
    cv::Mat src;
    cv::Size dst;
  };
  const Case cases[] = {
      {noise(960, 540, 1), {640, 360}},  // the analysis step at 1080p
      {noise(960, 540, 2), {700, 393}},  // odd factors
      {noise(800, 600, 3), {799, 599}},  // almost 1:1
      {noise(100, 80, 4), {150, 120}},   // upscaling
      {photo, {photo.cols * 2 / 3, photo.rows * 2 / 3}},
  };
  for (const Case& c : cases) {
    BilinearResizer r;
    cv::Mat ours, theirs;
    r.resize(GrayView::of(c.src), c.dst, ours);
    cv::resize(c.src, theirs, c.dst, 0, 0, cv::INTER_LINEAR);
    ASSERT_EQ(ours.size(), theirs.size());
    EXPECT_LE(maxDiff(ours, theirs), 2.0) << c.src.size() << " -> " << c.dst;
    cv::Mat srcF, exact, oursF;
    c.src.convertTo(srcF, CV_32F);
    cv::resize(srcF, exact, c.dst, 0, 0, cv::INTER_LINEAR);
    ours.convertTo(oursF, CV_32F);
    double worst = 0;
    cv::minMaxLoc(cv::abs(oursF - exact), nullptr, &worst);
    const bool quarters = c.src.cols * 2 == c.dst.width * 3 && c.src.rows * 2 == c.dst.height * 3;
    EXPECT_LE(worst, quarters ? 0.501 : 1.0) << c.src.size() << " -> " << c.dst;
  }
}

TEST(Resize, RepeatedCallsKeepTheirBuffers) {
  const cv::Mat a = noise(1920, 1080, 5);
  const cv::Mat b = noise(1920, 1080, 6);
  DownScaler s;
  const GrayView first = s.scale(GrayView::of(a), 640, 360);
  const std::uint8_t* data = first.data;
  const GrayView second = s.scale(GrayView::of(b), 640, 360);
  EXPECT_EQ(second.data, data);
  EXPECT_EQ(second.width, 640);
  EXPECT_EQ(second.height, 360);
}

TEST(Resize, DownScalerHalvesThenInterpolates) {
  const cv::Mat src = test::photo("aero1.jpg");
  ASSERT_FALSE(src.empty());
  DownScaler s;
  // An exact power of two: halvings only, INTER_AREA exactly.
  const int w4 = src.cols / 4, h4 = src.rows / 4;
  cv::Mat expected;
  cv::resize(src, expected, cv::Size(src.cols / 2, src.rows / 2), 0, 0, cv::INTER_AREA);
  cv::resize(expected, expected, cv::Size(w4, h4), 0, 0, cv::INTER_AREA);
  const GrayView q = s.scale(GrayView::of(src), w4, h4);
  EXPECT_EQ(maxDiff(q.mat(), expected), 0.0);
  // Otherwise one bilinear step after the halvings.
  const int w = src.cols / 3, h = src.rows / 3;
  cv::Mat half;
  cv::resize(src, half, cv::Size(src.cols / 2, src.rows / 2), 0, 0, cv::INTER_AREA);
  cv::resize(half, expected, cv::Size(w, h), 0, 0, cv::INTER_LINEAR);
  const GrayView t = s.scale(GrayView::of(src), w, h);
  EXPECT_LE(maxDiff(t.mat(), expected), 2.0);
  // No wider than the target: the source itself.
  EXPECT_EQ(s.scale(GrayView::of(src), src.cols, src.rows).data, src.data);
}

}  // namespace
}  // namespace keyframed
