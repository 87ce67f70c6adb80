#pragma once

#include <cstdint>
#include <vector>

#include <opencv2/core/types.hpp>

#include "core/frame.h"

namespace keyframed {

// FAST-9 corners (Rosten and Drummond): a pixel is a corner when 9 contiguous
// pixels of the 16 on a radius-3 circle around it are all brighter than it by
// more than the threshold, or all darker. Its response is the largest threshold
// at which it would still be one, and with non-maximum suppression a corner is
// kept only when its response beats all 8 neighbours'. The same corners, in the
// same order (row by row), as cv::FAST with TYPE_9_16 (whose responses are 0
// without the suppression; these never are). Row buffers are kept:
// detection allocates nothing once they are sized (and `out` has the capacity).
class FastCorners {
 public:
  FastCorners(int threshold, bool nonmaxSuppression);

  void detect(GrayView image, std::vector<cv::KeyPoint>& out);

 private:
  // Response of the pixel at p as a brighter (darker) corner; circle: offsets
  // of the 16 circle pixels.
  static int score(const std::uint8_t* p, const int* circle, bool brighter);

  int threshold_;
  bool nonmax_;
  std::vector<std::uint8_t> scores_;  // three rows of responses, a ring
  std::vector<std::int32_t> cols_;    // three rows of corner columns
  int count_[3] = {};                 // corners in each of those rows
};

}  // namespace keyframed
