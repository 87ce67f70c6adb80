#include "core/selector.h"

#include <algorithm>
#include <cmath>

namespace keyframed {

const char* toString(Reason reason) {
  switch (reason) {
    case Reason::First: return "first";
    case Reason::OverlapTarget: return "overlap_target";
    case Reason::PaperDistance: return "paper_distance";
    case Reason::GapFill: return "gap_fill";
    case Reason::Blurry: return "blurry";
    case Reason::Redundant: return "redundant";
    case Reason::Lost: return "lost";
    case Reason::Featureless: return "featureless";
    case Reason::Commanded: return "commanded";
    case Reason::Refocus: return "refocus";
  }
  return "unknown";
}

std::string SelectorConfig::validate() const {
  if (auto e = blur.validate(); !e.empty()) return e;
  if (auto e = overlap.validate(); !e.empty()) return e;
  if (!(target > 0.0 && target < 1.0)) return "overlap target must be in (0, 1)";
  if (!(bandLow > 0.0 && bandLow <= target)) return "overlap band low must be in (0, target]";
  if (!(bandHigh >= target && bandHigh < 1.0)) return "overlap band high must be in [target, 1)";
  if (!(motionRatio == 0.0 || motionRatio >= 1.0)) return "motion ratio must be 0 (off) or >= 1";
  // Not 0: a hover's sub-pixel jitter would become the reference every cruise is
  // judged fast against.
  if (!(motionMinFraction > 0.0 && motionMinFraction < 1.0))
    return "motion minimum fraction must be in (0, 1)";
  if (motionWindow < 5 || motionWindow > 10000) return "motion window must be 5..10000 frames";
  if (!(minOverlap > 0.0 && minOverlap <= bandLow))
    return "minimum overlap must be in (0, band low]";
  if (analysisWidth < 0 || (analysisWidth > 0 && analysisWidth < 64))
    return "analysis width must be 0 (full) or >= 64";
  if (captureWaitMs < 0 || captureWaitMs > 60000) return "capture wait must be 0..60000 ms";
  return {};
}

KeyframeSelector::KeyframeSelector(const SelectorConfig& config, const Clock* clock)
    : config_(config),
      clock_(clock),
      sharpness_(config.blur),
      overlap_(OverlapEstimator::create(config.overlap)),
      motion_(static_cast<std::size_t>(std::max(1, config.motionWindow))) {}

bool KeyframeSelector::motionTooFast(double motionPx, int analysisWidth) {
  if (std::isnan(motionPx)) return false;  // unknown (no tracking, paper mode)
  // The lower quartile, not the median: a long manoeuvre must not raise the
  // reference it is judged against.
  const double floorPx = config_.motionMinFraction * analysisWidth;
  const bool fast = config_.motionRatio > 0.0 && motion_.size() >= 5 &&
                    motionPx > config_.motionRatio * motion_.quantile(0.25) && motionPx > floorPx;
  // Only frames that move count towards the reference: after a hover, the cruise
  // that follows is judged against the cruise before it, not against standing still.
  if (std::isfinite(motionPx) && motionPx >= 0.25 * floorPx) motion_.push(motionPx);
  return fast;
}

bool KeyframeSelector::reconfigureRestartsChain(const SelectorConfig& config) const {
  return !(config.overlap == config_.overlap && config.analysisWidth == config_.analysisWidth);
}

void KeyframeSelector::reconfigure(const SelectorConfig& config) {
  const bool restart = reconfigureRestartsChain(config);
  const SelectorConfig before = config_;
  config_ = config;
  // What the new settings leave as it was carries on: the blur statistic (a fresh one
  // judges against the floor alone for its warm-up, where a blurred frame can start
  // a chain), the motion reference, and the chain with its reference and candidate
  // (a new target or band applies to the frames that follow).
  if (!(config.blur == before.blur)) {
    sharpness_ = SharpnessScorer(config.blur);
    keyframesSinceScorer_ = 0;
  }
  if (config.motionWindow != before.motionWindow) {
    motion_ = RunningQuantile(static_cast<std::size_t>(std::max(1, config.motionWindow)));
  }
  if (!restart) return;
  // A new estimator has no reference: the next sharp frame starts a new chain.
  overlap_ = OverlapEstimator::create(config.overlap);
  haveKeyframe_ = false;
  needAnchor_ = false;
  firstInWarmup_ = false;
  clearCandidate();
}

bool KeyframeSelector::requestCapture() {
  int n = captureRequests_.load();
  do {
    if (n >= kMaxCaptureRequests) return false;
  } while (!captureRequests_.compare_exchange_weak(n, n + 1));
  return true;
}

void KeyframeSelector::clearCandidate() {
  candidateIndex_ = -1;
  candidateSharpness_ = 0.0;
  candidateRank_ = 0.0;
  candidateGrade_ = 0;
  candidateSharp_ = false;
}

void KeyframeSelector::keepCurrent(Decision& d, Reason reason) {
  d.kept = true;
  d.reason = reason;
  d.candidate = false;
  overlap_->setReferenceToCurrent();
  haveKeyframe_ = true;
  keyframeFeatures_ = d.features;
  chainTracked_ = false;
  needAnchor_ = false;
  firstInWarmup_ = reason == Reason::First && keyframesSinceScorer_ == 0 && warmingUp_;
  firstSharpness_ = d.sharpness;
  clearCandidate();
  ++keyframes_;
  ++keyframesSinceScorer_;
}

int KeyframeSelector::minTrackable() const {
  return config_.overlap.mode == OverlapMode::Paper ? config_.overlap.paperMinMatches
                                                    : config_.overlap.minInliers;
}

void KeyframeSelector::noteCandidate(Decision& d) {
  // The fallback: a sharp frame beats a blurry one, then the higher score wins.
  // Scores are compared among neighbours rather than against the threshold, which a
  // drop in ground texture can leave out of reach.
  // A frame that measures sharp but moved fast (motion gate) ranks between: not kept
  // at the target, but good enough to fall back on at the band's edge, so that a
  // speed-up the gate has not adapted to yet does not push keyframes under the band.
  // In paper mode, of frames equally sharp by grade, the one with the most distance
  // from the keyframe: every frame under t is offered, from the keyframe's next one
  // on, and the sharpest of them could be a near copy of the keyframe, which would
  // close no gap.
  const int grade =
      d.sharp ? 2 : (d.fastMotion && d.sharpness >= d.threshold && d.sharpness > 0.0 ? 1 : 0);
  const bool paper = config_.overlap.mode == OverlapMode::Paper;
  const double rank = paper ? d.paperDistance : d.sharpness;
  const bool better = candidateIndex_ < 0 || grade > candidateGrade_ ||
                      (grade == candidateGrade_ && rank > candidateRank_);
  // (a uniform frame, score 0, is no candidate even with a floor of 0)
  if (d.sharpness < config_.blur.floor || !(d.sharpness > 0.0) || !better) return;
  candidateIndex_ = d.index;
  candidateSharpness_ = d.sharpness;
  candidateRank_ = rank;
  candidateGrade_ = grade;
  candidateSharp_ = grade > 0;
  d.candidate = true;
  overlap_->markCandidate();
}

void KeyframeSelector::fallBackToCandidate(Decision& d) {
  promoteCandidate(d);
  // The candidate is the reference now: this frame's overlap is measured against it.
  const OverlapResult again = overlap_->setReferenceToCandidate();
  d.overlap = again.overlap;
  d.paperDistance = again.paperDistance;
  d.tracking = again.valid;
  if (!again.valid) {
    haveKeyframe_ = false;
    overlap_->reset();
  }
}

bool KeyframeSelector::promoteCandidate(Decision& d) {
  if (candidateIndex_ < 0) return false;
  d.promotedIndex = candidateIndex_;
  clearCandidate();
  ++keyframes_;
  ++keyframesSinceScorer_;
  // A keyframe after the first: the view that one showed is no longer the reference
  // a refocused frame would replace.
  firstInWarmup_ = false;
  return true;
}

bool KeyframeSelector::candidateAcceptable() const {
  // Geometric mode falls back on a blurry frame only at the band's hard floor, where
  // coverage would otherwise break; at a loss or the end the overlap there is unknown,
  // and a blurred frame between two views adds little but trouble for matching. Paper
  // mode, which has no floor, keeps the best frame there was.
  return candidateSharp_ || config_.overlap.mode == OverlapMode::Paper;
}

std::int64_t KeyframeSelector::finish() {
  Decision d;
  if (!candidateAcceptable() || !promoteCandidate(d)) return -1;
  haveKeyframe_ = false;
  overlap_->reset();
  return d.promotedIndex;
}

void KeyframeSelector::serveCaptureRequest(Decision& d) {
  // (A clock that went back, a source restarted: the wait starts again from here.)
  if (captureWaitFromNs_ < 0 || d.timestampNs < captureWaitFromNs_)
    captureWaitFromNs_ = d.timestampNs;
  const bool waited =
      d.timestampNs - captureWaitFromNs_ >= std::int64_t{config_.captureWaitMs} * 1'000'000;
  if (!d.kept && (d.sharp || (waited && d.sharpness >= config_.blur.floor && d.sharpness > 0.0))) {
    // Whatever state the decision above left (a new chain, a promoted candidate, a
    // featureless scene), this frame becomes the reference, as any keyframe does.
    keepCurrent(d, Reason::Commanded);
  }
  if (!d.kept) return;
  --captureRequests_;
  captureWaitFromNs_ = -1;
}

Decision KeyframeSelector::process(const Frame& frame) {
  Decision d;
  d.index = frame.index;
  d.timestampNs = frame.timestampNs;
  const std::int64_t t0 = now();

  const GrayView gray = luma_.luma(frame);
  const std::int64_t t1 = now();

  warmingUp_ = sharpness_.warmingUp();
  const SharpnessScorer::Result blur = sharpness_.evaluate(gray);
  d.sharpness = blur.score;
  d.threshold = blur.threshold;
  d.sharp = blur.sharp;
  const std::int64_t t2 = now();

  // Halve (2x2 average) while that stays above the target, then one bilinear step:
  // 1920 -> 640 in a fraction of a direct INTER_AREA resize by 3, and no allocation
  // once the sizes are known.
  const GrayView analysis = scaler_.scaleToWidth(gray, config_.analysisWidth);
  const std::int64_t t3 = now();

  OverlapResult ov = overlap_->observe(analysis);
  d.features = ov.features;
  d.matches = ov.matches;
  d.inliers = ov.inliers;
  d.tracking = ov.valid;
  d.overlap = ov.overlap;
  d.paperDistance = ov.paperDistance;
  d.motionPx = ov.motionPx;
  if (motionTooFast(ov.motionPx, analysis.width)) {
    d.fastMotion = true;
    d.sharp = false;
  }

  const bool paper = config_.overlap.mode == OverlapMode::Paper;
  if (ov.valid) chainTracked_ = true;
  // Tracked from the frame before it (geometric mode; paper mode matches against the
  // keyframe alone and has no such test).
  const bool anchored = paper || std::isfinite(ov.motionPx);
  if (!haveKeyframe_) {
    if (d.sharp && (!needAnchor_ || anchored))
      keepCurrent(d, Reason::First);
    else
      d.reason = d.sharp ? Reason::Lost : Reason::Blurry;
  } else if (!ov.valid && keyframeFeatures_ < minTrackable()) {
    // The keyframe had nothing to track: there was no chain to lose. A new chain
    // starts at the first sharp frame with texture enough; until then each frame
    // would be another keyframe of the same blank scene, at the full frame rate.
    if (d.sharp && d.features >= minTrackable()) {
      overlap_->reset();
      keepCurrent(d, Reason::First);
    } else {
      d.reason = d.sharp ? Reason::Featureless : Reason::Blurry;
    }
  } else if (!ov.valid) {
    // Tracking lost: keep the best frame seen since the last keyframe so that no
    // gap opens (a sharp one: candidateAcceptable), then start a new chain at the
    // next sharp frame.
    if (candidateAcceptable()) promoteCandidate(d);
    clearCandidate();
    haveKeyframe_ = false;
    overlap_->reset();
    // A keyframe lost before any frame was tracked against it: the scene may not be
    // trackable at all, and each sharp frame would become one more "first".
    needAnchor_ = !paper && !chainTracked_;
    if (d.sharp && (!needAnchor_ || anchored))
      keepCurrent(d, Reason::First);
    else
      d.reason = Reason::Lost;
  } else if (firstInWarmup_ && d.sharp && d.sharpness >= kRefocusRatio * firstSharpness_ &&
             (paper ? ov.paperDistance < config_.overlap.paperThreshold
                    : ov.overlap > config_.bandHigh)) {
    // The view the first keyframe shows, now in focus: it becomes the reference (and
    // a keyframe: the one before cannot be taken back).
    keepCurrent(d, Reason::Refocus);
  } else if (paper) {
    const bool reached = ov.paperDistance >= config_.overlap.paperThreshold;
    if (d.sharp && reached) {
      keepCurrent(d, Reason::PaperDistance);
    } else if (reached) {
      // t reached on a blurred frame: the paper's rule would wait for the next sharp
      // one, however far on (a blurred turn, a gap). A sharp frame seen before it,
      // under t, is kept instead; with none, the wait goes on (and a loss of the
      // matches falls back to the best frame there was, above).
      d.reason = Reason::Blurry;
      if (candidateSharp_) fallBackToCandidate(d);
    } else {
      d.reason = d.sharp ? Reason::Redundant : Reason::Blurry;
      noteCandidate(d);
    }
  } else {
    const double o = ov.overlap;
    if (d.sharp && o <= config_.target) {
      keepCurrent(d, Reason::OverlapTarget);
    } else if (o < config_.bandLow && (candidateSharp_ || o < config_.minOverlap)) {
      // About to leave the band with no sharp frame at the target: fall back to
      // the best frame in the band since the last keyframe. A blurry fallback is
      // taken only at the hard floor (minOverlap): until then a sharp frame may
      // still come, e.g. when a yaw turn blurs a few frames and ends.
      d.reason = Reason::Blurry;  // a sharp frame here was kept by the branch above
      if (candidateIndex_ >= 0) {
        fallBackToCandidate(d);
      } else if (d.sharpness >= config_.blur.floor) {
        // Nothing in the band to fall back on: this frame is the last one that
        // still overlaps by the floor. Waiting longer would open a gap.
        keepCurrent(d, Reason::GapFill);
      }
    } else {
      d.reason = d.sharp ? Reason::Redundant : Reason::Blurry;
      if (o <= config_.bandHigh && o >= config_.minOverlap) noteCandidate(d);
    }
  }

  if (captureRequests_.load() > 0) serveCaptureRequest(d);

  const std::int64_t t4 = now();
  d.times.lumaNs = t1 - t0;
  d.times.blurNs = t2 - t1;
  d.times.resizeNs = t3 - t2;
  d.times.overlapNs = t4 - t3;
  d.times.totalNs = t4 - t0;
  return d;
}

}  // namespace keyframed
