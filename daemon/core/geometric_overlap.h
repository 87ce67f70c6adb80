#pragma once

#include <span>
#include <vector>

#include <opencv2/core/matx.hpp>
#include <opencv2/core/types.hpp>

#include "core/fast_corners.h"
#include "core/homography.h"
#include "core/lk_tracker.h"
#include "core/overlap.h"

namespace keyframed {

// Overlap as geometry: corners tracked frame to frame with pyramidal
// Lucas-Kanade, a RANSAC homography per step, composed into the homography from
// the reference keyframe to the current frame. The overlap is the fraction of
// the reference image area that the current frame still shows. Composing steps
// (instead of matching against the keyframe) keeps each step small and cheap,
// and lets any past frame whose homography was remembered become the reference.
class GeometricOverlap final : public OverlapEstimator {
 public:
  explicit GeometricOverlap(const OverlapConfig& config);

  OverlapResult observe(GrayView gray) override;
  void setReferenceToCurrent() override;
  void markCandidate() override;
  OverlapResult setReferenceToCandidate() override;
  void reset() override;
  // The corners tracked into the frame last observed (for tests: how they spread).
  [[nodiscard]] std::span<const cv::Point2f> tracks() const { return prevPts_; }

 private:
  void replenish(GrayView gray);
  OverlapResult overlapNow() const;
  // The lens at the analysis size and the ideal pixels of its sample grid.
  void prepareLens();
  // How far the image moved in a step, in image pixels.
  double stepMotion(const cv::Matx33d& h) const;
  // The in-plane rotation of a step's homography about the image centre, radians.
  double rotationAtCentre(const cv::Matx33d& h) const;
  double lensVisibleFraction(const cv::Matx33d& refToCur) const;

  OverlapConfig config_;
  cv::Size size_;
  LkPyramid prevPyr_;
  LkPyramid curPyr_;
  LkTracker lk_;
  std::vector<cv::Point2f> prevPts_;
  std::vector<cv::Point2f> curPts_;
  std::vector<cv::Point2f> goodPrev_;
  std::vector<cv::Point2f> goodCur_;
  LensModel lens_;                      // config_.lens at the analysis size
  std::vector<cv::Point2f> idealPrev_;  // goodPrev_/goodCur_ undistorted
  std::vector<cv::Point2f> idealCur_;
  std::vector<cv::Point2d> sampleIdeal_;  // the reference's sample grid, ideal pixels
  double lensReach2_ = 0.0;               // lens_.monotonicRadius() squared
  std::vector<unsigned char> status_;
  std::vector<unsigned char> inlierMask_;
  std::vector<cv::KeyPoint> keypoints_;
  int perCell_;                         // corners wanted per grid cell
  std::vector<int> cellCount_;          // tracked corners per cell
  std::vector<int> cellBestCount_;      // new corners held per cell
  std::vector<cv::KeyPoint> cellBest_;  // perCell_ slots per cell
  FastCorners fast_;
  RansacHomography ransac_;
  cv::Matx33d refToCur_ = cv::Matx33d::eye();
  cv::Matx33d refToCandidate_ = cv::Matx33d::eye();
  bool havePrev_ = false;
  bool haveReference_ = false;
  bool haveCandidate_ = false;
  int lastTracked_ = 0;
  int lastInliers_ = 0;
  double lastMotion_ = 0.0;
  double lastRotation_ = 0.0;
};

}  // namespace keyframed
