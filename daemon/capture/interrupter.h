#pragma once

#include <atomic>
#include <chrono>

namespace keyframed {

// Wakes a capture wait from another thread, for good: an eventfd that poll()
// watches beside the device, raised when the owner stops. A blocked
// FrameSource::next() returns at once instead of sitting out its frame timeout
// (2 s), so SIGTERM stops the daemon promptly even when the camera has stalled.
class Interrupter {
 public:
  Interrupter();
  ~Interrupter();
  Interrupter(const Interrupter&) = delete;
  Interrupter& operator=(const Interrupter&) = delete;

  // Thread-safe; every later wait() returns Interrupted at once.
  void raise();
  [[nodiscard]] bool raised() const { return raised_.load(); }

  enum class Wake { Ready, Timeout, Interrupted, Failed };
  struct Result {
    Wake wake = Wake::Timeout;
    short revents = 0;  // of `fd`, when Ready
    int err = 0;        // errno, when Failed
  };
  // Waits until `fd` has one of `events`, `timeout` passes, or raise() is called.
  // `fd` < 0 waits only for the timeout or raise() (an interruptible sleep).
  // EINTR is retried with the time left.
  [[nodiscard]] Result wait(int fd, short events, std::chrono::milliseconds timeout) const;

 private:
  int eventFd_ = -1;  // -1 when eventfd() failed: waits then poll in short slices
  std::atomic<bool> raised_{false};
};

}  // namespace keyframed
