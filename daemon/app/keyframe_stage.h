#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <string>

#include "capture/frame_queue.h"
#include "core/capture_answer.h"
#include "core/selector.h"

namespace keyframed {

// What the analysis hands to the output for one frame (or at the end of the
// stream): the decision, and the pixels of whatever became a keyframe with it.
struct KeyframeEvent {
  Decision decision;
  FramePtr keyframe;           // decision.kept: this frame's pixels (owned copy)
  FramePtr promoted;           // a candidate promoted to keyframe with this decision (gap fill)
  bool endOfStream = false;    // the selector's finish(): only `promoted` is meaningful
  std::int64_t decidedNs = 0;  // with a keyframe: the clock's time at the decision (0: no clock)
};

struct StageCounts {
  std::int64_t framesRead = 0;
  std::int64_t kept = 0;
  std::int64_t rejectedBlur = 0;     // Reason::Blurry, or Lost and not sharp; never promoted
  std::int64_t rejectedOverlap = 0;  // Reason::Redundant, never promoted
  std::int64_t promoted = 0;         // kept later as gap fills (included in kept)
  double analysisNs = 0.0;           // selector time, summed
};

// The analysis end of the data path, shared by `keyframed select` (called inline)
// and `keyframed run` (on the analysis thread): runs the selector on each frame,
// keeps a copy of the fallback candidate so that a later gap fill still has its
// pixels, counts, and emits one KeyframeEvent per frame. No I/O.
class KeyframeStage {
 public:
  using Emit = std::function<void(KeyframeEvent&&)>;

  KeyframeStage(const SelectorConfig& config, const Clock* clock, Emit emit);

  void process(const Frame& frame);
  // End of the stream: the pending candidate becomes a keyframe (emitted with
  // endOfStream) so the last stretch is covered too.
  void finish();
  // New settings (SIGHUP). When they start a new chain (KeyframeSelector::reconfigure)
  // the pending candidate is kept first, as at the end of a stream, so changing
  // settings never opens a coverage gap; otherwise the chain goes on.
  void reconfigure(const SelectorConfig& config);
  [[nodiscard]] bool restartsChain(const SelectorConfig& config) const {
    return selector_.reconfigureRestartsChain(config);
  }
  // A capture asked for (MAVLink): see KeyframeSelector::requestCapture().
  bool requestCapture() { return selector_.requestCapture(); }
  [[nodiscard]] int pendingCaptures() const { return selector_.pendingCaptures(); }

  [[nodiscard]] const StageCounts& counts() const { return counts_; }
  [[nodiscard]] const SelectorConfig& config() const { return selector_.config(); }

 private:
  FramePtr copyOf(const Frame& frame);

  KeyframeSelector selector_;
  const Clock* clock_;
  Emit emit_;
  StageCounts counts_;
  FramePool pool_;         // keyframe copies on their way to the output
  FrameBuffer candidate_;  // the fallback candidate's pixels (storage reused)
  std::int64_t candidateIndex_ = -1;
  bool candidateBlur_ = false;  // the candidate was counted as rejected for blur
};

// Captures asked for over MAVLink (MAV_CMD_IMAGE_START_CAPTURE), on the telemetry
// thread, on their way to the stage on the analysis thread. One limit holds for
// those on their way and those waiting in the selector, so that a request is refused
// (TEMPORARILY_REJECTED) rather than acknowledged and then dropped.
class CaptureRequests {
 public:
  // One more: Busy when KeyframeSelector::kMaxCaptureRequests wait already or, with
  // onlyIfIdle (an interval capture's tick), when any waits (a source that yields no
  // usable frame for a while must not make a burst of near-identical ones after);
  // Ended once close() was called.
  CaptureAnswer add(bool onlyIfIdle = false) {
    int n = n_.load();
    do {
      if (n < 0) return CaptureAnswer::Ended;
      const int waiting = n + staged_.load();
      if (waiting >= KeyframeSelector::kMaxCaptureRequests || (onlyIfIdle && waiting > 0))
        return CaptureAnswer::Busy;
    } while (!n_.compare_exchange_weak(n, n + 1));
    return CaptureAnswer::Taken;
  }
  // Hands the waiting ones to the stage, before its next frame; returns how many it
  // refused (only in the moment between the two counts; logged by the caller).
  int drainInto(KeyframeStage& stage) {
    int n = n_.load();
    do {
      if (n <= 0) break;
    } while (!n_.compare_exchange_weak(n, 0));
    int refused = 0;
    for (; n > 0; --n) refused += stage.requestCapture() ? 0 : 1;
    noteServed(stage);
    return refused;
  }
  // After each frame: how many still wait in the selector.
  void noteServed(const KeyframeStage& stage) { staged_.store(stage.pendingCaptures()); }
  // The source has ended (after the stage's finish()): every capture asked for from
  // now on is Ended, and those taken but never served (no usable frame came after
  // them) are returned, for the caller to say so.
  int close(const KeyframeStage& stage) {
    const int onTheirWay = n_.exchange(kClosed);
    staged_.store(0);
    return (onTheirWay > 0 ? onTheirWay : 0) + stage.pendingCaptures();
  }

 private:
  static constexpr int kClosed = -1;
  std::atomic<int> n_{0};       // asked for, not yet handed to the stage; kClosed: ended
  std::atomic<int> staged_{0};  // waiting in the selector
};

}  // namespace keyframed
