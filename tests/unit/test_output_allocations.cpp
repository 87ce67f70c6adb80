// "No heap allocation per frame in steady state" for the daemon's per-frame work
// after selection: the decision row (file and flight record), the keyframe scores
// kept for the metadata, the preview frame queued to the MCAP recorder, and the
// preview's scaling. Counted on the calling thread only (the recorder's writer thread
// is the mcap crate's, whose per-chunk buffers are its own; docs/performance.md).
// The preview's JPEG is libjpeg-turbo's, which takes its work memory from malloc for
// every picture: the preview encoder is checked to add nothing to that.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include <unistd.h>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "alloc_counter.h"
#include "app/decision_log.h"
#include "app/keyframe_output.h"
#include "app/keyframe_writer.h"
#include "app/preview_encoder.h"
#include "core/frame.h"
#include "output/flight_outputs.h"
#include "tagging/jpeg_encoder.h"

namespace keyframed {
namespace {

namespace fs = std::filesystem;

fs::path freshDir(const std::string& name) {
  const fs::path dir =
      fs::temp_directory_path() / ("keyframed-alloc-" + name + "-" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

// A frame that is no keyframe, with every column of its row filled; every 40th a
// candidate (a gap-fill fallback held back until the next one settles it).
Decision decisionAt(std::int64_t i) {
  Decision d;
  d.index = i;
  d.timestampNs = 1'000'000'000 + i * 33'333'333;
  d.kept = false;
  d.reason = i % 7 == 0 ? Reason::Blurry : Reason::Redundant;
  d.candidate = i % 40 == 5;
  d.sharpness = 150.0 + static_cast<double>(i % 13);
  d.threshold = 80.5;
  d.sharp = i % 7 != 0;
  d.overlap = 0.95 - 0.001 * static_cast<double>(i % 50);
  d.paperDistance = 31.25;
  d.tracking = true;
  d.motionPx = 3.5;
  d.features = 400 + static_cast<int>(i % 17);
  d.matches = 380;
  d.inliers = 350;
  d.times.lumaNs = 120'000;
  d.times.blurNs = 410'000;
  d.times.resizeNs = 230'000;
  d.times.overlapNs = 1'250'000;
  d.times.totalNs = 2'010'000;
  return d;
}

TEST(OutputAllocations, TheCounterSeesThisThreadOnly) {
  bench::setCountingThisThread(true);
  const std::uint64_t before = bench::allocations();
  std::vector<int> mine(100);
  const std::uint64_t seen = bench::allocations() - before;
  std::uint64_t other = 0;
  std::thread([&] {
    const std::uint64_t b = bench::allocations();
    std::vector<int> theirs(100);
    other = bench::allocations() - b;
    EXPECT_EQ(theirs.size(), 100u);
  }).join();
  bench::setCountingThisThread(false);
  EXPECT_GE(seen, 1u);  // otherwise a zero below would prove nothing
  EXPECT_EQ(mine.size(), 100u);
  EXPECT_EQ(other, 0u);  // the other thread's vector is not counted
}

// The output thread's work for a frame that is no keyframe, KeyframeOutput::handle
// (the decisions file, the scores, the record's decision row), and the preview
// frame queued to the flight record, for CSV and JSON-lines decision files.
TEST(OutputAllocations, NonePerFrameForTheDecisionRowsAndTheRecord) {
  for (const DecisionFormat format : {DecisionFormat::Csv, DecisionFormat::JsonLines}) {
    SCOPED_TRACE(format == DecisionFormat::Csv ? "csv" : "jsonl");
    const fs::path dir = freshDir(format == DecisionFormat::Csv ? "csv" : "jsonl");
    std::string error;
    KeyframeWriter writer;
    KeyframeWriterConfig wc;
    wc.dir = dir.string();
    ASSERT_TRUE(writer.open(wc, error)) << error;
    DecisionLog log;
    ASSERT_TRUE(log.open((dir / "decisions").string(), format, error)) << error;
    FlightOutputs outputs;
    FlightOutputOptions fo;
    fo.mcapPath = (dir / "flight.mcap").string();
    fo.mcapCompression = "none";
    fo.liveClock = false;
    ASSERT_TRUE(outputs.open(fo, 1920, 1080, nullptr, error)) << error;
    KeyframeOutput output(writer, log, outputs, nullptr, 0);
    // A 640x360 preview JPEG's size; its bytes do not matter to the record.
    std::vector<std::uint8_t> preview(42'000);
    for (std::size_t i = 0; i < preview.size(); ++i) preview[i] = static_cast<std::uint8_t>(i * 7);

    constexpr int kWarmup = 400, kCounted = 400;
    std::uint64_t counted = 0, base = 0;
    for (int i = 0; i < kWarmup + kCounted; ++i) {
      KeyframeEvent ev;
      ev.decision = decisionAt(i);
      const bool count = i >= kWarmup;
      if (i == kWarmup) base = outputs.recordedMessages();
      if (count) {
        // The writer keeps up, as it does with a camera (a stalled writer would leave
        // the frame no spare buffer: not what is counted here). Two messages a frame.
        const auto wanted = base + 2 * static_cast<std::uint64_t>(i - kWarmup);
        const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
        while (outputs.recordedMessages() < wanted && std::chrono::steady_clock::now() < deadline)
          std::this_thread::sleep_for(std::chrono::milliseconds(1));
        ASSERT_GE(outputs.recordedMessages(), wanted) << "the MCAP writer stalled for 10 s";
      }
      if (count) bench::setCountingThisThread(true);
      const std::uint64_t before = bench::allocations();
      ASSERT_TRUE(output.handle(ev, error)) << error;
      outputs.preview(ev.decision.timestampNs, preview, "jpeg");
      counted += bench::allocations() - before;
      bench::setCountingThisThread(false);
      // A burst while warming up (so that the recorder holds spare buffers), then a
      // frame every 2 ms.
      if (i >= kWarmup / 2) std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
    EXPECT_EQ(counted, 0u) << "allocations in " << kCounted << " frames";
    ASSERT_TRUE(outputs.close("done", error)) << error;
    ASSERT_TRUE(log.close(error)) << error;
    // Every row reached the file: the rows were written, not skipped.
    std::ifstream in(dir / "decisions");
    int lines = 0;
    for (std::string line; std::getline(in, line);) ++lines;
    EXPECT_EQ(lines, kWarmup + kCounted + (format == DecisionFormat::Csv ? 1 : 0));
    fs::remove_all(dir);
  }
}

// The preview of a 1080p camera frame (YUV420, NV12, YUYV: scaled plane by plane):
// the encoder's own work allocates nothing, so a frame costs what libjpeg-turbo
// alone costs for the 640x360 picture. (A file source's BGR frames go through
// OpenCV's resize, which allocates: not counted here.)
TEST(OutputAllocations, ThePreviewAddsNothingToTheJpegLibrarys) {
  cv::Mat bgr(1080, 1920, CV_8UC3);
  cv::randu(bgr, 0, 255);
  cv::GaussianBlur(bgr, bgr, cv::Size(9, 9), 3);
  cv::Mat i420, nv12;
  cv::cvtColor(bgr, i420, cv::COLOR_BGR2YUV_I420);
  {
    // NV12 from I420: the same luma, chroma interleaved.
    nv12.create(1620, 1920, CV_8UC1);
    i420.rowRange(0, 1080).copyTo(nv12.rowRange(0, 1080));
    const std::uint8_t* u = i420.ptr(1080);
    const std::uint8_t* v = u + 960 * 540;
    std::uint8_t* uv = nv12.ptr(1080);
    for (int k = 0; k < 960 * 540; ++k) {
      uv[2 * k] = u[k];
      uv[2 * k + 1] = v[k];
    }
  }
  // YUYV (4:2:2) from the same planes: each chroma row twice.
  cv::Mat yuyv(1080, 1920, CV_8UC2);
  {
    const std::uint8_t* u = i420.ptr(1080);
    const std::uint8_t* v = u + 960 * 540;
    for (int r = 0; r < 1080; ++r) {
      const std::uint8_t* y = i420.ptr(r);
      std::uint8_t* out = yuyv.ptr(r);
      for (int k = 0; k < 960; ++k) {
        out[4 * k] = y[2 * k];
        out[4 * k + 1] = u[(r / 2) * 960 + k];
        out[4 * k + 2] = y[2 * k + 1];
        out[4 * k + 3] = v[(r / 2) * 960 + k];
      }
    }
  }
  const struct {
    const char* name;
    Frame frame;
  } cases[] = {
      {"YUV420", Frame{PixelFormat::YUV420, i420.data, 1920, 1080, 1920, 0, 0}},
      {"NV12", Frame{PixelFormat::NV12, nv12.data, 1920, 1080, 1920, 0, 0}},
      {"YUYV", Frame{PixelFormat::YUYV, yuyv.data, 1920, 1080, 3840, 0, 0}},
  };
  for (const auto& c : cases) {
    SCOPED_TRACE(c.name);
    PreviewEncoder preview(640);
    std::vector<std::uint8_t> out;
    constexpr int kWarmup = 5, kCounted = 20;
    std::uint64_t previewAllocs = 0;
    for (int i = 0; i < kWarmup + kCounted; ++i) {
      if (i >= kWarmup) bench::setCountingThisThread(true);
      const std::uint64_t before = bench::allocations();
      ASSERT_TRUE(preview.encode(c.frame, out)) << preview.error();
      previewAllocs += bench::allocations() - before;
      bench::setCountingThisThread(false);
    }
    ASSERT_STREQ(preview.format(), "jpeg");
    const cv::Mat picture = cv::imdecode(out, cv::IMREAD_COLOR);
    ASSERT_EQ(picture.cols, 640);
    ASSERT_EQ(picture.rows, 360);

    // The picture is the frame's: its mean colour within a few levels of the frame's
    // (YUYV's chroma de-interleaved right, not swapped or shifted).
    const cv::Scalar want = cv::mean(bgr), got = cv::mean(picture);
    for (int ch = 0; ch < 3; ++ch) EXPECT_NEAR(got[ch], want[ch], 3.0) << "channel " << ch;

    // libjpeg-turbo alone on a 640x360 picture from YUV planes.
    cv::Mat small;
    cv::resize(bgr, small, cv::Size(640, 360), 0, 0, cv::INTER_AREA);
    cv::Mat smallI420;
    cv::cvtColor(small, smallI420, cv::COLOR_BGR2YUV_I420);
    const Frame planes{PixelFormat::YUV420, smallI420.data, 640, 360, 640, 0, 0};
    JpegEncoder jpeg;
    std::vector<std::uint8_t> alone;
    std::uint64_t jpegAllocs = 0;
    for (int i = 0; i < kWarmup + kCounted; ++i) {
      std::string error;
      if (i >= kWarmup) bench::setCountingThisThread(true);
      const std::uint64_t before = bench::allocations();
      const bool ok = jpeg.encode(planes, 85, alone, error);
      jpegAllocs += bench::allocations() - before;
      bench::setCountingThisThread(false);
      ASSERT_TRUE(ok) << error;
    }
    EXPECT_GT(jpegAllocs, 0u) << "libjpeg-turbo was expected to allocate its work memory";
    EXPECT_EQ(previewAllocs, jpegAllocs)
        << "per frame: preview " << static_cast<double>(previewAllocs) / kCounted
        << ", libjpeg-turbo alone " << static_cast<double>(jpegAllocs) / kCounted;
  }
}

}  // namespace
}  // namespace keyframed
