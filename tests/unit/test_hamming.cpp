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

// Mutual nearest neighbours the plain way: every pair's distance in a table, the first
// of equals nearest both ways.
MutualMatches naiveMutual(const cv::Mat& a, const cv::Mat& b) {
  std::vector<int> dist(static_cast<std::size_t>(a.rows) * static_cast<std::size_t>(b.rows));
  for (int i = 0; i < a.rows; ++i)
    for (int j = 0; j < b.rows; ++j)
      dist[static_cast<std::size_t>(i * b.rows + j)] =
          static_cast<int>(cv::norm(a.row(i), b.row(j), cv::NORM_HAMMING));
  const auto at = [&](int i, int j) { return dist[static_cast<std::size_t>(i * b.rows + j)]; };
  MutualMatches r;
  double sum = 0;
  for (int i = 0; i < a.rows; ++i) {
    int bj = 0;
    for (int j = 1; j < b.rows; ++j)
      if (at(i, j) < at(i, bj)) bj = j;
    int bi = 0;
    for (int k = 1; k < a.rows; ++k)
      if (at(k, bj) < at(bi, bj)) bi = k;
    if (bi == i) {
      ++r.count;
      sum += at(i, bj);
    }
  }
  r.meanDistance = r.count > 0 ? sum / r.count : 0.0;
  return r;
}

// The matcher takes queries four at a time: every remainder, and descriptors drawn from
// a few values so that ties are everywhere, must give exactly the plain result.
TEST(Hamming, EqualsThePlainMutualMatchForAnyCountAndTies) {
  cv::RNG rng(11);
  HammingMatcher m;
  for (const int nq : {1, 2, 3, 4, 5, 7, 8, 61}) {
    for (const int levels : {2, 256}) {
      cv::Mat a(nq, 32, CV_8UC1), b(37, 32, CV_8UC1);
      rng.fill(a, cv::RNG::UNIFORM, 0, levels);
      rng.fill(b, cv::RNG::UNIFORM, 0, levels);
      const MutualMatches want = naiveMutual(a, b);
      const MutualMatches got = m.match(a, b);
      EXPECT_EQ(got.count, want.count) << nq << " queries, " << levels << " levels";
      EXPECT_DOUBLE_EQ(got.meanDistance, want.meanDistance) << nq << " queries";
      // Both ways round: the trains become the queries.
      const MutualMatches back = m.match(b, a);
      EXPECT_EQ(back.count, naiveMutual(b, a).count) << nq << " trains";
    }
  }
}

TEST(Hamming, EmptyInputsGiveNoMatches) {
  HammingMatcher m;
  EXPECT_EQ(m.match(cv::Mat(), cv::Mat(10, 32, CV_8UC1, cv::Scalar(0))).count, 0);
}

}  // namespace
}  // namespace keyframed
