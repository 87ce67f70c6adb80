#include <gtest/gtest.h>
#include <opencv2/features2d.hpp>

#include "core/hamming.h"

namespace keyframed {
namespace {

TEST(Hamming, AgreesWithOpenCvCrossCheckMatcher) {
  cv::RNG rng(7);
  cv::Mat a(700, 32, CV_8UC1), b(650, 32, CV_8UC1);
  rng.fill(a, cv::RNG::UNIFORM, 0, 256);
  rng.fill(b, cv::RNG::UNIFORM, 0, 256);
  // Plant near-duplicates so that there are real matches.
  for (int i = 0; i < 300; ++i) {
    a.row(i).copyTo(b.row(i * 2));
    b.at<uchar>(i * 2, i % 32) ^= 0x5;
  }
  cv::BFMatcher bf(cv::NORM_HAMMING, true);
  std::vector<cv::DMatch> ref;
  bf.match(a, b, ref);
  double sum = 0;
  for (const auto& m : ref) sum += m.distance;
  HammingMatcher m;
  const MutualMatches got = m.match(a, b);
  // Ties may resolve differently; counts and mean must agree closely.
  EXPECT_NEAR(got.count, static_cast<int>(ref.size()), 3);
  EXPECT_NEAR(got.meanDistance, sum / static_cast<double>(ref.size()), 0.5);
  EXPECT_GE(got.count, 300);
}

TEST(Hamming, EmptyInputsGiveNoMatches) {
  HammingMatcher m;
  EXPECT_EQ(m.match(cv::Mat(), cv::Mat(10, 32, CV_8UC1, cv::Scalar(0))).count, 0);
}

}  // namespace
}  // namespace keyframed
