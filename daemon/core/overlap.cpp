#include "core/overlap.h"

#include "core/geometric_overlap.h"
#include "core/paper_overlap.h"

namespace keyframed {

const char* toString(OverlapMode mode) {
  return mode == OverlapMode::Paper ? "paper" : "geometric";
}

std::string OverlapConfig::validate() const {
  if (orbFeatures < 50 || orbFeatures > 50000) return "ORB features must be 50..50000";
  if (!(paperThreshold > 0.0 && paperThreshold <= 256.0))
    return "paper threshold must be in (0, 256]";
  if (paperMinMatches < 4 || paperMinMatches > orbFeatures)
    return "paper minimum matches must be 4..ORB features";
  if (maxTracks < 20 || maxTracks > 5000) return "max tracks must be 20..5000";
  if (minTracks < 8 || minTracks > maxTracks) return "min tracks must be 8..max tracks";
  // Tracks are replenished below minTracks: fewer than minInliers of them would lose
  // the track before they are.
  if (minInliers < 4 || minInliers > minTracks) return "min inliers must be 4..min tracks";
  if (!(ransacPixels > 0.0 && ransacPixels < 50.0)) return "RANSAC threshold must be in (0, 50) px";
  if (fastThreshold < 1 || fastThreshold > 200) return "FAST threshold must be 1..200";
  if (lkWindow < 5 || lkWindow > 61) return "LK window must be 5..61";
  if (lkLevels < 0 || lkLevels > 6) return "LK pyramid levels must be 0..6";
  return lens.invalidReason();
}

std::unique_ptr<OverlapEstimator> OverlapEstimator::create(const OverlapConfig& config) {
  if (config.mode == OverlapMode::Paper) return std::make_unique<PaperOverlap>(config);
  return std::make_unique<GeometricOverlap>(config);
}

}  // namespace keyframed
