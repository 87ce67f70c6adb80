#include "core/paper_overlap.h"

namespace keyframed {

PaperOverlap::PaperOverlap(const OverlapConfig& config)
    : config_(config), orb_(cv::ORB::create(config.orbFeatures)) {
  keypoints_.reserve(static_cast<std::size_t>(config.orbFeatures) * 2);
}

OverlapResult PaperOverlap::observe(GrayView gray) {
  OverlapResult r;
  keypoints_.clear();
  orb_->detectAndCompute(gray.mat(), cv::noArray(), keypoints_, current_);
  r.features = current_.rows;
  if (!haveReference_) return r;
  const MutualMatches m = matcher_.match(current_, reference_);
  r.matches = m.count;
  r.paperDistance = m.meanDistance;
  r.valid = m.count >= config_.paperMinMatches;
  return r;
}

void PaperOverlap::setReferenceToCurrent() {
  current_.copyTo(reference_);
  haveReference_ = true;
  haveCandidate_ = false;
}

void PaperOverlap::markCandidate() {
  current_.copyTo(candidate_);
  haveCandidate_ = true;
}

OverlapResult PaperOverlap::setReferenceToCandidate() {
  OverlapResult r;
  if (!haveCandidate_) return r;
  std::swap(reference_, candidate_);
  haveReference_ = true;
  haveCandidate_ = false;
  const MutualMatches m = matcher_.match(current_, reference_);
  r.features = current_.rows;
  r.matches = m.count;
  r.paperDistance = m.meanDistance;
  r.valid = m.count >= config_.paperMinMatches;
  return r;
}

void PaperOverlap::reset() {
  haveReference_ = false;
  haveCandidate_ = false;
}

}  // namespace keyframed
