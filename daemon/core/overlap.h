#pragma once

#include <limits>
#include <memory>
#include <string>

#include "core/frame.h"
#include "core/lens.h"

namespace keyframed {

enum class OverlapMode {
  Paper,      // ORB + brute-force Hamming, mean distance against a threshold t
  Geometric,  // tracked features + RANSAC homography, visible-area fraction
};

const char* toString(OverlapMode mode);

struct OverlapConfig {
  OverlapMode mode = OverlapMode::Geometric;
  // Paper mode.
  int orbFeatures = 2500;
  double paperThreshold = 50.0;  // keep when mean mutual-match distance >= t (bits)
  int paperMinMatches = 20;      // fewer mutual matches: the scene is lost
  // Geometric mode.
  int maxTracks = 200;        // points tracked frame to frame
  int minTracks = 80;         // replenish below this many
  int minInliers = 15;        // fewer RANSAC inliers: tracking lost
  double ransacPixels = 1.5;  // RANSAC reprojection threshold at analysis size
  int fastThreshold = 20;
  int lkWindow = 13;
  int lkLevels = 3;
  // The camera's lens (geometric mode): when set, tracked points are undistorted
  // before the homography is fitted, and the overlap is the share of the reference
  // image's pixels that land inside the current image through the lens. Scaled to
  // the analysis size. None: pixels are taken as a distortion-free pinhole's.
  LensModel lens;

  bool operator==(const OverlapConfig&) const = default;
  [[nodiscard]] std::string validate() const;
};

struct OverlapResult {
  bool valid = false;  // false: no reference yet, or tracking lost
  double overlap = std::numeric_limits<double>::quiet_NaN();        // 0..1 (geometric)
  double paperDistance = std::numeric_limits<double>::quiet_NaN();  // bits (paper)
  int features = 0;  // features detected or tracked in this frame
  int matches = 0;   // correspondences with the reference chain
  int inliers = 0;   // RANSAC inliers (geometric)
  // Geometric: how far the image moved since the previous frame, the largest
  // displacement of its corners and centre, in analysis pixels (NaN if unknown).
  double motionPx = std::numeric_limits<double>::quiet_NaN();
  // Geometric: how far the image turned about the optical axis (the principal point
  // with a lens, else the image centre) since the previous frame, radians; positive
  // takes +x toward +y (x right, y down: clockwise on screen). NaN if unknown.
  double stepRotationRad = std::numeric_limits<double>::quiet_NaN();
};

// Measures how much of the last keyframe the current frame still shows.
// Frames are observed in capture order; the selector tells the estimator which
// frame becomes the reference.
class OverlapEstimator {
 public:
  virtual ~OverlapEstimator() = default;

  // Analyse the next frame (grey, at analysis size) against the reference.
  virtual OverlapResult observe(GrayView gray) = 0;
  // The frame just observed becomes the reference.
  virtual void setReferenceToCurrent() = 0;
  // Remember the frame just observed as a possible later reference.
  virtual void markCandidate() = 0;
  // The remembered candidate becomes the reference; the current frame's overlap
  // with it is returned. Returns an invalid result when there is no candidate.
  virtual OverlapResult setReferenceToCandidate() = 0;
  // Forget the reference (after tracking is lost).
  virtual void reset() = 0;

  static std::unique_ptr<OverlapEstimator> create(const OverlapConfig& config);
};

}  // namespace keyframed
