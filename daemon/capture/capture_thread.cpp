#include "capture/capture_thread.h"

#include <algorithm>
#include <cctype>
#include <cstdio>
#include <exception>
#include <string>

#include "app/log.h"
#include "app/log_throttle.h"
#include "core/thread_name.h"

namespace keyframed {

namespace {

using SteadyClock = std::chrono::steady_clock;

// A message without its numbers ("reopen attempt 7 failed" and "... 8 failed" are one kind).
std::string kindOf(const std::string& message) {
  std::string k;
  k.reserve(message.size());
  for (const char c : message) {
    if (std::isdigit(static_cast<unsigned char>(c)) == 0) k += c;
  }
  return k;
}

// Says what goes wrong with a source without flooding the log: an outage's first
// error at once, a new kind of error at most once a second, the same kind at most
// every 10 s with the number left unsaid; and when frames come back.
class ErrorLog {
 public:
  // `source`: the source's description, to tell when it comes back as another.
  void error(const std::string& message, const std::string& source) {
    const auto now = SteadyClock::now();
    if (errors_ == 0) {
      outageStart_ = now;
      outageSource_ = source;
    }
    ++errors_;
    const std::int64_t nowNs =
        std::chrono::duration_cast<std::chrono::nanoseconds>(now.time_since_epoch()).count();
    if (const auto held = throttle_.pass(kindOf(message), nowNs)) {
      KF_LOG(Capture, Warning) << message
                               << (*held > 0 ? " (" + std::to_string(*held) +
                                                   " more capture errors since the last line)"
                                             : std::string());
    }
  }
  void frame(const std::string& source) {
    if (errors_ == 0) return;
    char took[32];
    std::snprintf(took, sizeof took, "%.1f s",
                  std::chrono::duration<double>(SteadyClock::now() - outageStart_).count());
    // A camera found again on another node (a USB camera re-enumerated) says where.
    KF_LOG(Capture, Notice) << "capture recovered after " << errors_ << " error"
                            << (errors_ == 1 ? "" : "s") << " in " << took
                            << (source != outageSource_ ? "; now " + source : std::string());
    errors_ = 0;
    throttle_.reset();
  }

 private:
  std::uint64_t errors_ = 0;  // in the current outage
  SteadyClock::time_point outageStart_{};
  std::string outageSource_;
  LogThrottle throttle_{10'000'000'000, 1'000'000'000};
};

}  // namespace

CaptureThread::CaptureThread(FrameSource& source, FramePool& pool, FrameQueue& queue,
                             int maxConsecutiveErrors)
    : source_(source), pool_(pool), queue_(queue), maxConsecutiveErrors_(maxConsecutiveErrors) {}

CaptureThread::~CaptureThread() {
  stop();
}

void CaptureThread::start(std::int64_t discardBeforeNs) {
  if (thread_.joinable()) return;
  discardBeforeNs_ = discardBeforeNs;
  stop_ = false;
  {
    std::lock_guard lock(stopMutex_);
    finished_ = false;
  }
  running_ = true;
  thread_ = std::thread([this] {
    nameThisThread("kf-capture");
    run();
  });
}

void CaptureThread::requestStop() {
  {
    std::lock_guard lock(stopMutex_);
    stop_ = true;
  }
  stopped_.notify_all();
  // A camera waiting for a frame gives up now, not at its timeout.
  if (thread_.joinable()) source_.interrupt();
}

void CaptureThread::stop() {
  requestStop();
  if (thread_.joinable()) thread_.join();
  running_ = false;
}

bool CaptureThread::stopWithin(std::chrono::milliseconds wait) {
  requestStop();
  if (thread_.joinable()) {
    std::unique_lock lock(stopMutex_);
    if (!stopped_.wait_for(lock, wait, [this] { return finished_; })) return false;
    lock.unlock();
    thread_.join();
  }
  running_ = false;
  return true;
}

bool CaptureThread::pause(std::chrono::nanoseconds d) {
  std::unique_lock lock(stopMutex_);
  return !stopped_.wait_for(lock, d, [this] { return stop_.load(); });
}

CaptureThread::Stats CaptureThread::stats() const {
  std::lock_guard lock(mutex_);
  return stats_;
}

std::string CaptureThread::lastError() const {
  std::lock_guard lock(mutex_);
  return lastError_;
}

void CaptureThread::run() {
  // A source or a copy that throws (out of memory, a decoder's exception) ends the
  // capture like a permanent error: the owner reports it and flushes, nothing aborts.
  try {
    loop();
  } catch (const std::exception& e) {
    std::lock_guard lock(mutex_);
    lastError_ = std::string("capture failed: ") + e.what();
  }
  queue_.close();
  running_ = false;
  {
    std::lock_guard lock(stopMutex_);
    finished_ = true;
  }
  stopped_.notify_all();
}

void CaptureThread::loop() {
  int consecutiveErrors = 0;
  std::chrono::nanoseconds backoff = kFirstBackoff;
  ErrorLog log;
  std::string error;
  bool fresh = discardBeforeNs_ == std::numeric_limits<std::int64_t>::min();
  if (!fresh) {
    // What the device filled before the start goes back unread: the timestamp test
    // below cannot tell it from now where the camera stamps a frame as it is read.
    const std::uint64_t waiting = source_.discardQueued();
    std::lock_guard lock(mutex_);
    stats_.stale += waiting;
  }
  while (!stop_) {
    Frame frame;
    const auto called = SteadyClock::now();
    const ReadStatus status = source_.next(frame, error);
    if (stop_) break;  // stopped while reading: an interrupted read is no capture error
    if (status == ReadStatus::End) {
      ended_ = true;
      break;
    }
    if (status == ReadStatus::Error) {
      ++consecutiveErrors;
      {
        std::lock_guard lock(mutex_);
        ++stats_.errors;
        lastError_ = error;
      }
      // A permanent error is the owner's to report (lastError()): it ends the run.
      if (source_.failed()) break;
      if (maxConsecutiveErrors_ > 0 && consecutiveErrors >= maxConsecutiveErrors_) break;
      log.error(error, source_.info().description);
      // A read that failed slowly (a poll timeout) has waited already.
      const auto waited = SteadyClock::now() - called;
      if (waited < backoff && !pause(backoff - waited)) break;
      backoff = std::min<std::chrono::nanoseconds>(backoff * 2, kMaxBackoff);
      continue;
    }
    consecutiveErrors = 0;
    backoff = kFirstBackoff;
    log.frame(source_.info().description);
    if (!fresh) {
      // Only until the first fresh frame: later timestamps are the stream's own.
      std::lock_guard lock(mutex_);
      if (frame.timestampNs < discardBeforeNs_ && stats_.stale < kMaxStaleFrames) {
        ++stats_.stale;
        continue;
      }
      // More than a camera's buffers can hold: not frames from before the start but a
      // clock that lags this one (a loopback device fed presentation times, a driver
      // stamping from its own counter). Thrown away for ever, they would keep the
      // daemon from ever starting: kept, and said.
      if (frame.timestampNs < discardBeforeNs_) {
        KF_LOG(Capture, Warning)
            << "the camera's timestamps lie " << (discardBeforeNs_ - frame.timestampNs) / 1'000'000
            << " ms behind the start of the capture after " << stats_.stale
            << " frames: its clock is not this machine's monotonic clock; the frames are kept";
      }
      fresh = true;
      stats_.lostBeforeStart = source_.lostFrames();
    }
    FramePtr buffer = pool_.acquire();
    {
      std::lock_guard lock(mutex_);
      ++stats_.captured;
      if (!buffer) ++stats_.noBuffer;
    }
    if (!buffer) continue;  // consumers hold every buffer: drop this frame, keep going
    copyFrame(frame, *buffer);
    queue_.push(std::move(buffer));
  }
}

}  // namespace keyframed
