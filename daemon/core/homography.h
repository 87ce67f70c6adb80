#pragma once

#include <cstdint>
#include <vector>

#include <opencv2/core/matx.hpp>
#include <opencv2/core/types.hpp>

namespace keyframed {

struct HomographyFit {
  bool ok = false;
  cv::Matx33d h = cv::Matx33d::eye();  // maps src points to dst points, h(2,2) = 1
  int inliers = 0;
};

// RANSAC homography between two point sets: 4-point solves on normalised
// coordinates, then a least-squares refit on all inliers. Unlike
// cv::findHomography (about 90 heap allocations a call) it works in buffers it
// keeps, and it is deterministic: the sampler is seeded the same every call.
class RansacHomography {
 public:
  HomographyFit fit(const std::vector<cv::Point2f>& src, const std::vector<cv::Point2f>& dst,
                    double thresholdPx, std::vector<unsigned char>& inlierMask,
                    double confidence = 0.995, int maxIterations = 500);

 private:
  std::vector<cv::Point2d> a_;  // normalised src
  std::vector<cv::Point2d> b_;  // normalised dst
  std::vector<unsigned char> bestMask_;
  std::vector<int> inlierIdx_;
};

// Solves the 8x8 DLT system for the homography (h33 = 1) through four or more
// correspondences in the least-squares sense. Returns false when degenerate.
bool solveHomography(const cv::Point2d* src, const cv::Point2d* dst, const int* idx, int n,
                     cv::Matx33d& out);

}  // namespace keyframed
