#pragma once

#include <cstdint>
#include <vector>

#include <opencv2/core/mat.hpp>

namespace keyframed {

struct MutualMatches {
  int count = 0;            // mutual nearest neighbours (the cross-check)
  double meanDistance = 0;  // their mean Hamming distance, bits
};

// Brute-force Hamming matching of 32-byte binary descriptors (ORB), both ways
// in one pass, keeping only mutual nearest neighbours. A plain popcount loop,
// built for the CPU's popcount instruction where one exists: several times
// faster than Debian's baseline-SSE2 cv::BFMatcher (see docs/performance.md).
class HammingMatcher {
 public:
  MutualMatches match(const cv::Mat& query, const cv::Mat& train);

 private:
  std::vector<std::uint16_t> bestTrainDist_;
  std::vector<std::int32_t> bestTrainIdx_;
  std::vector<std::uint16_t> bestQueryDist_;
  std::vector<std::int32_t> bestQueryIdx_;
};

}  // namespace keyframed
