#include "capture/capture_thread.h"

namespace keyframed {

CaptureThread::CaptureThread(FrameSource& source, FramePool& pool, FrameQueue& queue,
                             int maxConsecutiveErrors)
    : source_(source), pool_(pool), queue_(queue), maxConsecutiveErrors_(maxConsecutiveErrors) {}

CaptureThread::~CaptureThread() {
  stop();
}

void CaptureThread::start() {
  if (thread_.joinable()) return;
  stop_ = false;
  running_ = true;
  thread_ = std::thread([this] { run(); });
}

void CaptureThread::stop() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
  running_ = false;
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
  int consecutiveErrors = 0;
  std::string error;
  while (!stop_) {
    Frame frame;
    const ReadStatus status = source_.next(frame, error);
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
      if (maxConsecutiveErrors_ > 0 && consecutiveErrors >= maxConsecutiveErrors_) break;
      continue;
    }
    consecutiveErrors = 0;
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
  queue_.close();
  running_ = false;
}

}  // namespace keyframed
