#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>

#include "capture/frame_source.h"
#include "capture/interrupter.h"
#include "core/selector.h"

namespace keyframed {

// The selector's stage clock on CLOCK_MONOTONIC (what frames and telemetry use).
class MonotonicClock final : public Clock {
 public:
  [[nodiscard]] std::int64_t nowNs() const override;
};

// A video file played as a camera would deliver it (`realtime`): at its own frame
// rate, each frame stamped with the CLOCK_MONOTONIC time it is due (as a camera
// stamps a frame when it captures it, however late it is read), the clock live
// telemetry is mapped to, or, given `startUnixNs` (a recorded flight replayed with
// its tlog), with its container time shifted by that: the tlog's unix times.
// Otherwise as fast as it decodes, with container times shifted by `startUnixNs`
// when given. Shared by
// `select --realtime` and the daemon's file source. The decoding's CPU time is
// counted apart: a camera delivers frames decoded.
class PacedSource final : public FrameSource {
 public:
  PacedSource(std::unique_ptr<FrameSource> inner, bool realtime,
              std::optional<std::int64_t> startUnixNs);
  [[nodiscard]] const SourceInfo& info() const override { return inner_->info(); }
  ReadStatus next(Frame& frame, std::string& error) override;
  [[nodiscard]] bool failed() const override { return inner_->failed(); }
  [[nodiscard]] TimestampOrigin timestampOrigin() const override {
    return inner_->timestampOrigin();
  }
  // Also ends a wait for a frame's presentation time.
  void interrupt() override {
    interrupter_.raise();
    inner_->interrupt();
  }
  [[nodiscard]] double decodeCpuSeconds() const {
    return static_cast<double>(decodeCpuNs_.load()) / 1e9;
  }

 private:
  std::unique_ptr<FrameSource> inner_;
  bool realtime_;
  std::optional<std::int64_t> startUnixNs_;
  std::int64_t startNs_ = -1;
  std::int64_t lastDueNs_ = -1;  // when the last frame was due (realtime)
  // A jump in the timestamps larger than this restarts the pacing.
  static constexpr std::int64_t kMaxGapNs = 2'000'000'000;
  std::atomic<std::int64_t> decodeCpuNs_{0};
  Interrupter interrupter_;
};

}  // namespace keyframed
