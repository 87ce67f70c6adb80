#include <poll.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <string>
#include <string_view>
#include <thread>
#include <utility>
#include <vector>

#include <gtest/gtest.h>

#include "app/log.h"
#include "capture/buffer_pool.h"
#include "capture/capture_thread.h"
#include "capture/frame_queue.h"
#include "capture/interrupter.h"
#include "capture/plane_layout.h"

namespace keyframed {
namespace {

using namespace std::chrono_literals;

TEST(BoundedQueue, FifoOrder) {
  BoundedQueue<int> q(4);
  for (int i = 0; i < 3; ++i) EXPECT_TRUE(q.push(i));
  EXPECT_EQ(q.size(), 3u);
  for (int i = 0; i < 3; ++i) EXPECT_EQ(q.tryPop().value(), i);
  EXPECT_FALSE(q.tryPop().has_value());
  EXPECT_EQ(q.dropped(), 0u);
}

TEST(BoundedQueue, DropsOldestWhenFullAndCounts) {
  BoundedQueue<int> q(3);
  for (int i = 0; i < 3; ++i) EXPECT_TRUE(q.push(i));
  EXPECT_FALSE(q.push(3));  // 0 goes
  EXPECT_FALSE(q.push(4));  // 1 goes
  EXPECT_EQ(q.dropped(), 2u);
  EXPECT_EQ(q.pushed(), 5u);
  EXPECT_EQ(q.size(), 3u);
  EXPECT_EQ(q.tryPop().value(), 2);
  EXPECT_EQ(q.tryPop().value(), 3);
  EXPECT_EQ(q.tryPop().value(), 4);
}

TEST(BoundedQueue, PushWaitBlocksWhenFullAndLosesNothing) {
  // analysis -> output: the producer waits for room instead of dropping.
  BoundedQueue<int> q(2);
  std::atomic<int> pushed{0};
  std::thread producer([&] {
    for (int i = 0; i < 100; ++i) {
      ASSERT_TRUE(q.pushWait(i));
      pushed.fetch_add(1);
    }
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  EXPECT_LE(pushed.load(), 3) << "a full queue must hold the producer back";
  for (int i = 0; i < 100; ++i) {
    const auto v = q.pop(std::chrono::seconds(5));
    ASSERT_TRUE(v.has_value());
    EXPECT_EQ(*v, i);
  }
  producer.join();
  EXPECT_EQ(q.dropped(), 0u);
}

TEST(BoundedQueue, CloseReleasesAWaitingPusher) {
  BoundedQueue<int> q(1);
  ASSERT_TRUE(q.pushWait(1));
  std::thread producer([&] { EXPECT_FALSE(q.pushWait(2)); });
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  q.close();
  producer.join();
  EXPECT_EQ(q.dropped(), 1u);
  EXPECT_EQ(q.pop(std::chrono::milliseconds(1)).value_or(-1), 1);  // queued items still pop
}

TEST(BoundedQueue, PopTimesOutWhenEmpty) {
  BoundedQueue<int> q(2);
  const auto t0 = std::chrono::steady_clock::now();
  EXPECT_FALSE(q.pop(20ms).has_value());
  EXPECT_GE(std::chrono::steady_clock::now() - t0, 15ms);
}

TEST(BoundedQueue, CloseWakesConsumerAndRejectsPushes) {
  BoundedQueue<int> q(2);
  q.push(7);
  std::thread consumer([&] {
    EXPECT_EQ(q.pop().value(), 7);
    EXPECT_FALSE(q.pop().has_value());  // woken by close()
  });
  std::this_thread::sleep_for(10ms);
  q.close();
  consumer.join();
  EXPECT_FALSE(q.push(8));
  EXPECT_TRUE(q.closed());
}

TEST(BoundedQueue, ProducerNeverBlocksOnSlowConsumer) {
  BoundedQueue<int> q(2);
  std::atomic<bool> done{false};
  std::vector<int> seen;
  std::thread consumer([&] {
    while (auto v = q.pop()) {
      seen.push_back(*v);
      std::this_thread::sleep_for(1ms);
    }
    done = true;
  });
  const auto t0 = std::chrono::steady_clock::now();
  for (int i = 0; i < 2000; ++i) q.push(i);
  const auto pushTime = std::chrono::steady_clock::now() - t0;
  q.close();
  consumer.join();
  EXPECT_LT(pushTime, 500ms);  // 2000 pushes against a 1 ms/item consumer
  EXPECT_EQ(q.pushed(), 2000u);
  EXPECT_EQ(q.dropped() + seen.size(), 2000u);
  EXPECT_GT(q.dropped(), 0u);
  for (std::size_t i = 1; i < seen.size(); ++i) EXPECT_LT(seen[i - 1], seen[i]);
  EXPECT_EQ(seen.back(), 1999);  // the freshest frame always survives
}

TEST(BufferPool, ReturnsObjectsWhenLastHolderLetsGo) {
  BufferPool<std::vector<int>> pool(2);
  auto a = pool.acquire();
  auto b = pool.acquire();
  ASSERT_TRUE(a && b);
  EXPECT_FALSE(pool.acquire());  // exhausted
  EXPECT_EQ(pool.exhaustedCount(), 1u);
  std::vector<int>* raw = a.get();
  a->push_back(42);
  auto a2 = a;  // a second holder
  a.reset();
  EXPECT_EQ(pool.available(), 0u);
  a2.reset();
  EXPECT_EQ(pool.available(), 1u);
  auto c = pool.acquire();
  EXPECT_EQ(c.get(), raw);  // the same object came back, contents kept
  EXPECT_EQ(c->size(), 1u);
  EXPECT_EQ(pool.created(), 2u);
}

TEST(BufferPool, NoAllocationPerFrameInSteadyState) {
  FramePool pool(4);
  FrameQueue q(2);
  std::vector<std::uint8_t> pixels(64 * 48 * 2, 128);
  Frame src{PixelFormat::YUYV, pixels.data(), 64, 48, 128, 0, 0};
  for (int i = 0; i < 1000; ++i) {
    FramePtr buf = pool.acquire();
    ASSERT_TRUE(buf) << "pool exhausted at frame " << i;
    src.index = i;
    src.timestampNs = i * 33'000'000LL;
    copyFrame(src, *buf);
    q.push(std::move(buf));  // drops the oldest when full: it goes back to the pool
    if (i % 3 == 0) q.tryPop();
  }
  EXPECT_LE(pool.created(), 4u);
  EXPECT_LE(pool.controlBlockAllocations(), 4u);
  EXPECT_GT(q.dropped(), 0u);
  auto last = q.tryPop();
  while (auto more = q.tryPop()) last = std::move(more);
  ASSERT_TRUE(last.has_value());
  EXPECT_EQ((*last)->frame.index, 999);
  EXPECT_EQ((*last)->frame.data, (*last)->pixels.data());
  EXPECT_EQ((*last)->frame.timestampNs, 999 * 33'000'000LL);
}

TEST(BufferPool, ObjectsMayOutliveThePool) {
  std::shared_ptr<std::vector<int>> keep;
  {
    BufferPool<std::vector<int>> pool(1);
    keep = pool.acquire();
    keep->assign(10, 1);
  }
  EXPECT_EQ(keep->size(), 10u);
  keep.reset();  // deleted, not returned: no crash (ASan checks the rest)
}

TEST(FrameBytes, CoversAllPlanes) {
  Frame f{PixelFormat::NV12, nullptr, 640, 480, 640, 0, 0};
  EXPECT_EQ(frameBytes(f), 640u * 480u * 3u / 2u);
  f.format = PixelFormat::YUV420;
  EXPECT_EQ(frameBytes(f), 640u * 480u * 3u / 2u);
  f.format = PixelFormat::YUYV;
  f.stride = 1280;
  EXPECT_EQ(frameBytes(f), 1280u * 480u);
}

TEST(FrameBytes, MatchesThePlanesACameraHandsOverForEveryStride) {
  // copyFrame() reads frameBytes() from a buffer contiguousFrame() checked against
  // planeSizes(): the two must agree, or an odd stride reads past the frame.
  for (const PixelFormat fmt : {PixelFormat::NV12, PixelFormat::YUV420, PixelFormat::YUYV,
                                PixelFormat::Gray8, PixelFormat::BGR24}) {
    for (const int stride : {640, 641, 643, 1280}) {
      for (const int height : {480, 481}) {
        std::size_t planes = 0;
        for (std::size_t n : planeSizes(fmt, stride, height)) planes += n;
        const Frame f{fmt, nullptr, 640, height, stride, 0, 0};
        EXPECT_EQ(frameBytes(f), planes)
            << toString(fmt) << " stride " << stride << " height " << height;
      }
    }
  }
}

TEST(FrameQueue, ConcurrentProducerConsumerKeepsOrderAndReturnsBuffers) {
  FramePool pool(6);
  FrameQueue q(3);
  std::vector<std::uint8_t> pixels(32 * 32, 0);
  std::atomic<int> consumed{0};
  std::thread consumer([&] {
    std::int64_t last = -1;
    while (auto f = q.pop()) {
      EXPECT_GT((*f)->frame.index, last);
      last = (*f)->frame.index;
      ++consumed;
    }
  });
  std::uint64_t noBuffer = 0;
  for (int i = 0; i < 5000; ++i) {
    FramePtr buf = pool.acquire();
    if (!buf) {
      ++noBuffer;  // every buffer in flight: a real producer counts a drop
      continue;
    }
    Frame src{PixelFormat::Gray8, pixels.data(), 32, 32, 32, i, i};
    copyFrame(src, *buf);
    q.push(std::move(buf));
  }
  q.close();
  consumer.join();
  EXPECT_EQ(consumed + q.dropped() + noBuffer, 5000u);
  EXPECT_EQ(pool.available(), 6u);
}

}  // namespace
}  // namespace keyframed

namespace keyframed {
namespace {

// A source that produces `count` small gray frames as fast as asked.
class CountingSource final : public FrameSource {
 public:
  explicit CountingSource(int count, int errorsAt = -1) : count_(count), errorsAt_(errorsAt) {
    info_.width = 16;
    info_.height = 8;
    pixels_.assign(16 * 8, 0);
  }
  const SourceInfo& info() const override { return info_; }
  ReadStatus next(Frame& f, std::string& error) override {
    if (n_ == errorsAt_ && !erred_) {
      erred_ = true;
      error = "device lost: test";
      return ReadStatus::Error;
    }
    if (n_ >= count_) return ReadStatus::End;
    pixels_[0] = static_cast<std::uint8_t>(n_);
    f = Frame{PixelFormat::Gray8, pixels_.data(), 16, 8, 16, n_ * 1000LL, n_};
    ++n_;
    return ReadStatus::Frame;
  }

 private:
  SourceInfo info_;
  std::vector<std::uint8_t> pixels_;
  int count_, errorsAt_, n_ = 0;
  bool erred_ = false;
};

TEST(CaptureThread, DeliversCopiesInOrderAndClosesAtEnd) {
  CountingSource src(500, 100);
  FramePool pool(8);
  FrameQueue q(4);
  CaptureThread capture(src, pool, q);
  capture.start();
  std::vector<std::int64_t> seen;
  while (auto f = q.pop()) {
    EXPECT_EQ((*f)->pixels[0], static_cast<std::uint8_t>((*f)->frame.index));  // a real copy
    seen.push_back((*f)->frame.index);
    std::this_thread::sleep_for(std::chrono::microseconds(200));  // a slow consumer
  }
  capture.stop();
  EXPECT_TRUE(capture.ended());
  const auto st = capture.stats();
  EXPECT_EQ(st.captured, 500u);
  EXPECT_EQ(st.errors, 1u);
  EXPECT_EQ(capture.lastError(), "device lost: test");
  EXPECT_EQ(seen.size() + q.dropped() + st.noBuffer, 500u);
  EXPECT_EQ(seen.back(), 499);
  for (std::size_t i = 1; i < seen.size(); ++i) EXPECT_LT(seen[i - 1], seen[i]);
  EXPECT_LE(pool.created(), 8u);
}

TEST(CaptureThread, FramesHeldFromBeforeTheStartAreThrownAway) {
  // A camera streaming since its open: its 4 buffers hold frames of t = 1..4 s, it
  // could not deliver 96 more while nobody read, then frames come from t = 10 s on.
  class HeldFrames final : public FrameSource {
   public:
    HeldFrames() {
      info_.width = 16;
      info_.height = 8;
      pixels_.assign(16 * 8, 0);
    }
    const SourceInfo& info() const override { return info_; }
    ReadStatus next(Frame& f, std::string&) override {
      if (n_ >= 20) return ReadStatus::End;
      std::int64_t ts = n_ < 4 ? (1 + n_) * 1'000'000'000LL : 10'000'000'000LL + n_ * 33'000'000LL;
      if (n_ == 12) ts = 5'000'000'000LL;  // a clock step later on: the stream's own business
      if (n_ == 4) lost_ = 96;
      f = Frame{PixelFormat::Gray8, pixels_.data(), 16, 8, 16, ts, n_};
      ++n_;
      return ReadStatus::Frame;
    }
    std::uint64_t lostFrames() const override { return lost_; }

   private:
    SourceInfo info_;
    std::vector<std::uint8_t> pixels_;
    int n_ = 0;
    std::atomic<std::uint64_t> lost_{0};
  };
  HeldFrames src;
  FramePool pool(32);
  FrameQueue q(32);
  CaptureThread capture(src, pool, q);
  capture.start(10'000'000'000LL - 50'000'000LL);
  std::vector<std::int64_t> seen;
  while (auto f = q.pop()) seen.push_back((*f)->frame.index);
  capture.stop();
  std::vector<std::int64_t> expected;
  for (std::int64_t i = 4; i < 20; ++i) expected.push_back(i);
  EXPECT_EQ(seen, expected);
  const auto st = capture.stats();
  EXPECT_EQ(st.stale, 4u);
  EXPECT_EQ(st.captured, 16u);
  EXPECT_EQ(st.lostBeforeStart, 96u);
}

// A source whose clock lags far behind (a loopback device fed presentation times
// from 0): its frames are all "before the start". No camera holds more than
// kMaxStaleFrames: past them, frames are kept, not thrown away for ever.
TEST(CaptureThread, AClockFarBehindHasItsFramesKeptAfterABufferfulAreThrownAway) {
  class LaggingClock final : public FrameSource {
   public:
    LaggingClock() {
      info_.width = 16;
      info_.height = 8;
      pixels_.assign(16 * 8, 0);
    }
    const SourceInfo& info() const override { return info_; }
    ReadStatus next(Frame& f, std::string&) override {
      if (n_ >= 100) return ReadStatus::End;
      f = Frame{PixelFormat::Gray8, pixels_.data(), 16, 8, 16, n_ * 33'000'000LL, n_};
      ++n_;
      return ReadStatus::Frame;
    }

   private:
    SourceInfo info_;
    std::vector<std::uint8_t> pixels_;
    int n_ = 0;
  };
  LaggingClock src;
  FramePool pool(128);
  FrameQueue q(128);
  CaptureThread capture(src, pool, q);
  capture.start(3'600'000'000'000LL);  // an hour after boot
  std::vector<std::int64_t> seen;
  while (auto f = q.pop()) seen.push_back((*f)->frame.index);
  capture.stop();
  const auto st = capture.stats();
  EXPECT_EQ(st.stale, CaptureThread::kMaxStaleFrames);
  ASSERT_EQ(seen.size(), 100 - CaptureThread::kMaxStaleFrames);
  EXPECT_EQ(seen.front(), static_cast<std::int64_t>(CaptureThread::kMaxStaleFrames));
  EXPECT_EQ(seen.back(), 99);
}

TEST(CaptureThread, KeepsEveryFrameByDefault) {
  CountingSource src(50);
  FramePool pool(64);
  FrameQueue q(64);
  CaptureThread capture(src, pool, q);
  capture.start();  // CountingSource stamps frames from 0 ns: none is "stale"
  std::size_t n = 0;
  while (q.pop()) ++n;
  capture.stop();
  EXPECT_EQ(n, 50u);
  EXPECT_EQ(capture.stats().stale, 0u);
}

TEST(CaptureThread, GivesUpAfterConsecutiveErrors) {
  class Failing final : public FrameSource {
   public:
    const SourceInfo& info() const override { return info_; }
    ReadStatus next(Frame&, std::string& error) override {
      error = "no such device: /dev/video9";
      return ReadStatus::Error;
    }
    SourceInfo info_;
  } src;
  FramePool pool(2);
  FrameQueue q(2);
  CaptureThread capture(src, pool, q, 3);
  capture.start();
  EXPECT_FALSE(q.pop().has_value());  // closed by the thread
  capture.stop();
  EXPECT_EQ(capture.stats().errors, 3u);
  EXPECT_FALSE(capture.ended());
}

// Fails `errors` times (at once, as a vanished device does), then delivers `frames`.
class FlakySource final : public FrameSource {
 public:
  FlakySource(int errors, int frames, bool permanent = false)
      : errors_(errors), frames_(frames), permanent_(permanent) {
    info_.width = 16;
    info_.height = 8;
    pixels_.assign(16 * 8, 0);
  }
  const SourceInfo& info() const override { return info_; }
  ReadStatus next(Frame& f, std::string& error) override {
    ++calls;
    if (errors_ > 0 || permanent_) {
      if (--errors_ == 0 && !backAs.empty()) info_.description = backAs;
      error = permanent_
                  ? "video ended early: test"
                  : "device lost: /dev/video9 (attempt " + std::to_string(calls.load()) + ")";
      return ReadStatus::Error;
    }
    if (frames_-- <= 0) return ReadStatus::End;
    f = Frame{PixelFormat::Gray8, pixels_.data(), 16, 8, 16, calls.load() * 1000LL, calls.load()};
    return ReadStatus::Frame;
  }
  bool failed() const override { return permanent_; }
  std::atomic<int> calls{0};
  std::string backAs;  // the description it comes back with, "" the same

 private:
  SourceInfo info_;
  std::vector<std::uint8_t> pixels_;
  int errors_, frames_;
  bool permanent_;
};

// Captures the log lines of one category while alive.
class LogCapture {
 public:
  LogCapture() {
    logging::setSink([this](LogCategory c, LogLevel l, std::string_view m) {
      if (c == LogCategory::Capture) lines.emplace_back(l, std::string(m));
    });
  }
  ~LogCapture() { logging::setSink({}); }
  std::vector<std::pair<LogLevel, std::string>> lines;
};

TEST(CaptureThread, BacksOffInsteadOfSpinningOnASourceThatFailsAtOnce) {
  FlakySource src(1'000'000, 0);
  FramePool pool(2);
  FrameQueue q(2);
  CaptureThread capture(src, pool, q);  // never gives up
  capture.start();
  // 10, 20, 40, ... ms apart: the 7th call some 630 ms in, then a pause of 640 ms.
  const auto start = std::chrono::steady_clock::now();
  while (src.calls.load() < 7 && std::chrono::steady_clock::now() - start < std::chrono::seconds(5))
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  ASSERT_GE(src.calls.load(), 7);
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  const auto t0 = std::chrono::steady_clock::now();
  capture.stop();  // while it backs off: not after the ~590 ms left of the pause
  EXPECT_LT(std::chrono::steady_clock::now() - t0, std::chrono::milliseconds(100));
  EXPECT_LE(src.calls.load(), 9) << "not backing off";
  EXPECT_GE(std::chrono::steady_clock::now() - start, std::chrono::milliseconds(600));
  EXPECT_TRUE(capture.running() == false);
}

TEST(CaptureThread, StopsAtOnceOnAPermanentErrorAndLeavesItToTheOwner) {
  LogCapture log;
  FlakySource src(0, 0, true);
  FramePool pool(2);
  FrameQueue q(2);
  CaptureThread capture(src, pool, q);  // never gives up, but the source has failed
  capture.start();
  EXPECT_FALSE(q.pop().has_value());  // closed by the thread
  capture.stop();
  EXPECT_EQ(src.calls.load(), 1);
  EXPECT_FALSE(capture.ended());
  EXPECT_EQ(capture.lastError(), "video ended early: test");
  EXPECT_TRUE(log.lines.empty());  // the owner reports why capture stopped, once
}

TEST(CaptureThread, ASourceThatThrowsEndsTheCaptureWithTheReason) {
  class Throwing final : public FrameSource {
   public:
    const SourceInfo& info() const override { return info_; }
    ReadStatus next(Frame& f, std::string&) override {
      if (n_ == 3) throw std::runtime_error("decoder exploded");
      pixels_.assign(16 * 8, 0);
      f = Frame{PixelFormat::Gray8, pixels_.data(), 16, 8, 16, n_ * 1000LL, n_};
      ++n_;
      return ReadStatus::Frame;
    }
    SourceInfo info_{};
    std::vector<std::uint8_t> pixels_;
    int n_ = 0;
  } src;
  FramePool pool(8);
  FrameQueue q(8);
  CaptureThread capture(src, pool, q);
  capture.start();
  int frames = 0;
  while (q.pop()) ++frames;  // closed by the thread, the frames before it delivered
  capture.stop();
  EXPECT_EQ(frames, 3);
  EXPECT_FALSE(capture.running());
  EXPECT_FALSE(capture.ended());
  EXPECT_EQ(capture.lastError(), "capture failed: decoder exploded");
}

TEST(CaptureThread, LogsAnOutageOnceAndItsEnd) {
  LogCapture log;
  FlakySource src(5, 3);
  FramePool pool(4);
  FrameQueue q(8);
  CaptureThread capture(src, pool, q);
  capture.start();
  int frames = 0;
  while (q.pop()) ++frames;
  capture.stop();
  EXPECT_EQ(frames, 3);
  EXPECT_EQ(capture.stats().errors, 5u);
  ASSERT_EQ(log.lines.size(), 2u);
  EXPECT_EQ(log.lines[0].first, LogLevel::Warning);
  EXPECT_EQ(log.lines[0].second, "device lost: /dev/video9 (attempt 1)");
  EXPECT_EQ(log.lines[1].first, LogLevel::Notice);
  EXPECT_NE(log.lines[1].second.find("capture recovered after 5 errors"), std::string::npos);
  EXPECT_EQ(log.lines[1].second.find("now"), std::string::npos) << log.lines[1].second;
}

TEST(CaptureThread, SaysWhereACameraFoundOnAnotherNodeIsNow) {
  LogCapture log;
  FlakySource src(2, 1);
  src.backAs = "v4l2:/dev/video3 (uvcvideo: cam) MJPG 64x48";
  FramePool pool(4);
  FrameQueue q(8);
  CaptureThread capture(src, pool, q);
  capture.start();
  while (q.pop()) {
  }
  capture.stop();
  ASSERT_EQ(log.lines.size(), 2u);
  EXPECT_NE(log.lines[1].second.find("capture recovered after 2 errors"), std::string::npos);
  EXPECT_NE(log.lines[1].second.find("; now v4l2:/dev/video3 (uvcvideo: cam)"), std::string::npos)
      << log.lines[1].second;
}

// A camera that has stalled: next() waits for a frame that never comes, up to its
// 2 s timeout, unless interrupted, as V4l2Source does.
class StalledCamera final : public FrameSource {
 public:
  StalledCamera() { EXPECT_EQ(::pipe(pipe_), 0); }
  ~StalledCamera() override {
    ::close(pipe_[0]);
    ::close(pipe_[1]);
  }
  const SourceInfo& info() const override { return info_; }
  ReadStatus next(Frame&, std::string& error) override {
    ++calls;
    const auto r = interrupter_.wait(pipe_[0], POLLIN, 2000ms);
    error = r.wake == Interrupter::Wake::Interrupted ? "interrupted" : "timeout: no frame";
    return ReadStatus::Error;
  }
  void interrupt() override { interrupter_.raise(); }
  std::atomic<int> calls{0};

 private:
  SourceInfo info_;
  int pipe_[2] = {-1, -1};
  Interrupter interrupter_;
};

TEST(CaptureThread, StopInterruptsASourceWaitingForAFrame) {
  LogCapture log;
  StalledCamera src;
  FramePool pool(2);
  FrameQueue q(2);
  CaptureThread capture(src, pool, q);
  capture.start();
  while (src.calls.load() == 0) std::this_thread::sleep_for(1ms);
  std::this_thread::sleep_for(50ms);  // well inside the wait
  const auto t0 = std::chrono::steady_clock::now();
  capture.stop();
  const auto took = std::chrono::steady_clock::now() - t0;
  EXPECT_LT(took, 300ms) << "stop() sat out the source's frame timeout";
  EXPECT_EQ(src.calls.load(), 1);
  EXPECT_EQ(capture.stats().errors, 0u);  // an interrupted read is no capture error
  EXPECT_TRUE(log.lines.empty());
  EXPECT_FALSE(q.pop(0ms).has_value());
}

TEST(QueueFramesFor, CoversTheConfiguredTimeAtTheSourceRate) {
  constexpr std::size_t k1080 = 1920 * 1080 * 3;
  EXPECT_EQ(queueFramesFor(300, 30.0, k1080), 9u);           // 300 ms at 30 fps
  EXPECT_EQ(queueFramesFor(100, 29.97, k1080), 3u);          // 2.997 frames: rounded up
  EXPECT_EQ(queueFramesFor(300, 60.0, 640 * 480 * 3), 18u);  // twice the frames at 60 fps
  EXPECT_EQ(queueFramesFor(1000, 25.0, 0), 25u);             // size unknown: time alone
}

TEST(QueueFramesFor, StaysWithinTwoAndSixtyFourFramesAndTheMemoryBudget) {
  constexpr std::size_t k1080 = 1920 * 1080 * 3;
  EXPECT_EQ(queueFramesFor(0, 30.0, k1080), 2u);   // no slack asked: still double-buffered
  EXPECT_EQ(queueFramesFor(10, 30.0, k1080), 2u);  // 0.3 frames
  EXPECT_EQ(queueFramesFor(300, 0.0, k1080), 2u);  // a source that does not know its rate
  EXPECT_EQ(queueFramesFor(300, std::numeric_limits<double>::quiet_NaN(), k1080), 2u);
  EXPECT_EQ(queueFramesFor(5000, 240.0, 320 * 240 * 3), 64u);  // 1200 frames asked
  // 1080p60: 18 frames asked, 10 fit in 64 MiB; 4K: 2 frames at most (25 MB each).
  EXPECT_EQ(queueFramesFor(300, 60.0, k1080), kQueueBudgetBytes / k1080);
  EXPECT_EQ(queueFramesFor(300, 60.0, k1080), 10u);
  EXPECT_EQ(queueFramesFor(300, 30.0, 3840 * 2160 * 3), 2u);
}

}  // namespace
}  // namespace keyframed
