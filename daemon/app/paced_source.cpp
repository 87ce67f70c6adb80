#include "app/paced_source.h"

#include <time.h>

#include <algorithm>
#include <chrono>

#include "telemetry/link.h"

namespace keyframed {

namespace {
std::int64_t threadCpuNs() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000LL + ts.tv_nsec;
}
}  // namespace

std::int64_t MonotonicClock::nowNs() const {
  return monotonicNowNs();
}

PacedSource::PacedSource(std::unique_ptr<FrameSource> inner, bool realtime,
                         std::optional<std::int64_t> startUnixNs)
    : inner_(std::move(inner)), realtime_(realtime), startUnixNs_(startUnixNs) {}

ReadStatus PacedSource::next(Frame& frame, std::string& error) {
  const std::int64_t cpu0 = threadCpuNs();
  const ReadStatus st = inner_->next(frame, error);
  decodeCpuNs_.fetch_add(threadCpuNs() - cpu0);
  if (st != ReadStatus::Frame) return st;
  if (realtime_) {
    // The frame exists at its presentation time, counted from the first frame.
    const std::int64_t containerNs = frame.timestampNs;
    if (startNs_ < 0) startNs_ = monotonicNowNs() - frame.timestampNs;
    std::int64_t due = startNs_ + frame.timestampNs;
    const std::int64_t now = monotonicNowNs();
    // A jump in the timestamps (files joined, a recorder's pause, an MPEG-TS clock
    // reset) is neither waited out as dead air nor raced through: a camera would have
    // gone on delivering. The pacing restarts at this frame, one frame period on.
    const std::int64_t period =
        inner_->info().fps > 0.0 ? static_cast<std::int64_t>(1e9 / inner_->info().fps) : 33'333'333;
    // A step back of any size is one too (an MPEG-TS's half-second step back, a
    // repeated timestamp): frame times never go backwards, as a camera's do not.
    if (lastDueNs_ >= 0 && (due > std::max(now, lastDueNs_) + kMaxGapNs || due <= lastDueNs_)) {
      due = std::max(now, lastDueNs_ + period);
      startNs_ = due - frame.timestampNs;
    }
    lastDueNs_ = due;
    // A file's timestamps may jump (a gap, variable frame rate): stopping must not wait.
    const auto wait =
        std::chrono::ceil<std::chrono::milliseconds>(std::chrono::nanoseconds(due - now));
    if (due > now && interrupter_.wait(-1, 0, wait).wake == Interrupter::Wake::Interrupted) {
      error = "interrupted: waiting for a frame's time";
      return ReadStatus::Error;
    }
    // A camera stamps on CLOCK_MONOTONIC when it captures, not when the frame is read:
    // the time it was due, also when this thread came late (a busy machine, a slow
    // decode), so that frame times keep the video's rhythm. A recorded flight keeps
    // its own clock.
    frame.timestampNs = startUnixNs_ ? *startUnixNs_ + containerNs : due;
  } else if (startUnixNs_) {
    frame.timestampNs += *startUnixNs_;
  }
  return st;
}

}  // namespace keyframed
