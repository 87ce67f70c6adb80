#include "app/paced_source.h"

#include <time.h>

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
    const std::int64_t due = startNs_ + frame.timestampNs;
    const std::int64_t now = monotonicNowNs();
    // A file's timestamps may jump (a gap, variable frame rate): stopping must not wait.
    const auto wait =
        std::chrono::ceil<std::chrono::milliseconds>(std::chrono::nanoseconds(due - now));
    if (due > now && interrupter_.wait(-1, 0, wait).wake == Interrupter::Wake::Interrupted) {
      error = "interrupted: waiting for a frame's time";
      return ReadStatus::Error;
    }
    // A camera stamps on CLOCK_MONOTONIC; a recorded flight keeps its own clock.
    frame.timestampNs = startUnixNs_ ? *startUnixNs_ + containerNs : monotonicNowNs();
  } else if (startUnixNs_) {
    frame.timestampNs += *startUnixNs_;
  }
  return st;
}

}  // namespace keyframed
