#pragma once

#include <vector>

#include <opencv2/features2d.hpp>

#include "core/hamming.h"
#include "core/overlap.h"

namespace keyframed {

// The paper's redundancy test: ORB features of each frame matched by brute-force
// Hamming distance against the last keyframe's; the statistic is the mean
// distance of the mutual nearest neighbours (it grows as the views part).
class PaperOverlap final : public OverlapEstimator {
 public:
  explicit PaperOverlap(const OverlapConfig& config);

  OverlapResult observe(GrayView gray) override;
  void setReferenceToCurrent() override;
  void markCandidate() override;
  OverlapResult setReferenceToCandidate() override;
  void reset() override;

 private:
  OverlapConfig config_;
  cv::Ptr<cv::ORB> orb_;
  HammingMatcher matcher_;
  std::vector<cv::KeyPoint> keypoints_;
  cv::Mat current_;
  cv::Mat reference_;
  cv::Mat candidate_;
  bool haveReference_ = false;
  bool haveCandidate_ = false;
};

}  // namespace keyframed
