#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "capture/frame_queue.h"
#include "capture/frame_source.h"

namespace keyframed {

// The capture end of the data path: one thread that reads a FrameSource,
// copies each frame into a pooled buffer and pushes it into a bounded queue
// that drops the oldest frame when the analysis falls behind. It never waits
// for the consumer. On End or a permanent Error it closes the queue.
class CaptureThread {
 public:
  struct Stats {
    std::uint64_t captured = 0;  // frames read from the source
    std::uint64_t noBuffer = 0;  // frames dropped because every pooled buffer was in use
    std::uint64_t errors = 0;    // Error results from the source
  };

  // `maxConsecutiveErrors` Error results in a row end the thread (a source
  // that recovers by itself, like V4l2Source with autoReopen, returns Error
  // while it waits; 0 means never give up).
  CaptureThread(FrameSource& source, FramePool& pool, FrameQueue& queue,
                int maxConsecutiveErrors = 0);
  ~CaptureThread();
  CaptureThread(const CaptureThread&) = delete;
  CaptureThread& operator=(const CaptureThread&) = delete;

  void start();
  // Asks the thread to stop after the current next() call and joins it.
  void stop();
  [[nodiscard]] bool running() const { return running_; }
  [[nodiscard]] Stats stats() const;
  [[nodiscard]] std::string lastError() const;
  [[nodiscard]] bool ended() const { return ended_; }  // the source said End

 private:
  void run();

  FrameSource& source_;
  FramePool& pool_;
  FrameQueue& queue_;
  int maxConsecutiveErrors_;
  std::thread thread_;
  std::atomic<bool> stop_{false};
  std::atomic<bool> running_{false};
  std::atomic<bool> ended_{false};
  mutable std::mutex mutex_;
  Stats stats_;
  std::string lastError_;
};

}  // namespace keyframed
