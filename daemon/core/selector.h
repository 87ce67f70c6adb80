#pragma once

#include <atomic>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "core/frame.h"
#include "core/overlap.h"
#include "core/resize.h"
#include "core/running_quantile.h"
#include "core/sharpness.h"

namespace keyframed {

// Why a frame was or was not kept.
enum class Reason {
  First,          // kept: the first sharp frame (or the first after tracking was lost)
  OverlapTarget,  // kept: overlap with the last keyframe fell to the target
  PaperDistance,  // kept: paper mode, match distance reached the threshold t
  GapFill,        // kept as a fallback: the sharpest frame in the band since the last
                  //   keyframe, promoted later because overlap was about to leave the
                  //   band (paper mode: t was reached on a blurred frame) or tracking
                  //   was lost; or, with no such frame, the frame at
                  //   the band's lower edge even though it is not sharp
  Blurry,         // dropped: sharpness under the threshold
  Redundant,      // dropped: overlap still above the target (or distance under t)
  Lost,           // dropped: tracking was lost and this frame cannot start a new chain
                  //   (blurry, or not yet tracked from the frame before it)
  Featureless,    // dropped: the last keyframe had too little texture to track (water,
                  //   sky, a uniform field), and so has this frame: no overlap to
                  //   measure, and no reason to keep it over the keyframe
  Commanded,      // kept: a capture was requested (MAVLink MAV_CMD_IMAGE_START_CAPTURE)
                  //   and this is the first sharp frame since (or, after
                  //   captureWaitMs, the first at the blur floor)
  Refocus,        // kept: the stream's first keyframe was taken while the blur statistic
                  //   was warming up (only the floor to judge by) and this frame of the
                  //   same view is kRefocusRatio times as sharp: a camera that opened
                  //   out of focus. It replaces that keyframe as the reference.
};

const char* toString(Reason reason);

// Durations are measured by the caller's clock; core itself reads no clock.
class Clock {
 public:
  virtual ~Clock() = default;
  [[nodiscard]] virtual std::int64_t nowNs() const = 0;
};

struct StageTimes {
  std::int64_t lumaNs = 0;
  std::int64_t blurNs = 0;
  std::int64_t resizeNs = 0;
  std::int64_t overlapNs = 0;
  std::int64_t totalNs = 0;
};

// The outcome for one frame. Every frame gets one.
struct Decision {
  std::int64_t index = 0;
  std::int64_t timestampNs = 0;
  bool kept = false;
  Reason reason = Reason::Redundant;
  // This frame is now the best fallback since the last keyframe: the caller must
  // keep its pixels until a later decision promotes it or a keyframe supersedes it.
  bool candidate = false;
  // >= 0: that earlier candidate frame is a keyframe now (Reason::GapFill).
  std::int64_t promotedIndex = -1;
  double sharpness = 0.0;
  double threshold = 0.0;
  bool sharp = false;
  double overlap = std::numeric_limits<double>::quiet_NaN();  // vs the last keyframe
  double paperDistance = std::numeric_limits<double>::quiet_NaN();
  bool tracking = false;
  bool fastMotion = false;                                     // failed the motion gate
  double motionPx = std::numeric_limits<double>::quiet_NaN();  // since the previous frame
  int features = 0;
  int matches = 0;
  int inliers = 0;
  StageTimes times;
};

struct SelectorConfig {
  SharpnessConfig blur;
  OverlapConfig overlap;
  double target = 0.70;      // keep a frame when overlap with the last keyframe falls to this
  double bandLow = 0.60;     // never let overlap fall under this: promote the best candidate
  double bandHigh = 0.85;    // frames above this are too redundant to be fallbacks
  double minOverlap = 0.50;  // hard floor: below this even a blurry fallback is kept
  // Motion gate (geometric mode): a frame that moved more than motionRatio times
  // the lower quartile of recent moving frames' motion (robust to long manoeuvres;
  // frames moving less than a quarter of the floor below, a hover, do not count),
  // and more than motionMinFraction of the image width, is judged blurred by motion
  // whatever its Laplacian score says. 0 disables.
  double motionRatio = 4.0;
  double motionMinFraction = 0.01;
  int motionWindow = 150;   // recent frames whose lower-quartile motion is the reference
  int analysisWidth = 640;  // overlap analysis width in pixels (0: full resolution)
  // A requested capture waits this long (frame time, ms) for a sharp frame, then
  // takes the next frame at the blur floor: a photograph asked for is never refused.
  int captureWaitMs = 1000;

  [[nodiscard]] std::string validate() const;
};

// Frame-selection policy: blur gate, then overlap against the last keyframe.
class KeyframeSelector {
 public:
  explicit KeyframeSelector(const SelectorConfig& config = {}, const Clock* clock = nullptr);

  // Decide for the next frame (frames in capture order).
  Decision process(const Frame& frame);

  // End of the stream: the candidate, if any, becomes a keyframe so that the
  // last stretch of the flight is covered too (in geometric mode a sharp one only:
  // candidateAcceptable). Returns its index, or -1.
  std::int64_t finish();

  // Apply new settings (SIGHUP). A new overlap mode, tracking setting or analysis
  // size restarts selection at the next sharp frame (call finish() first to keep the
  // candidate); a new target, band or blur setting applies to the frames that follow,
  // against the same last keyframe. The blur statistic starts again only when a blur
  // setting changed. Requested captures still pending stay so.
  [[nodiscard]] bool reconfigureRestartsChain(const SelectorConfig& config) const;
  void reconfigure(const SelectorConfig& config);

  // A capture was asked for (e.g. by the autopilot or a ground station): the next
  // sharp frame is a keyframe whatever its overlap (Reason::Commanded), unless a
  // keyframe comes anyway. Each request gives one keyframe; at most
  // kMaxCaptureRequests wait at a time (more are refused: returns false).
  // Thread-safe (the rest of the selector is not).
  bool requestCapture();
  static constexpr int kMaxCaptureRequests = 16;
  // Reason::Refocus: how much sharper than a first keyframe taken in the warm-up.
  static constexpr double kRefocusRatio = 2.0;
  [[nodiscard]] int pendingCaptures() const { return captureRequests_.load(); }

  [[nodiscard]] const SelectorConfig& config() const { return config_; }
  [[nodiscard]] std::int64_t keyframes() const { return keyframes_; }
  [[nodiscard]] std::int64_t candidateIndex() const { return candidateIndex_; }

 private:
  [[nodiscard]] std::int64_t now() const { return clock_ ? clock_->nowNs() : 0; }
  void keepCurrent(Decision& d, Reason reason);
  bool promoteCandidate(Decision& d);
  // The candidate may be kept at a loss of tracking or at the end (where no overlap
  // says a gap would open): sharp, or any in paper mode.
  [[nodiscard]] bool candidateAcceptable() const;
  // The candidate becomes a keyframe (promoted with this decision) and the reference.
  void fallBackToCandidate(Decision& d);
  // This frame, not kept, becomes the fallback candidate if it is the best since the
  // last keyframe (and not under the blur floor).
  void noteCandidate(Decision& d);
  void clearCandidate();
  void serveCaptureRequest(Decision& d);
  bool motionTooFast(double motionPx, int analysisWidth);
  // Fewer features than this in a reference and overlap cannot be measured against it.
  [[nodiscard]] int minTrackable() const;

  SelectorConfig config_;
  const Clock* clock_;
  LumaExtractor luma_;
  SharpnessScorer sharpness_;
  std::unique_ptr<OverlapEstimator> overlap_;
  DownScaler scaler_;  // luma -> analysis image
  bool haveKeyframe_ = false;
  int keyframeFeatures_ = 0;  // features of the frame kept last (keepCurrent)
  // Geometric mode: a frame was tracked against the last keyframe since it was kept.
  // A keyframe lost at once, never tracked, may be a scene nothing can be tracked in
  // (glinting water, noise at dusk, a garbled frame): the next chain then starts only
  // at a frame tracked from the one before it (needAnchor_), not at every sharp frame.
  bool chainTracked_ = false;
  bool needAnchor_ = false;
  // The last keyframe is the stream's first and was judged sharp only against the
  // blur floor (Reason::Refocus); its score.
  bool firstInWarmup_ = false;
  double firstSharpness_ = 0.0;
  bool warmingUp_ = false;  // the frame being decided was judged in the warm-up
  std::int64_t keyframes_ = 0;
  std::int64_t keyframesSinceScorer_ = 0;  // since the blur statistic began (reconfigure)
  std::int64_t candidateIndex_ = -1;
  double candidateSharpness_ = 0.0;
  double candidateRank_ = 0.0;   // its sharpness (paper mode: its distance), among its grade
  int candidateGrade_ = 0;       // 2 sharp, 1 sharp but moved fast, 0 blurry (noteCandidate)
  bool candidateSharp_ = false;  // grade > 0: fallen back on at the band's low edge
  RunningQuantile motion_;       // recent frame motions (analysis px)
  std::atomic<int> captureRequests_{0};  // requestCapture() may come from another thread
  std::int64_t captureWaitFromNs_ = -1;  // first frame seen with a request pending
};

}  // namespace keyframed
