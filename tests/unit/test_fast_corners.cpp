#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>

#include "core/fast_corners.h"
#include "photos.h"

namespace keyframed {
namespace {

void expectSameAsOpenCv(const cv::Mat& img, int threshold, bool nonmax) {
  std::vector<cv::KeyPoint> theirs, ours;
  cv::FAST(img, theirs, threshold, nonmax, cv::FastFeatureDetector::TYPE_9_16);
  FastCorners fast(threshold, nonmax);
  fast.detect(GrayView::of(img), ours);
  ASSERT_EQ(ours.size(), theirs.size()) << img.size() << " t=" << threshold;
  for (std::size_t i = 0; i < ours.size(); ++i) {
    ASSERT_EQ(ours[i].pt, theirs[i].pt) << i;
    // cv::FAST scores corners only for the suppression (else response 0).
    if (nonmax) {
      ASSERT_EQ(ours[i].response, theirs[i].response) << i << " at " << ours[i].pt;
    }
  }
}

TEST(FastCorners, SameCornersAndResponsesAsCvFast) {
  for (const std::string& name : test::photoNames()) {
    const cv::Mat img = test::photo(name);
    ASSERT_FALSE(img.empty());
    for (const int t : {10, 20, 40}) {
      expectSameAsOpenCv(img, t, true);
      expectSameAsOpenCv(img, t, false);
    }
  }
}

TEST(FastCorners, NoiseOddSizesAndStridedViews) {
  cv::Mat noise(203, 317, CV_8UC1);
  cv::RNG rng(3);
  rng.fill(noise, cv::RNG::UNIFORM, 0, 256);
  cv::GaussianBlur(noise, noise, cv::Size(3, 3), 0.8);
  expectSameAsOpenCv(noise, 5, true);
  expectSameAsOpenCv(noise(cv::Rect(5, 7, 101, 60)).clone(), 5, true);
  // A view with a stride wider than its row.
  const cv::Mat roi = noise(cv::Rect(5, 7, 101, 60));
  std::vector<cv::KeyPoint> fromView, fromCopy;
  FastCorners fast(5, true);
  fast.detect(GrayView::of(roi), fromView);
  fast.detect(GrayView::of(roi.clone()), fromCopy);
  ASSERT_EQ(fromView.size(), fromCopy.size());
  // Saturated extremes: thresholds beyond the grey range find nothing.
  cv::Mat extremes(40, 40, CV_8UC1, cv::Scalar(0));
  cv::rectangle(extremes, cv::Rect(10, 10, 20, 20), cv::Scalar(255), cv::FILLED);
  expectSameAsOpenCv(extremes, 0, true);
  expectSameAsOpenCv(extremes, 254, true);
  expectSameAsOpenCv(extremes, 255, true);
}

TEST(FastCorners, TinyImagesHaveNoCorners) {
  const cv::Mat tiny(6, 6, CV_8UC1, cv::Scalar(9));
  std::vector<cv::KeyPoint> out(3);
  FastCorners(20, true).detect(GrayView::of(tiny), out);
  EXPECT_TRUE(out.empty());
}

}  // namespace
}  // namespace keyframed
