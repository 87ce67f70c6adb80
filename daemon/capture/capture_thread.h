#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <limits>
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
//
// Errors: after an Error the next read waits (10 ms, doubling to 1 s; time the
// failing read itself took counts), so a source that fails at once cannot spin.
// A source whose failed() is true, or `maxConsecutiveErrors` Errors in a row, end
// the thread; lastError() says why. Passing errors are logged (capture, warning):
// the first of an outage at once, a different kind at most once a second, the
// same kind at most every 10 s with a count; a line when frames come back.
class CaptureThread {
 public:
  struct Stats {
    std::uint64_t captured = 0;  // frames read from the source
    std::uint64_t noBuffer = 0;  // frames dropped because every pooled buffer was in use
    std::uint64_t errors = 0;    // Error results from the source
    // Frames the camera held from before start(discardBeforeNs): handed back unread
    // (FrameSource::discardQueued) or read and thrown away, not part of the stream
    // (neither captured nor dropped).
    std::uint64_t stale = 0;
    // The source's lostFrames() at the first frame kept: what the camera could not
    // deliver while nobody read it (its buffers full of stale frames), before start.
    std::uint64_t lostBeforeStart = 0;
  };

  // `maxConsecutiveErrors`: 0 means never give up on a source that may recover
  // (like V4l2Source with autoReopen, which returns Error while it waits).
  CaptureThread(FrameSource& source, FramePool& pool, FrameQueue& queue,
                int maxConsecutiveErrors = 0);
  ~CaptureThread();
  CaptureThread(const CaptureThread&) = delete;
  CaptureThread& operator=(const CaptureThread&) = delete;

  // `discardBeforeNs`: a camera streams from its open(), and the frames its buffers
  // hold when the capture starts (seconds later, after the telemetry wait) show the
  // past: until the first frame stamped at or after this instant (the source's
  // clock), frames are thrown away. The default keeps every frame.
  // At most kMaxStaleFrames (more than a V4L2 queue's 32 buffers) are thrown away:
  // a source whose clock lags far behind has its frames kept, with a warning.
  void start(std::int64_t discardBeforeNs = std::numeric_limits<std::int64_t>::min());
  static constexpr std::uint64_t kMaxStaleFrames = 40;
  // Stops the thread and joins it: interrupts the source's next() (a camera
  // waiting for a frame returns at once; see FrameSource::interrupt, which is for
  // good) and any back-off wait.
  void stop();
  // stop(), but waits for the thread only `wait`: false when it is still inside a read
  // that the source cannot interrupt (a file source on a pipe whose writer went
  // silent). The thread is then left to itself; the owner flushes and exits without
  // destroying this object (whose destructor would wait for it).
  [[nodiscard]] bool stopWithin(std::chrono::milliseconds wait);
  [[nodiscard]] bool running() const { return running_; }
  [[nodiscard]] Stats stats() const;
  [[nodiscard]] std::string lastError() const;
  [[nodiscard]] bool ended() const { return ended_; }  // the source said End

  static constexpr std::chrono::milliseconds kFirstBackoff{10};
  static constexpr std::chrono::milliseconds kMaxBackoff{1000};

 private:
  void run();
  void loop();
  // Sets stop_ and interrupts the source's read; no join.
  void requestStop();
  // Waits up to `d` unless stop() is called; false when it was.
  bool pause(std::chrono::nanoseconds d);

  FrameSource& source_;
  FramePool& pool_;
  FrameQueue& queue_;
  int maxConsecutiveErrors_;
  std::int64_t discardBeforeNs_ = std::numeric_limits<std::int64_t>::min();
  std::thread thread_;
  std::atomic<bool> stop_{false};
  std::atomic<bool> running_{false};
  std::atomic<bool> ended_{false};
  bool finished_ = false;  // run() returned (under stopMutex_)
  std::mutex stopMutex_;
  std::condition_variable stopped_;
  mutable std::mutex mutex_;
  Stats stats_;
  std::string lastError_;
};

}  // namespace keyframed
