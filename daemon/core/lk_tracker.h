#pragma once

#include <cstdint>
#include <vector>

#include <opencv2/core/hal/intrin.hpp>
#include <opencv2/core/mat.hpp>
#include <opencv2/core/types.hpp>

#include "core/frame.h"

namespace keyframed {

// An image pyramid for LkTracker: level 0 is the image, each level above is the
// one below smoothed with the 5-tap binomial kernel and halved (cv::pyrDown).
// Every level sits inside a border filled by reflection (BORDER_REFLECT_101), so
// a tracking window may hang over the image edge. Buffers are kept: rebuilding
// at an unchanged size allocates nothing.
class LkPyramid {
 public:
  // Up to maxLevel + 1 levels; fewer when a level would be no larger than
  // `window` (as cv::buildOpticalFlowPyramid).
  void build(GrayView image, int maxLevel, int window);

  [[nodiscard]] int levels() const { return levels_; }
  // Pixels readable beyond each side of every level.
  [[nodiscard]] int border() const { return border_; }
  // Level i without its border.
  [[nodiscard]] GrayView level(int i) const;

 private:
  std::vector<cv::Mat> padded_;
  std::vector<std::uint16_t> rowSums_;  // pyrDown's vertical pass
  int levels_ = 0;
  int border_ = 0;
};

struct LkConfig {
  int window = 13;              // side of the square window, pixels
  int maxLevel = 3;             // pyramid levels above the image
  int maxIterations = 20;       // per level
  double epsilon = 0.03;        // a level ends when a step is shorter than this (pixels)
  double minEigenvalue = 1e-4;  // as cv::calcOpticalFlowPyrLK's minEigThreshold
};

// Pyramidal Lucas-Kanade (Bouguet's iterative scheme, as cv::calcOpticalFlowPyrLK):
// per level, the window's gradients in the previous image are interpolated once,
// then the displacement is refined by Newton steps with bilinear sampling of the
// next image. A point fails when its gradient matrix is too weak (flat or
// one-dimensional texture) or its window leaves the image at the finest level.
// Scratch space is sized once; tracking allocates nothing once the output
// vectors have the capacity.
class LkTracker {
 public:
  explicit LkTracker(const LkConfig& config);

  // Floats in a window row as the tracker stores it: window rounded up to
  // whole pairs of vectors.
  static int rowStride(int window);

  // nextPts[i] and status[i] (1: tracked) for every prevPts[i].
  void track(const LkPyramid& prev, const LkPyramid& next, const std::vector<cv::Point2f>& prevPts,
             std::vector<cv::Point2f>& nextPts, std::vector<unsigned char>& status);

 private:
  bool trackPoint(const LkPyramid& prev, const LkPyramid& next, int levels, cv::Point2f prevPt,
                  cv::Point2f& nextPt);

  static constexpr int kLanes = cv::v_float32x4::nlanes;

  LkConfig config_;
  int stride_;
  std::vector<float> patch_;  // (window + 2) rows of samples of the previous image
  std::vector<float> i_;      // window rows of samples of the previous image
  std::vector<float> ix_;     // and its gradients
  std::vector<float> iy_;
  std::vector<cv::v_float32x4> rows_;  // two rows of the next image, interpolated along x
};

}  // namespace keyframed
