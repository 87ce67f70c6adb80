#include "app/keyframe_stage.h"

#include <memory>
#include <utility>

namespace keyframed {

namespace {
// Keyframe copies in flight between analysis and output; more are allocated if a
// slow disk holds them longer (a keyframe is never dropped).
constexpr std::size_t kKeyframeBuffers = 6;
}  // namespace

KeyframeStage::KeyframeStage(const SelectorConfig& config, const Clock* clock, Emit emit)
    : selector_(config, clock), clock_(clock), emit_(std::move(emit)), pool_(kKeyframeBuffers) {}

FramePtr KeyframeStage::copyOf(const Frame& frame) {
  FramePtr p = pool_.acquire();
  if (!p) p = std::make_shared<FrameBuffer>();
  copyFrame(frame, *p);
  return p;
}

void KeyframeStage::process(const Frame& frame) {
  ++counts_.framesRead;
  KeyframeEvent ev;
  ev.decision = selector_.process(frame);
  const Decision& d = ev.decision;
  if (clock_ != nullptr && (d.kept || d.promotedIndex >= 0)) ev.decidedNs = clock_->nowNs();
  counts_.analysisNs += static_cast<double>(d.times.totalNs);
  // Each frame is counted once by its decision; a candidate promoted later moves
  // from its rejection counter to the kept one.
  if (d.promotedIndex >= 0) {
    if (d.promotedIndex == candidateIndex_) {
      ev.promoted = copyOf(candidate_.frame);
    }
    ++counts_.kept;
    ++counts_.promoted;
    --(candidateBlur_ ? counts_.rejectedBlur : counts_.rejectedOverlap);
    candidateIndex_ = -1;
  }
  // Featureless frames count with the redundant ones: nothing new to measure. A frame
  // dropped while tracking is lost counts as blurred only when it is: a sharp one was
  // turned down by the overlap stage (no chain to measure it against yet).
  const bool blur = d.reason == Reason::Blurry || (d.reason == Reason::Lost && !d.sharp);
  if (d.kept) {
    ev.keyframe = copyOf(frame);
    ++counts_.kept;
    candidateIndex_ = -1;
  } else {
    ++(blur ? counts_.rejectedBlur : counts_.rejectedOverlap);
    if (d.candidate) {
      copyFrame(frame, candidate_);
      candidateIndex_ = d.index;
      candidateBlur_ = blur;
    }
  }
  emit_(std::move(ev));
}

void KeyframeStage::finish() {
  const std::int64_t last = selector_.finish();
  if (last >= 0 && last == candidateIndex_) {
    KeyframeEvent ev;
    ev.endOfStream = true;
    if (clock_ != nullptr) ev.decidedNs = clock_->nowNs();
    ev.promoted = copyOf(candidate_.frame);
    ++counts_.kept;
    ++counts_.promoted;
    --(candidateBlur_ ? counts_.rejectedBlur : counts_.rejectedOverlap);
    candidateIndex_ = -1;
    emit_(std::move(ev));
  }
}

void KeyframeStage::reconfigure(const SelectorConfig& config) {
  // A new chain: the candidate of the old one is kept first, as at the end of a run.
  if (selector_.reconfigureRestartsChain(config)) finish();
  selector_.reconfigure(config);
}

}  // namespace keyframed
