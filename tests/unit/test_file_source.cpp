#include <chrono>
#include <filesystem>
#include <fstream>
#include <memory>
#include <thread>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>

#include "app/paced_source.h"
#include "capture/file_source.h"
#include "photos.h"
#include "telemetry/link.h"
#include "temp_dir.h"

namespace keyframed {
namespace {

std::string writeVideo(const std::string& name, int frames) {
  const std::string path = (test::processTempDir("keyframed-unit") / name).string();
  cv::VideoWriter w(path, cv::VideoWriter::fourcc('M', 'J', 'P', 'G'), 30.0, cv::Size(320, 180));
  EXPECT_TRUE(w.isOpened());
  const cv::Mat strip = test::photoStrip();
  for (int i = 0; i < frames; ++i) {
    cv::Mat g = test::viewAt(strip, 100 + 4 * i, 320, 180), bgr;
    cv::cvtColor(g, bgr, cv::COLOR_GRAY2BGR);
    w.write(bgr);
  }
  return path;
}

TEST(FileSource, ReadsEveryFrameWithTimestamps) {
  const std::string path = writeVideo("ok.avi", 20);
  std::string err;
  auto src = FileSource::open(path, err);
  ASSERT_TRUE(src) << err;
  EXPECT_EQ(src->info().width, 320);
  EXPECT_NEAR(src->info().fps, 30.0, 0.01);
  Frame f;
  std::int64_t n = 0, lastTs = -1;
  while (src->next(f, err) == ReadStatus::Frame) {
    EXPECT_EQ(f.index, n);
    EXPECT_GT(f.timestampNs, lastTs);
    lastTs = f.timestampNs;
    ++n;
  }
  EXPECT_EQ(n, 20);
  EXPECT_NEAR(static_cast<double>(lastTs), 19 / 30.0 * 1e9, 2e6);
}

TEST(FileSource, MissingFileAndNonVideoAreClearErrors) {
  std::string err;
  EXPECT_FALSE(FileSource::open("/no/such/video.avi", err));
  EXPECT_NE(err.find("no such file"), std::string::npos);
  const std::string junk = (test::processTempDir("keyframed-unit") / "junk.avi").string();
  std::ofstream(junk) << "this is not a video at all";
  err.clear();
  EXPECT_FALSE(FileSource::open(junk, err));
  EXPECT_NE(err.find("not a readable video"), std::string::npos);
}

TEST(FileSource, TruncatedVideoEndsWithAnErrorAfterTheGoodFrames) {
  const std::string path = writeVideo("full.avi", 60);
  const std::string cut = (test::processTempDir("keyframed-unit") / "cut.avi").string();
  std::filesystem::copy_file(path, cut, std::filesystem::copy_options::overwrite_existing);
  std::filesystem::resize_file(cut, std::filesystem::file_size(path) / 2);
  std::string err;
  auto src = FileSource::open(cut, err);
  ASSERT_TRUE(src) << err;
  Frame f;
  ReadStatus st;
  std::int64_t n = 0;
  while ((st = src->next(f, err)) == ReadStatus::Frame) ++n;
  EXPECT_GT(n, 5);
  EXPECT_LT(n, 60);
  EXPECT_EQ(st, ReadStatus::Error);
  EXPECT_TRUE(src->truncated());
  EXPECT_NE(err.find("ended early"), std::string::npos);
  EXPECT_NE(err.find(cut), std::string::npos);
  // Permanent: a capture thread stops instead of asking again; asking again repeats it.
  EXPECT_TRUE(src->failed());
  std::string again;
  EXPECT_EQ(src->next(f, again), ReadStatus::Error);
  EXPECT_EQ(again, err);
}

// An MPEG-TS has no frame index; a cut is found by the last packet being partial.
TEST(FileSource, TransportStreamCutMidPacketIsTruncated) {
  const std::string whole = (test::processTempDir("keyframed-unit") / "whole.ts").string();
  {
    cv::VideoWriter w(whole, cv::VideoWriter::fourcc('m', 'p', '4', 'v'), 30.0, cv::Size(320, 180));
    ASSERT_TRUE(w.isOpened());
    const cv::Mat strip = test::photoStrip();
    for (int i = 0; i < 40; ++i) {
      cv::Mat bgr;
      cv::cvtColor(test::viewAt(strip, 100 + 4 * i, 320, 180), bgr, cv::COLOR_GRAY2BGR);
      w.write(bgr);
    }
  }
  const auto size = std::filesystem::file_size(whole);
  ASSERT_EQ(size % 188, 0U);
  const auto readAll = [](const std::string& path, std::string& err) {
    auto src = FileSource::open(path, err);
    EXPECT_TRUE(src) << err;
    if (!src) return std::make_pair(ReadStatus::Error, std::int64_t{0});
    Frame f;
    ReadStatus st;
    std::int64_t n = 0;
    while ((st = src->next(f, err)) == ReadStatus::Frame) ++n;
    EXPECT_EQ(src->truncated(), st == ReadStatus::Error);
    return std::make_pair(st, n);
  };
  std::string err;
  const auto [wholeStatus, wholeFrames] = readAll(whole, err);
  EXPECT_EQ(wholeStatus, ReadStatus::End) << err;
  EXPECT_EQ(wholeFrames, 40);

  const std::string cut = (test::processTempDir("keyframed-unit") / "cut.ts").string();
  std::filesystem::copy_file(whole, cut, std::filesystem::copy_options::overwrite_existing);
  std::filesystem::resize_file(cut, (size / 2 / 188) * 188 + 77);
  err.clear();
  const auto [cutStatus, cutFrames] = readAll(cut, err);
  EXPECT_EQ(cutStatus, ReadStatus::Error);
  EXPECT_GT(cutFrames, 5);
  EXPECT_LT(cutFrames, 40);
  EXPECT_NE(err.find("transport packet"), std::string::npos) << err;
}

TEST(FileSource, AWholeVideoHasNotFailed) {
  const std::string path = writeVideo("whole.avi", 10);
  std::string err;
  auto src = FileSource::open(path, err);
  ASSERT_TRUE(src) << err;
  Frame f;
  while (src->next(f, err) == ReadStatus::Frame) {
  }
  EXPECT_FALSE(src->failed());
  EXPECT_EQ(src->next(f, err), ReadStatus::End);
}

// A colour video of a real photo, `size`, three frames, lossless enough to compare.
std::string writeColourVideo(const std::string& name, cv::Size size) {
  const std::string path = (test::processTempDir("keyframed-unit") / name).string();
  cv::VideoWriter w(path, cv::VideoWriter::fourcc('M', 'J', 'P', 'G'), 30.0, size);
  EXPECT_TRUE(w.isOpened());
  const cv::Mat fruits = test::photo("fruits.jpg", cv::IMREAD_COLOR);
  for (int i = 0; i < 3; ++i) w.write(fruits(cv::Rect(cv::Point(4 * i, 0), size)));
  return path;
}

TEST(FileSource, DeliversYuvAsACameraWould) {
  const std::string path = writeColourVideo("colour.avi", cv::Size(320, 180));
  std::string err;
  auto bgrSrc = FileSource::open(path, err);
  auto i420Src = FileSource::open(path, err);
  auto nv12Src = FileSource::open(path, err);
  ASSERT_TRUE(bgrSrc && i420Src && nv12Src) << err;
  ASSERT_TRUE(i420Src->setOutputFormat(PixelFormat::YUV420, err)) << err;
  ASSERT_TRUE(nv12Src->setOutputFormat(PixelFormat::NV12, err)) << err;
  Frame bgr, i420, nv12;
  for (int n = 0; n < 3; ++n) {
    ASSERT_EQ(bgrSrc->next(bgr, err), ReadStatus::Frame) << err;
    ASSERT_EQ(i420Src->next(i420, err), ReadStatus::Frame) << err;
    ASSERT_EQ(nv12Src->next(nv12, err), ReadStatus::Frame) << err;
    EXPECT_EQ(bgr.format, PixelFormat::BGR24);
    EXPECT_EQ(i420.format, PixelFormat::YUV420);
    EXPECT_EQ(nv12.format, PixelFormat::NV12);
    for (const Frame* f : {&i420, &nv12}) {
      EXPECT_EQ(f->index, bgr.index);
      EXPECT_EQ(f->timestampNs, bgr.timestampNs);
      EXPECT_EQ(f->width, 320);
      EXPECT_EQ(f->height, 180);
      EXPECT_EQ(f->stride, 320);
    }
    // Converted back, each is the decoded picture (BT.601 limited range both ways).
    const cv::Mat decoded(180, 320, CV_8UC3, const_cast<std::uint8_t*>(bgr.data),
                          static_cast<std::size_t>(bgr.stride));
    cv::Mat fromI420, fromNv12;
    cv::cvtColor(cv::Mat(270, 320, CV_8UC1, const_cast<std::uint8_t*>(i420.data)), fromI420,
                 cv::COLOR_YUV2BGR_I420);
    cv::cvtColor(cv::Mat(270, 320, CV_8UC1, const_cast<std::uint8_t*>(nv12.data)), fromNv12,
                 cv::COLOR_YUV2BGR_NV12);
    EXPECT_GT(cv::PSNR(fromI420, decoded), 30.0);
    EXPECT_EQ(cv::norm(fromI420, fromNv12, cv::NORM_INF), 0.0);  // the same samples
  }
}

TEST(FileSource, CameraFormatsAVideoCannotBeDeliveredInAreRefused) {
  std::string err;
  auto src = FileSource::open(writeVideo("fmt.avi", 2), err);
  ASSERT_TRUE(src) << err;
  EXPECT_FALSE(src->setOutputFormat(PixelFormat::YUYV, err));
  EXPECT_NE(err.find("YUYV"), std::string::npos) << err;
  // OpenCV's writer rounds sizes to even; a YUV4MPEG2 stream, written by hand, does not.
  const std::string oddPath = (test::processTempDir("keyframed-unit") / "odd.y4m").string();
  {
    std::ofstream y4m(oddPath, std::ios::binary);
    y4m << "YUV4MPEG2 W161 H91 F30:1 Ip A1:1 C420jpeg\n";
    for (int n = 0; n < 3; ++n) {
      y4m << "FRAME\n"
          << std::string(161 * 91, static_cast<char>(90 + 10 * n))
          << std::string(2 * 81 * 46, static_cast<char>(128));
    }
  }
  auto odd = FileSource::open(oddPath, err);
  ASSERT_TRUE(odd) << err;
  ASSERT_EQ(odd->info().width, 161);
  EXPECT_FALSE(odd->setOutputFormat(PixelFormat::NV12, err));
  EXPECT_NE(err.find("even width and height"), std::string::npos) << err;
  EXPECT_TRUE(odd->setOutputFormat(PixelFormat::BGR24, err)) << err;
}

// Frames at the given times in the file (ns), as after gaps in a recording.
class GapSource final : public FrameSource {
 public:
  explicit GapSource(std::vector<std::int64_t> times) : times_(std::move(times)) {
    info_.fps = 30.0;
  }
  const SourceInfo& info() const override { return info_; }
  ReadStatus next(Frame& f, std::string&) override {
    if (n_ >= static_cast<std::int64_t>(times_.size())) return ReadStatus::End;
    f = Frame{PixelFormat::Gray8, pixel_, 1, 1, 1, times_[static_cast<std::size_t>(n_)], n_};
    ++n_;
    return ReadStatus::Frame;
  }

 private:
  SourceInfo info_;
  std::vector<std::int64_t> times_;
  std::uint8_t pixel_[1] = {0};
  std::int64_t n_ = 0;
};

TEST(PacedSource, InterruptEndsTheWaitForAFramesTime) {
  // The second frame 1.5 s on: a wait, not a jump.
  PacedSource src(std::make_unique<GapSource>(std::vector<std::int64_t>{0, 1'500'000'000}),
                  /*realtime=*/true, std::nullopt);
  Frame f;
  std::string err;
  ASSERT_EQ(src.next(f, err), ReadStatus::Frame);
  std::thread stopper([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    src.interrupt();
  });
  const auto t0 = std::chrono::steady_clock::now();
  EXPECT_EQ(src.next(f, err), ReadStatus::Error);  // due in 1.5 s
  const auto took = std::chrono::steady_clock::now() - t0;
  stopper.join();
  EXPECT_LT(took, std::chrono::milliseconds(1000));
  EXPECT_EQ(err, "interrupted: waiting for a frame's time");
}

// A jump of a minute forward, then of a minute back (files joined, a clock reset):
// delivered a frame period apart, neither waited out nor raced through.
TEST(PacedSource, AJumpInTheTimestampsRestartsThePacing) {
  const std::int64_t ms = 1'000'000;
  PacedSource src(std::make_unique<GapSource>(std::vector<std::int64_t>{
                      0, 33 * ms, 60'000 * ms, 60'033 * ms, 66 * ms, 99 * ms, 132 * ms}),
                  /*realtime=*/true, std::nullopt);
  Frame f;
  std::string err;
  std::vector<std::int64_t> at;
  const auto t0 = std::chrono::steady_clock::now();
  while (src.next(f, err) == ReadStatus::Frame) at.push_back(f.timestampNs);
  const auto took = std::chrono::steady_clock::now() - t0;
  ASSERT_EQ(at.size(), 7U) << err;
  // Not waited out: a minute forward took no minute.
  EXPECT_LT(took, std::chrono::milliseconds(1500));
  // Not raced through: each frame is due a period after the one before, the jumps
  // included, so the last is due six periods after the first (delivered then or,
  // on a busy machine, later; never earlier). Racing through the jump back would
  // deliver the last three at once, three periods (100 ms) sooner.
  EXPECT_GE(at.back() - at.front(), 180 * ms);  // six periods: 200 ms
}

// A step back under the jump limit (half a second: MPEG-TS, files joined) and a
// repeated timestamp: frame times still only go forward, a period apart.
TEST(PacedSource, FrameTimesNeverGoBackwards) {
  const std::int64_t ms = 1'000'000;
  PacedSource src(std::make_unique<GapSource>(std::vector<std::int64_t>{
                      0, 33 * ms, 600 * ms, 633 * ms, 133 * ms, 133 * ms, 166 * ms}),
                  /*realtime=*/true, std::nullopt);
  Frame f;
  std::string err;
  std::vector<std::int64_t> at;
  while (src.next(f, err) == ReadStatus::Frame) at.push_back(f.timestampNs);
  ASSERT_EQ(at.size(), 7U) << err;
  for (std::size_t i = 1; i < at.size(); ++i) EXPECT_GT(at[i], at[i - 1]) << i;
  // The step back and the repeat: a period on from the frame before.
  EXPECT_GE(at[4] - at[3], 30 * ms);
  EXPECT_GE(at[5] - at[4], 30 * ms);
}

// A camera delivers a frame after it captured it, never before: each frame is
// handed over no earlier than the monotonic time it is stamped with, so that a
// keyframe's capture time never follows the time it was decided at. Frame times
// that fall inside a millisecond, as 30 fps does.
TEST(PacedSource, NoFrameIsHandedOverBeforeItsStamp) {
  std::vector<std::int64_t> times;
  for (int n = 0; n < 40; ++n) times.push_back(n * 1'000'000'000LL / 301);
  PacedSource src(std::make_unique<GapSource>(times), /*realtime=*/true, std::nullopt);
  Frame f;
  std::string err;
  int frames = 0;
  while (src.next(f, err) == ReadStatus::Frame) {
    const std::int64_t handedOver = monotonicNowNs();
    EXPECT_LE(f.timestampNs, handedOver) << "frame " << frames;
    ++frames;
  }
  EXPECT_EQ(frames, 40) << err;
}

// A reader that comes late (a busy machine) gets the frames at once, each stamped
// with the time it was due, a period apart, as a camera stamps its frames when it
// captures them: not with the time it was read.
TEST(PacedSource, ALateReaderGetsTheFramesStampedWhenTheyWereDue) {
  const std::int64_t ms = 1'000'000;
  PacedSource src(
      std::make_unique<GapSource>(std::vector<std::int64_t>{0, 33 * ms, 66 * ms, 99 * ms}),
      /*realtime=*/true, std::nullopt);
  Frame f;
  std::string err;
  ASSERT_EQ(src.next(f, err), ReadStatus::Frame);
  const std::int64_t first = f.timestampNs;
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  std::vector<std::int64_t> at;
  while (src.next(f, err) == ReadStatus::Frame) at.push_back(f.timestampNs - first);
  ASSERT_EQ(at.size(), 3U) << err;
  EXPECT_EQ(at, (std::vector<std::int64_t>{33 * ms, 66 * ms, 99 * ms}));
}

}  // namespace
}  // namespace keyframed
