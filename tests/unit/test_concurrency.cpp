// The structures threads share, hammered from several threads at once: the pose
// store (telemetry thread writes, analysis and output threads read) and the frame
// pool and queue (capture thread fills, analysis reads, output returns buffers).
// Built into the unit tests (AddressSanitizer/UBSan) and into keyframed_tsan_test
// (ThreadSanitizer), which reports any data race these runs reach.

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <deque>
#include <mutex>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "capture/frame_queue.h"
#include "telemetry/pose_store.h"

namespace keyframed {
namespace {

constexpr std::int64_t kMs = 1'000'000;

// The flight the writer reports: at sample i (1 ms apart), heading 0.5 mrad per ms,
// latitude 1e-7 deg per ms. Both vary linearly, so interpolation between any two
// neighbouring samples is exact: any other value read is a torn or mixed-up sample.
double yawAt(double ms) {
  return 0.0005 * ms;
}
double latAt(double ms) {
  return 47.0 + 1e-7 * ms;
}

TEST(Concurrency, PoseStoreReadWhileWrittenAndPruned) {
  PoseStore::Config config;
  config.historyNs = 500 * kMs;  // pruned all the time
  PoseStore store(config);
  constexpr int kSamples = 6000;
  std::atomic<bool> done{false};
  std::thread writer([&] {
    for (int i = 0; i < kSamples; ++i) {
      const std::int64_t t = i * kMs;
      store.addAttitude(t, quaternionFromEuler(0.0, 0.0, yawAt(i)));
      GeoPosition p;
      p.latDeg = latAt(i);
      p.lonDeg = 8.0;
      p.altAmslM = 100.0;
      store.addPosition(t, p);
      if (i % 50 == 0) {
        GpsQuality q;
        q.fixType = 3;
        q.satellites = 12;
        store.addGps(t, q);
      }
      if (i % 200 == 0) std::this_thread::yield();
    }
    done = true;
  });
  std::atomic<int> checked{0};
  std::atomic<int> wrong{0};
  const auto reader = [&](unsigned seed) {
    std::uint64_t x = seed;
    // Bounded: a store that never answered would fail the test, not hang it.
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    while ((!done.load() || checked.load() < 200) && std::chrono::steady_clock::now() < deadline) {
      const auto newest = store.newestNs();
      if (!newest || *newest < 100 * kMs) continue;
      x = x * 6364136223846793005ULL + 1442695040888963407ULL;
      // Between samples, within the history still kept.
      const double ms = static_cast<double>(*newest / kMs) - 1.0 -
                        static_cast<double>((x >> 33) % 300'000) / 1000.0;
      const Pose pose = store.at(static_cast<std::int64_t>(ms * kMs));
      (void)store.covers(static_cast<std::int64_t>(ms * kMs));
      (void)store.size();
      if (!pose.attitude || !pose.position) continue;  // pruned meanwhile: said, not wrong
      const bool ok =
          angleBetween(*pose.attitude, quaternionFromEuler(0.0, 0.0, yawAt(ms))) < 1e-6 &&
          std::fabs(pose.position->latDeg - latAt(ms)) < 1e-9 && pose.position->lonDeg == 8.0 &&
          pose.gps.fixType == 3;
      if (!ok) ++wrong;
      ++checked;
    }
  };
  std::thread r1(reader, 1U);
  std::thread r2(reader, 2U);
  writer.join();
  r1.join();
  r2.join();
  EXPECT_GE(checked.load(), 200);
  EXPECT_EQ(wrong.load(), 0);
  EXPECT_LE(store.size(), 2U * 600U + 20U);  // pruned to the history (three streams)
}

TEST(Concurrency, FramesTravelCaptureToAnalysisToOutputAndBackToThePool) {
  // Capture fills pooled buffers and queues them; analysis pops them and hands some
  // (keyframes) to an output thread; whichever thread lets go last returns the
  // buffer to the pool. Every frame is delivered, dropped or refused, none twice.
  constexpr int kFrames = 4000;
  FramePool pool(8);
  FrameQueue queue(3);
  std::mutex outMutex;
  std::deque<FramePtr> toOutput;
  std::atomic<bool> analysisDone{false};
  std::atomic<int> analysed{0};
  std::atomic<int> written{0};
  std::atomic<int> bad{0};
  std::thread analysis([&] {
    std::int64_t last = -1;
    while (auto f = queue.pop()) {
      const Frame& fr = (*f)->frame;
      if (fr.index <= last || fr.data[0] != static_cast<std::uint8_t>(fr.index)) ++bad;
      last = fr.index;
      ++analysed;
      if (fr.index % 7 == 0) {
        std::lock_guard lock(outMutex);
        toOutput.push_back(std::move(*f));
      }
    }
    analysisDone = true;
  });
  std::thread output([&] {
    for (;;) {
      FramePtr f;
      {
        std::lock_guard lock(outMutex);
        if (!toOutput.empty()) {
          f = std::move(toOutput.front());
          toOutput.pop_front();
        }
      }
      if (f) {
        if (f->frame.data[0] != static_cast<std::uint8_t>(f->frame.index)) ++bad;
        ++written;
        continue;  // f released here, on this thread
      }
      if (analysisDone.load()) {
        std::lock_guard lock(outMutex);
        if (toOutput.empty()) return;
      }
      std::this_thread::yield();
    }
  });
  std::vector<std::uint8_t> pixels(24 * 16, 0);
  int refused = 0;
  for (int i = 0; i < kFrames; ++i) {
    FramePtr buf = pool.acquire();
    if (!buf) {
      ++refused;  // every buffer in flight: a camera's driver drops the frame
      std::this_thread::yield();
      continue;
    }
    pixels[0] = static_cast<std::uint8_t>(i);
    const Frame src{PixelFormat::Gray8, pixels.data(), 24, 16, 24, i * kMs, i};
    copyFrame(src, *buf);
    queue.push(std::move(buf));
  }
  queue.close();
  analysis.join();
  output.join();
  EXPECT_EQ(bad.load(), 0);
  EXPECT_EQ(analysed.load() + static_cast<int>(queue.dropped()) + refused, kFrames);
  EXPECT_GT(written.load(), 0);
  EXPECT_EQ(pool.available(), 8U);  // every buffer back
}

}  // namespace
}  // namespace keyframed
