// V4l2Source::next() against a driver in memory (V4l2Io): the MJPEG path with its
// early requeue, raw buffers lent until the next call, a lost device reopened, and
// interrupt() ending a wait for a frame or for the device to come back. vivid under
// qemu covers the kernel side (tests/harness/test_v4l2_vivid.py); vivid has no MJPEG.

#include <linux/videodev2.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <deque>
#include <memory>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include <gtest/gtest.h>
#include <turbojpeg.h>

#include "capture/v4l2_source.h"

namespace keyframed {
namespace {

using namespace std::chrono_literals;
using SteadyClock = std::chrono::steady_clock;

constexpr int kWidth = 64;
constexpr int kHeight = 48;
constexpr std::size_t kBufferBytes = 64 * 1024;

std::vector<std::uint8_t> jpegOf(int w, int h, std::uint8_t green) {
  std::vector<unsigned char> bgr(static_cast<std::size_t>(w * h * 3), 0);
  for (std::size_t i = 1; i < bgr.size(); i += 3) bgr[i] = green;
  tjhandle tj = tjInitCompress();
  unsigned char* out = nullptr;
  unsigned long size = 0;
  EXPECT_EQ(tjCompress2(tj, bgr.data(), w, w * 3, h, TJPF_BGR, &out, &size, TJSAMP_422, 95, 0), 0);
  std::vector<std::uint8_t> jpeg(out, out + size);
  tjFree(out);
  tjDestroy(tj);
  return jpeg;
}

// A capture driver in memory: one format at 64x48, mmap buffers, and a queue the
// test fills. Its descriptor is an eventfd, readable while a filled buffer waits.
class FakeDriver final : public V4l2Io {
 public:
  explicit FakeDriver(std::uint32_t fourcc) : fourcc_(fourcc) {}
  ~FakeDriver() override {
    if (fd_ >= 0) ::close(fd_);
  }

  bool present = true;           // false: unplugged (open fails, DQBUF says ENODEV)
  std::uint32_t width = kWidth;  // the frame size S_FMT settles on
  std::uint32_t height = kHeight;
  std::vector<std::uint8_t> onStreamOn;  // a frame delivered when streaming starts
  std::string card = "fake camera";      // (under 32 characters)
  std::string busInfo = "usb-0000:01:00.0-1.2";
  std::string path = "/dev/video-fake";  // the node it is on

  bool exists(const std::string& p) override { return present && p == path; }
  int open(const std::string& p) override {
    if (!present || p != path) return fail(ENOENT);
    fd_ = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    ++opens;
    return fd_;
  }
  int close(int fd) override {
    ::close(fd);
    fd_ = -1;
    return 0;
  }
  void* mmap(std::size_t, int, std::int64_t offset) override {
    return memory_.at(static_cast<std::size_t>(offset) / kBufferBytes).data();
  }
  int munmap(void*, std::size_t) override { return 0; }
  int ioctl(int, unsigned long request, void* arg) override {
    switch (request) {
      case VIDIOC_QUERYCAP: {
        auto* c = static_cast<v4l2_capability*>(arg);
        std::strcpy(reinterpret_cast<char*>(c->driver), "fake");
        std::strcpy(reinterpret_cast<char*>(c->card), card.c_str());
        std::strcpy(reinterpret_cast<char*>(c->bus_info), busInfo.c_str());
        c->capabilities = V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_STREAMING;
        return 0;
      }
      case VIDIOC_ENUM_FMT: {
        auto* d = static_cast<v4l2_fmtdesc*>(arg);
        if (d->index > 0) return fail(EINVAL);
        d->pixelformat = fourcc_;
        return 0;
      }
      case VIDIOC_G_FMT:
      case VIDIOC_S_FMT: {
        auto& pix = static_cast<v4l2_format*>(arg)->fmt.pix;
        pix.pixelformat = fourcc_;
        pix.width = width;
        pix.height = height;
        pix.field = V4L2_FIELD_NONE;
        pix.bytesperline = fourcc_ == V4L2_PIX_FMT_YUYV ? width * 2 : 0;
        pix.sizeimage = kBufferBytes;
        return 0;
      }
      case VIDIOC_REQBUFS: {
        auto* r = static_cast<v4l2_requestbuffers*>(arg);
        r->count = std::min(r->count, 4u);
        memory_.assign(r->count, std::vector<std::uint8_t>(kBufferBytes));
        queued_.clear();
        filled_.clear();
        return 0;
      }
      case VIDIOC_QUERYBUF: {
        auto* b = static_cast<v4l2_buffer*>(arg);
        b->length = kBufferBytes;
        b->m.offset = b->index * kBufferBytes;
        return 0;
      }
      case VIDIOC_QBUF: queued_.push_back(static_cast<v4l2_buffer*>(arg)->index); return 0;
      case VIDIOC_DQBUF: {
        if (!present) return fail(ENODEV);
        if (filled_.empty()) return fail(EAGAIN);
        auto* b = static_cast<v4l2_buffer*>(arg);
        const Filled f = filled_.front();
        filled_.pop_front();
        b->index = f.index;
        b->bytesused = static_cast<std::uint32_t>(f.used);
        b->flags = V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC;
        b->sequence = f.sequence;
        b->timestamp.tv_sec = 100 + b->sequence;
        if (filled_.empty()) {
          std::uint64_t n = 0;
          [[maybe_unused]] const ssize_t r = ::read(fd_, &n, sizeof n);  // no longer readable
        }
        return 0;
      }
      case VIDIOC_STREAMON:
        if (!onStreamOn.empty()) deliver(std::exchange(onStreamOn, {}));
        return 0;
      case VIDIOC_STREAMOFF: return 0;
      default: return fail(ENOTTY);  // G_PARM/S_PARM: no frame-rate control
    }
  }

  // Fills the buffer the driver has held longest with `bytes`; false when the
  // source holds every buffer: the frame is lost, and its sequence number with it,
  // as a real driver does.
  bool deliver(const std::vector<std::uint8_t>& bytes) {
    const std::uint32_t sequence = sequence_++;
    if (queued_.empty()) return false;
    const std::uint32_t index = queued_.front();
    queued_.pop_front();
    std::copy(bytes.begin(), bytes.end(), memory_[index].begin());
    filled_.push_back({index, bytes.size(), sequence});
    const std::uint64_t one = 1;
    [[maybe_unused]] const ssize_t r = ::write(fd_, &one, sizeof one);
    return true;
  }
  [[nodiscard]] std::size_t queued() const { return queued_.size(); }
  int opens = 0;

 private:
  struct Filled {
    std::uint32_t index;
    std::size_t used;
    std::uint32_t sequence;
  };
  static int fail(int err) {
    errno = err;
    return -1;
  }
  std::uint32_t fourcc_;
  int fd_ = -1;
  std::vector<std::vector<std::uint8_t>> memory_;
  std::deque<std::uint32_t> queued_;
  std::deque<Filled> filled_;
  std::uint32_t sequence_ = 0;
};

std::unique_ptr<V4l2Source> openFake(const std::shared_ptr<FakeDriver>& driver,
                                     bool autoReopen = false, int reopenIntervalMs = 10,
                                     int timeoutMs = 2000) {
  V4l2Options o;
  o.device = "/dev/video-fake";
  o.io = driver;
  o.timeoutMs = timeoutMs;
  o.autoReopen = autoReopen;
  o.reopenIntervalMs = reopenIntervalMs;
  std::string err;
  auto src = V4l2Source::open(o, err);
  EXPECT_NE(src, nullptr) << err;
  return src;
}

TEST(V4l2FakeDriver, MjpegFramesAreDecodedAndTheirBuffersRequeuedAtOnce) {
  auto driver = std::make_shared<FakeDriver>(V4L2_PIX_FMT_MJPEG);
  auto src = openFake(driver);
  ASSERT_NE(src, nullptr);
  EXPECT_EQ(src->fourcc(), "MJPG");
  EXPECT_EQ(src->pixelFormat(), PixelFormat::BGR24);
  EXPECT_EQ(driver->queued(), 4u);

  ASSERT_TRUE(driver->deliver(jpegOf(kWidth, kHeight, 200)));
  Frame f;
  std::string err;
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(f.format, PixelFormat::BGR24);
  EXPECT_EQ(f.width, kWidth);
  EXPECT_EQ(f.stride, kWidth * 3);
  EXPECT_NEAR(f.data[(24 * kWidth + 32) * 3 + 1], 200, 8);  // green, from the JPEG
  EXPECT_EQ(f.timestampNs, 100'000'000'000LL);              // the driver's time
  EXPECT_EQ(driver->queued(), 4u);  // the picture lives in the decoder: buffer back already

  // A JPEG of another size is skipped and counted; the next good one comes through.
  ASSERT_TRUE(driver->deliver(jpegOf(32, 32, 50)));
  ASSERT_TRUE(driver->deliver(jpegOf(kWidth, kHeight, 120)));
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_NEAR(f.data[(24 * kWidth + 32) * 3 + 1], 120, 8);
  EXPECT_EQ(f.index, 1);
  EXPECT_EQ(src->corruptFrames(), 1u);
  EXPECT_EQ(driver->queued(), 4u);
}

TEST(V4l2FakeDriver, RawBuffersAreLentUntilTheNextCall) {
  auto driver = std::make_shared<FakeDriver>(V4L2_PIX_FMT_YUYV);
  auto src = openFake(driver);
  ASSERT_NE(src, nullptr);
  std::vector<std::uint8_t> yuyv(kWidth * 2 * kHeight, 77);
  ASSERT_TRUE(driver->deliver(yuyv));
  Frame f;
  std::string err;
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(f.format, PixelFormat::YUYV);
  EXPECT_EQ(f.data[0], 77);
  EXPECT_EQ(driver->queued(), 3u);  // no copy: the source holds the buffer
  ASSERT_TRUE(driver->deliver(yuyv));
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(driver->queued(), 3u);  // the first one went back
  // A short frame (bytesused) is skipped and counted.
  ASSERT_TRUE(driver->deliver(std::vector<std::uint8_t>(100, 1)));
  ASSERT_TRUE(driver->deliver(yuyv));
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(src->corruptFrames(), 1u);
  // An empty buffer (bytesused 0: a payload lost on the bus) still holds an older
  // picture; it is skipped and counted, not delivered as a new frame.
  ASSERT_TRUE(driver->deliver(std::vector<std::uint8_t>(yuyv.size(), 11)));
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  for (int i = 0; i < 2; ++i) ASSERT_TRUE(driver->deliver({}));
  ASSERT_TRUE(driver->deliver(std::vector<std::uint8_t>(yuyv.size(), 22)));
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(f.data[0], 22);
  EXPECT_EQ(src->corruptFrames(), 3u);
}

TEST(V4l2FakeDriver, AnImplausibleFrameSizeIsRefused) {
  auto driver = std::make_shared<FakeDriver>(V4L2_PIX_FMT_YUYV);
  driver->width = 70000;  // its byte count would overflow a 32-bit size_t
  V4l2Options o;
  o.device = "/dev/video-fake";
  o.io = driver;
  std::string err;
  EXPECT_EQ(V4l2Source::open(o, err), nullptr);
  EXPECT_NE(err.find("unusable frame size: 70000x48"), std::string::npos) << err;
}

TEST(V4l2FakeDriver, AnOddSizeIn420IsRefusedSayingWhatToSet) {
  for (const std::uint32_t fourcc : {V4L2_PIX_FMT_NV12, V4L2_PIX_FMT_YUV420}) {
    auto driver = std::make_shared<FakeDriver>(fourcc);
    driver->width = 641;  // granted by a driver: the preview's conversion would throw
    V4l2Options o;
    o.device = "/dev/video-fake";
    o.io = driver;
    std::string err;
    EXPECT_EQ(V4l2Source::open(o, err), nullptr);
    EXPECT_NE(err.find("4:2:0 needs an even width and height"), std::string::npos) << err;
  }
}

TEST(V4l2FakeDriver, FramesTheDriverHadNoBufferForAreCountedLost) {
  auto driver = std::make_shared<FakeDriver>(V4L2_PIX_FMT_YUYV);
  auto src = openFake(driver);
  ASSERT_NE(src, nullptr);
  const std::vector<std::uint8_t> yuyv(kWidth * 2 * kHeight, 60);
  Frame f;
  std::string err;
  ASSERT_TRUE(driver->deliver(yuyv));
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;  // holds one buffer
  // The capture thread falls behind: three frames fill the ring, two find no buffer.
  for (int i = 0; i < 3; ++i) ASSERT_TRUE(driver->deliver(yuyv));
  EXPECT_FALSE(driver->deliver(yuyv));
  EXPECT_FALSE(driver->deliver(yuyv));
  for (int i = 0; i < 3; ++i) ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(src->lostFrames(), 0u);  // not known until a frame after them comes
  ASSERT_TRUE(driver->deliver(yuyv));
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(src->sequenceGaps(), 2u);
  EXPECT_EQ(src->lostFrames(), 2u);
  EXPECT_EQ(f.index, 4);  // indices count the frames delivered
  // A broken frame counts as lost too.
  ASSERT_TRUE(driver->deliver(std::vector<std::uint8_t>(100, 1)));
  ASSERT_TRUE(driver->deliver(yuyv));
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(src->lostFrames(), 3u);
}

TEST(V4l2FakeDriver, ALostDeviceIsReopenedAndIndicesContinue) {
  auto driver = std::make_shared<FakeDriver>(V4L2_PIX_FMT_MJPEG);
  auto src = openFake(driver, /*autoReopen=*/true);
  ASSERT_NE(src, nullptr);
  const auto jpeg = jpegOf(kWidth, kHeight, 90);
  ASSERT_TRUE(driver->deliver(jpeg));
  Frame f;
  std::string err;
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  driver->present = false;
  ASSERT_TRUE(driver->deliver(jpeg));  // poll wakes, DQBUF says ENODEV
  EXPECT_EQ(src->next(f, err), ReadStatus::Error);
  EXPECT_EQ(err, "device lost: /dev/video-fake: No such device (VIDIOC_DQBUF)");
  EXPECT_TRUE(src->lost());
  EXPECT_FALSE(src->failed());  // it will try again
  EXPECT_EQ(src->next(f, err), ReadStatus::Error);
  EXPECT_NE(err.find("reopen attempt 1 failed: no such device"), std::string::npos) << err;
  driver->present = true;
  // The reopen happens inside next(), which then waits for a frame: the driver
  // delivers one as the new stream starts.
  driver->onStreamOn = jpeg;
  EXPECT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(driver->opens, 2);
  EXPECT_EQ(f.index, 1);
  EXPECT_EQ(src->reopenCount(), 1u);
}

TEST(V4l2FakeDriver, FramesWaitingFromBeforeTheStartAreHandedBackUnread) {
  // Filled while no one read (the daemon waited for telemetry): with the stamp of
  // when they are read they would pass for now.
  auto driver = std::make_shared<FakeDriver>(V4L2_PIX_FMT_YUYV);
  auto src = openFake(driver);
  ASSERT_NE(src, nullptr);
  const std::size_t bufferCount = driver->queued();
  ASSERT_GE(bufferCount, 2u);
  const std::vector<std::uint8_t> old(kWidth * kHeight * 2, 10);
  ASSERT_TRUE(driver->deliver(old));
  ASSERT_TRUE(driver->deliver(old));
  EXPECT_EQ(src->discardQueued(), 2u);
  EXPECT_EQ(driver->queued(), bufferCount);  // every buffer back with the driver
  EXPECT_EQ(src->discardQueued(), 0u);       // none waits now
  const std::vector<std::uint8_t> now(kWidth * kHeight * 2, 200);
  ASSERT_TRUE(driver->deliver(now));
  Frame f;
  std::string err;
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(f.data[0], 200);  // the new frame, not one from before
}

// One frame read from an MJPEG stream that reopens itself, then the device gone.
void loseAfterAFrame(FakeDriver& driver, V4l2Source& src, Frame& f, std::string& err) {
  ASSERT_TRUE(driver.deliver(jpegOf(kWidth, kHeight, 90)));
  ASSERT_EQ(src.next(f, err), ReadStatus::Frame) << err;
  driver.present = false;
  ASSERT_TRUE(driver.deliver(jpegOf(kWidth, kHeight, 90)));  // poll wakes, DQBUF: ENODEV
  EXPECT_EQ(src.next(f, err), ReadStatus::Error);
  EXPECT_TRUE(src.lost());
}

TEST(V4l2FakeDriver, AnotherCameraOnTheNodeIsNotTakenForTheLostOne) {
  // The same mode, another camera (another USB port): its frames would be tagged
  // with the lost camera's calibration and mount.
  auto driver = std::make_shared<FakeDriver>(V4L2_PIX_FMT_MJPEG);
  auto src = openFake(driver, /*autoReopen=*/true);
  ASSERT_NE(src, nullptr);
  Frame f;
  std::string err;
  loseAfterAFrame(*driver, *src, f, err);
  driver->present = true;
  driver->busInfo = "usb-0000:01:00.0-1.4";
  EXPECT_EQ(src->next(f, err), ReadStatus::Error);
  EXPECT_NE(err.find("another camera came back: fake camera (usb-0000:01:00.0-1.4), not "
                     "fake camera (usb-0000:01:00.0-1.2)"),
            std::string::npos)
      << err;
  // The lost one back on its port: frames again.
  driver->busInfo = "usb-0000:01:00.0-1.2";
  driver->onStreamOn = jpegOf(kWidth, kHeight, 90);
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
}

TEST(V4l2FakeDriver, APickedCameraThatComesBackOnAnotherNodeIsFollowedANamedOneIsNot) {
  for (const bool follow : {true, false}) {
    auto driver = std::make_shared<FakeDriver>(V4L2_PIX_FMT_MJPEG);
    driver->path = "/dev/video0";
    V4l2Options o;
    o.device = "/dev/video0";
    o.io = driver;
    o.autoReopen = true;
    o.reopenIntervalMs = 10;
    o.followCamera = follow;  // what run sets when camera.device is ""
    std::string err;
    auto src = V4l2Source::open(o, err);
    ASSERT_NE(src, nullptr) << err;
    Frame f;
    loseAfterAFrame(*driver, *src, f, err);
    // Back as /dev/video3 (its old node still held when it re-enumerated).
    driver->present = true;
    driver->path = "/dev/video3";
    driver->onStreamOn = jpegOf(kWidth, kHeight, 90);
    if (follow) {
      ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
      EXPECT_EQ(src->device().path, "/dev/video3");
      EXPECT_NE(src->info().description.find("v4l2:/dev/video3"), std::string::npos)
          << src->info().description;
    } else {
      EXPECT_EQ(src->next(f, err), ReadStatus::Error);
      EXPECT_NE(err.find("no such device: /dev/video0"), std::string::npos) << err;
    }
  }
}

TEST(V4l2FakeDriver, ADeviceThatComesBackAtAnotherSizeIsNotUsed) {
  auto driver = std::make_shared<FakeDriver>(V4L2_PIX_FMT_MJPEG);
  auto src = openFake(driver, /*autoReopen=*/true);
  ASSERT_NE(src, nullptr);
  Frame f;
  std::string err;
  loseAfterAFrame(*driver, *src, f, err);
  // Another camera on the node: the frames downstream were sized for the first.
  driver->present = true;
  driver->width = 32;
  EXPECT_EQ(src->next(f, err), ReadStatus::Error);
  EXPECT_NE(err.find("came back as MJPG 32x48"), std::string::npos) << err;
  EXPECT_EQ(src->info().width, kWidth);
  // The right one back: frames again.
  driver->width = kWidth;
  driver->onStreamOn = jpegOf(kWidth, kHeight, 90);
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(f.width, kWidth);
}

TEST(V4l2FakeDriver, AStreamThatStallsOrSendsOnlyGarbageIsRestartedAndSaysWhy) {
  auto driver = std::make_shared<FakeDriver>(V4L2_PIX_FMT_MJPEG);
  auto src = openFake(driver, /*autoReopen=*/true, /*reopenIntervalMs=*/10, /*timeoutMs=*/100);
  ASSERT_NE(src, nullptr);
  const auto jpeg = jpegOf(kWidth, kHeight, 90);
  Frame f;
  std::string err;
  // Frames arrive, every one cut short: the timeout says so, with the reason.
  // (the end of the scan and its end marker lost: a flat picture's scan is short)
  const std::vector<std::uint8_t> cut(jpeg.begin(), jpeg.end() - 4);
  ASSERT_TRUE(driver->deliver(cut));
  ASSERT_TRUE(driver->deliver(cut));
  EXPECT_EQ(src->next(f, err), ReadStatus::Error);
  EXPECT_EQ(err.rfind("timeout: no usable frame from /dev/video-fake within 100 ms: 2 arrived, "
                      "all unusable (MJPEG frame cut short",
                      0),
            0u)
      << err;
  EXPECT_FALSE(src->lost());  // once is a hiccup
  // Twice in a row: the stream is started again, as after an unplug.
  EXPECT_EQ(src->next(f, err), ReadStatus::Error);
  EXPECT_EQ(err,
            "timeout: no frame from /dev/video-fake within 100 ms; device lost: "
            "/dev/video-fake: Connection timed out (stalled: restarting the stream)");
  EXPECT_TRUE(src->lost());
  driver->onStreamOn = jpeg;
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(driver->opens, 2);
  EXPECT_EQ(src->reopenCount(), 1u);
  // A good frame between two timeouts: no restart.
  EXPECT_EQ(src->next(f, err), ReadStatus::Error);
  ASSERT_TRUE(driver->deliver(jpeg));
  ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
  EXPECT_EQ(src->next(f, err), ReadStatus::Error);
  EXPECT_FALSE(src->lost());
}

TEST(V4l2FakeDriver, InterruptEndsAWaitForAFrameAndForTheDevice) {
  auto driver = std::make_shared<FakeDriver>(V4L2_PIX_FMT_MJPEG);
  auto src = openFake(driver, /*autoReopen=*/true, /*reopenIntervalMs=*/5000);
  ASSERT_NE(src, nullptr);
  Frame f;
  std::string err;
  // Stalled: no frame within the 2 s timeout, unless interrupted.
  std::thread stopper([&] {
    std::this_thread::sleep_for(50ms);
    src->interrupt();
  });
  auto t0 = SteadyClock::now();
  EXPECT_EQ(src->next(f, err), ReadStatus::Error);
  EXPECT_LT(SteadyClock::now() - t0, 500ms);
  stopper.join();
  EXPECT_EQ(err, "interrupted: waiting for a frame from /dev/video-fake");

  // Lost, with 5 s to wait before the next reopen attempt: ends at once too.
  auto driver2 = std::make_shared<FakeDriver>(V4L2_PIX_FMT_MJPEG);
  auto lostSrc = openFake(driver2, /*autoReopen=*/true, /*reopenIntervalMs=*/5000);
  ASSERT_NE(lostSrc, nullptr);
  driver2->present = false;
  ASSERT_TRUE(driver2->deliver(jpegOf(kWidth, kHeight, 90)));
  ASSERT_EQ(lostSrc->next(f, err), ReadStatus::Error);
  ASSERT_TRUE(lostSrc->lost());
  std::thread stopper2([&] {
    std::this_thread::sleep_for(50ms);
    lostSrc->interrupt();
  });
  t0 = SteadyClock::now();
  EXPECT_EQ(lostSrc->next(f, err), ReadStatus::Error);
  EXPECT_LT(SteadyClock::now() - t0, 500ms);
  stopper2.join();
  EXPECT_EQ(err.rfind("interrupted: device lost", 0), 0u) << err;
}

}  // namespace
}  // namespace keyframed
