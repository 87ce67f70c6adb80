#pragma once

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <utility>
#include <vector>

#include "capture/buffer_pool.h"
#include "core/frame.h"

namespace keyframed {

// A frame that owns its pixels: what crosses from the capture thread to the
// analysis thread. `frame.data` points into `pixels`.
struct FrameBuffer {
  Frame frame;
  std::vector<std::uint8_t> pixels;
};

using FramePtr = std::shared_ptr<FrameBuffer>;
using FramePool = BufferPool<FrameBuffer>;

// Bytes a frame's planes occupy (all planes for NV12/YUV420), rows `stride` apart.
[[nodiscard]] inline std::size_t frameBytes(const Frame& f) {
  const auto rows = static_cast<std::size_t>(f.height);
  const auto stride = static_cast<std::size_t>(f.stride);
  switch (f.format) {
    case PixelFormat::NV12: return stride * rows + stride * ((rows + 1) / 2);
    // Chroma rows stride / 2 long (as planeSizes() has them): an odd stride's are
    // shorter than half of it, and reading stride * rows / 2 would run past the frame.
    case PixelFormat::YUV420: return stride * rows + 2 * (stride / 2) * ((rows + 1) / 2);
    case PixelFormat::Gray8:
    case PixelFormat::YUYV:
    case PixelFormat::BGR24: return stride * rows;
  }
  return stride * rows;
}

// Copies a borrowed frame (valid only until the source's next call) into a
// pooled buffer. Reuses the buffer's storage when it is large enough.
inline void copyFrame(const Frame& src, FrameBuffer& dst) {
  const std::size_t bytes = frameBytes(src);
  if (dst.pixels.size() < bytes) dst.pixels.resize(bytes);
  if (bytes > 0 && src.data != nullptr) std::copy_n(src.data, bytes, dst.pixels.data());
  dst.frame = src;
  dst.frame.data = dst.pixels.data();
}

// A small thread-safe bounded FIFO between one producer that must never block
// (the capture thread) and a consumer. When full, push() drops the OLDEST item
// and counts it: the analysis always sees the freshest frames. A ring of fixed
// capacity: no allocation after construction.
template <typename T>
class BoundedQueue {
 public:
  explicit BoundedQueue(std::size_t capacity) : ring_(capacity == 0 ? 1 : capacity) {}
  BoundedQueue(const BoundedQueue&) = delete;
  BoundedQueue& operator=(const BoundedQueue&) = delete;

  // Never blocks (beyond the short lock). Returns false when an older item
  // was dropped to make room, or when the queue is closed (the item is dropped).
  bool push(T item) {
    std::optional<T> evicted;  // destroyed outside the lock (may return a buffer to a pool)
    bool kept = true;
    {
      std::lock_guard lock(mutex_);
      if (closed_) {
        ++dropped_;
        evicted.emplace(std::move(item));
        kept = false;
      } else {
        if (size_ == ring_.size()) {
          evicted.emplace(std::move(ring_[head_]));
          ring_[head_] = T{};
          head_ = (head_ + 1) % ring_.size();
          --size_;
          ++dropped_;
          kept = false;
        }
        ring_[(head_ + size_) % ring_.size()] = std::move(item);
        ++size_;
        ++pushed_;
      }
    }
    ready_.notify_one();
    return kept;
  }

  // For a consumer that must not lose items (analysis -> output): waits while the
  // queue is full instead of dropping. False (item dropped) once closed.
  bool pushWait(T item) {
    {
      std::unique_lock lock(mutex_);
      notFull_.wait(lock, [&] { return size_ < ring_.size() || closed_; });
      if (closed_) {
        ++dropped_;
        return false;
      }
      ring_[(head_ + size_) % ring_.size()] = std::move(item);
      ++size_;
      ++pushed_;
    }
    ready_.notify_one();
    return true;
  }

  // The oldest item, waiting up to `timeout`; nullopt on timeout, or when the
  // queue is closed and empty.
  template <typename Rep, typename Period>
  std::optional<T> pop(std::chrono::duration<Rep, Period> timeout) {
    std::unique_lock lock(mutex_);
    if (!ready_.wait_for(lock, timeout, [&] { return size_ > 0 || closed_; })) return std::nullopt;
    return takeLocked();
  }

  // Waits until an item arrives or the queue is closed.
  std::optional<T> pop() {
    std::unique_lock lock(mutex_);
    ready_.wait(lock, [&] { return size_ > 0 || closed_; });
    return takeLocked();
  }

  std::optional<T> tryPop() {
    std::lock_guard lock(mutex_);
    return takeLocked();
  }

  // Wakes waiting consumers; later pushes are dropped. Items already queued
  // can still be popped.
  void close() {
    {
      std::lock_guard lock(mutex_);
      closed_ = true;
    }
    ready_.notify_all();
    notFull_.notify_all();
  }

  [[nodiscard]] std::size_t capacity() const { return ring_.size(); }
  [[nodiscard]] std::size_t size() const {
    std::lock_guard lock(mutex_);
    return size_;
  }
  [[nodiscard]] std::uint64_t dropped() const {
    std::lock_guard lock(mutex_);
    return dropped_;
  }
  [[nodiscard]] std::uint64_t pushed() const {
    std::lock_guard lock(mutex_);
    return pushed_;
  }
  [[nodiscard]] bool closed() const {
    std::lock_guard lock(mutex_);
    return closed_;
  }

 private:
  std::optional<T> takeLocked() {
    if (size_ == 0) return std::nullopt;
    std::optional<T> out(std::move(ring_[head_]));
    ring_[head_] = T{};
    head_ = (head_ + 1) % ring_.size();
    --size_;
    notFull_.notify_one();
    return out;
  }

  mutable std::mutex mutex_;
  std::condition_variable ready_;
  std::condition_variable notFull_;  // pushWait(): room again
  std::vector<T> ring_;
  std::size_t head_ = 0;
  std::size_t size_ = 0;
  std::uint64_t dropped_ = 0;
  std::uint64_t pushed_ = 0;
  bool closed_ = false;
};

using FrameQueue = BoundedQueue<FramePtr>;

// How many frames the capture queue holds to ride out `queueMs` of analysis falling
// behind at `fps` (camera.queue_ms): rounded up, at least 2, at most 64, and no more
// than kQueueBudgetBytes of frames of `frameBytes` each (a 4K frame is 12-25 MB). The
// pool makes a buffer only when a stall first fills the queue that deep.
inline constexpr std::size_t kQueueBudgetBytes = std::size_t{64} << 20;
[[nodiscard]] inline std::size_t queueFramesFor(int queueMs, double fps, std::size_t frameBytes) {
  constexpr std::size_t kMin = 2, kMax = 64;
  std::size_t cap = kMax;
  if (frameBytes > 0) cap = std::clamp(kQueueBudgetBytes / frameBytes, kMin, kMax);
  if (!(fps > 0) || queueMs <= 0) return kMin;
  const double frames = std::ceil(queueMs * fps / 1000.0 - 1e-9);
  return std::clamp(frames >= static_cast<double>(cap) ? cap : static_cast<std::size_t>(frames),
                    kMin, cap);
}

}  // namespace keyframed
