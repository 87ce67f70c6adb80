// "No heap allocation per frame in steady state", checked: every malloc in this
// process is counted (tools/bench/alloc_counter.cpp interposes glibc's), and the
// selector runs over a 1080p pan, keyframes included.
#include <gtest/gtest.h>

#include <vector>

#include <opencv2/imgproc.hpp>

#include "alloc_counter.h"
#include "core/frame.h"
#include "core/selector.h"
#include "photos.h"

namespace keyframed {
namespace {

// A pan over the photo strip at 1920x1080, rendered before counting starts.
std::vector<cv::Mat> pan1080(int frames, bool bgr) {
  const cv::Mat strip = test::photoStrip();
  cv::Mat big;
  cv::resize(strip, big, cv::Size(), 2.5, 2.5, cv::INTER_LINEAR);
  std::vector<cv::Mat> out;
  for (int i = 0; i < frames; ++i) {
    cv::Mat v = test::viewAt(big, 200 + 12.0 * i, 1920, 1080, 80);
    if (bgr) cv::cvtColor(v, v, cv::COLOR_GRAY2BGR);
    out.push_back(v);
  }
  return out;
}

struct Count {
  std::uint64_t allocations = 0;
  std::int64_t keyframes = 0;
};

// Allocations over frames [warmup, end) of the pan.
Count steadyStateAllocations(const std::vector<cv::Mat>& frames, int warmup,
                             const LensModel& lens = {}) {
  SelectorConfig config;  // default settings: geometric, 640 px analysis
  config.overlap.lens = lens;
  KeyframeSelector sel(config);
  Count c;
  for (int i = 0; i < static_cast<int>(frames.size()); ++i) {
    const cv::Mat& m = frames[static_cast<std::size_t>(i)];
    const Frame f = m.channels() == 1
                        ? Frame::ofGray(m, i, i * 33333333LL)
                        : Frame{PixelFormat::BGR24,       m.data,         m.cols, m.rows,
                                static_cast<int>(m.step), i * 33333333LL, i};
    if (i == warmup) {
      c.keyframes = sel.keyframes();
      bench::setCounting(true);
    }
    const std::uint64_t before = bench::allocations();
    const Decision d = sel.process(f);
    c.allocations += bench::allocations() - before;
    (void)d;
  }
  bench::setCounting(false);
  c.keyframes = sel.keyframes() - c.keyframes;
  return c;
}

TEST(Allocations, TheCounterSeesAllocations) {
  // Otherwise a zero below would prove nothing.
  bench::setCounting(true);
  const std::uint64_t before = bench::allocations();
  cv::Mat m(64, 64, CV_8UC1);
  std::vector<int> v(100);
  const std::uint64_t seen = bench::allocations() - before;
  bench::setCounting(false);
  EXPECT_GE(seen, 2u);
  EXPECT_EQ(m.total() + v.size(), 64u * 64u + 100u);
}

TEST(Allocations, NonePerFrameInSteadyStateGeometricGrey) {
  const auto frames = pan1080(150, false);
  const Count c = steadyStateAllocations(frames, 30);
  EXPECT_GE(c.keyframes, 3) << "the pan must make keyframes while counting";
  EXPECT_EQ(c.allocations, 0u);
}

TEST(Allocations, NonePerFrameInSteadyStateThroughALens) {
  // A calibrated wide-angle lens: points undistorted, overlap sampled through it.
  LensModel lens;
  lens.kind = LensModel::Kind::Pinhole;
  lens.width = 1920;
  lens.height = 1080;
  lens.fx = lens.fy = 1400;
  lens.cx = 959.5;
  lens.cy = 539.5;
  lens.k = {-0.12, 0.04, 0.0, 0.0, 0.0};
  const auto frames = pan1080(150, false);
  const Count c = steadyStateAllocations(frames, 30, lens);
  EXPECT_GE(c.keyframes, 3);
  EXPECT_EQ(c.allocations, 0u);
}

TEST(Allocations, NonePerFrameInSteadyStateGeometricBgr) {
  const auto frames = pan1080(120, true);
  const Count c = steadyStateAllocations(frames, 30);
  EXPECT_GE(c.keyframes, 2);
  EXPECT_EQ(c.allocations, 0u);
}

}  // namespace
}  // namespace keyframed
