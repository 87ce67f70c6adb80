#include <linux/videodev2.h>

#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <turbojpeg.h>

#include "capture/mjpeg_decoder.h"
#include "capture/v4l2_source.h"

namespace keyframed {
namespace {

TEST(V4l2Source, ParsesFormatNames) {
  EXPECT_EQ(V4l2Source::parseFormat("NV12"), V4L2_PIX_FMT_NV12);
  EXPECT_EQ(V4l2Source::parseFormat("yuv420"), V4L2_PIX_FMT_YUV420);
  EXPECT_EQ(V4l2Source::parseFormat("YU12"), V4L2_PIX_FMT_YUV420);
  EXPECT_EQ(V4l2Source::parseFormat("yuyv"), V4L2_PIX_FMT_YUYV);
  EXPECT_EQ(V4l2Source::parseFormat("MJPEG"), V4L2_PIX_FMT_MJPEG);
  EXPECT_EQ(V4l2Source::parseFormat("MJPG"), V4L2_PIX_FMT_MJPEG);
  EXPECT_EQ(V4l2Source::parseFormat("H264"), 0u);
  EXPECT_EQ(V4l2Source::fourccString(V4L2_PIX_FMT_YUV420), "YU12");
  EXPECT_EQ(V4l2Source::fourccString(V4L2_PIX_FMT_MJPEG), "MJPG");
}

TEST(V4l2Source, PrefersPlanarYuvThenYuyvThenMjpeg) {
  using V = std::vector<std::uint32_t>;
  EXPECT_EQ(V4l2Source::chooseFormat(V{V4L2_PIX_FMT_MJPEG, V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_NV12}),
            V4L2_PIX_FMT_NV12);
  EXPECT_EQ(V4l2Source::chooseFormat(V{V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_YUV420}),
            V4L2_PIX_FMT_YUV420);
  EXPECT_EQ(V4l2Source::chooseFormat(V{V4L2_PIX_FMT_MJPEG, V4L2_PIX_FMT_YUYV}), V4L2_PIX_FMT_YUYV);
  EXPECT_EQ(V4l2Source::chooseFormat(V{V4L2_PIX_FMT_H264, V4L2_PIX_FMT_MJPEG}), V4L2_PIX_FMT_MJPEG);
  EXPECT_EQ(V4l2Source::chooseFormat(V{V4L2_PIX_FMT_H264, V4L2_PIX_FMT_RGB565}), 0u);
}

TEST(V4l2Source, AFormatThatReachesTheFrameRateBeatsAPreferredSlowOne) {
  using R = V4l2Source::FormatRate;
  // A USB 2 webcam at 1080p: uncompressed YUYV at 5 fps, MJPEG at 30.
  const std::vector<R> webcam{{V4L2_PIX_FMT_YUYV, 5.0}, {V4L2_PIX_FMT_MJPEG, 30.0}};
  EXPECT_EQ(V4l2Source::chooseFormat(webcam, 30.0), V4L2_PIX_FMT_MJPEG);
  EXPECT_EQ(V4l2Source::chooseFormat(webcam, 5.0), V4L2_PIX_FMT_YUYV);  // enough: no decode
  // Fast enough (29.97 for 30): the preference order decides.
  const std::vector<R> both{{V4L2_PIX_FMT_MJPEG, 30.0}, {V4L2_PIX_FMT_NV12, 29.97}};
  EXPECT_EQ(V4l2Source::chooseFormat(both, 30.0), V4L2_PIX_FMT_NV12);
  // None fast enough: the fastest, the preferred one among equals.
  const std::vector<R> slow{
      {V4L2_PIX_FMT_MJPEG, 15.0}, {V4L2_PIX_FMT_YUYV, 10.0}, {V4L2_PIX_FMT_NV12, 15.0}};
  EXPECT_EQ(V4l2Source::chooseFormat(slow, 30.0), V4L2_PIX_FMT_NV12);
  // A rate the driver does not list counts as enough (as before rates were asked).
  const std::vector<R> unknown{{V4L2_PIX_FMT_MJPEG, 30.0}, {V4L2_PIX_FMT_YUYV, 0.0}};
  EXPECT_EQ(V4l2Source::chooseFormat(unknown, 30.0), V4L2_PIX_FMT_YUYV);
  EXPECT_EQ(V4l2Source::chooseFormat(std::vector<R>{{V4L2_PIX_FMT_H264, 60.0}}, 30.0), 0u);
}

TEST(V4l2Source, TimevalToNanoseconds) {
  EXPECT_EQ(V4l2Source::timevalToNs(0, 0), 0);
  EXPECT_EQ(V4l2Source::timevalToNs(12, 345678), 12'345'678'000LL);
  // Beyond 2^32 seconds' worth of nanoseconds: no 32-bit overflow.
  EXPECT_EQ(V4l2Source::timevalToNs(5'000'000, 1), 5'000'000'000'001'000LL);
}

TEST(V4l2Source, MissingDeviceIsAOneLineError) {
  V4l2Options opt;
  opt.device = "/dev/video-does-not-exist-42";
  std::string err;
  EXPECT_EQ(V4l2Source::open(opt, err), nullptr);
  EXPECT_EQ(err, "no such device: /dev/video-does-not-exist-42");
  EXPECT_EQ(err.find('\n'), std::string::npos);
}

TEST(V4l2Source, NonV4l2NodeIsRejected) {
  V4l2Options opt;
  opt.device = "/dev/null";
  std::string err;
  EXPECT_EQ(V4l2Source::open(opt, err), nullptr);
  EXPECT_NE(err.find("/dev/null is not a V4L2 device"), std::string::npos) << err;
}

TEST(V4l2Source, RejectsBadBufferCount) {
  V4l2Options opt;
  opt.bufferCount = 1;
  std::string err;
  EXPECT_EQ(V4l2Source::open(opt, err), nullptr);
  EXPECT_NE(err.find("buffer count"), std::string::npos) << err;
}

TEST(V4l2Source, ListDevicesDescribesEveryNode) {
  // No camera on CI: the list may be empty, but whatever is there is described.
  for (const V4l2DeviceInfo& d : V4l2Source::listDevices()) {
    EXPECT_EQ(d.path.rfind("/dev/video", 0), 0u) << d.path;
  }
  V4l2DeviceInfo d;
  std::string err;
  EXPECT_FALSE(V4l2Source::describe("/dev/video-none", d, err));
  EXPECT_EQ(err, "no such device: /dev/video-none");
}

std::vector<unsigned char> encodeJpeg(int w, int h) {
  std::vector<unsigned char> bgr(static_cast<std::size_t>(w * h * 3));
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      unsigned char* p = &bgr[static_cast<std::size_t>((y * w + x) * 3)];
      p[0] = static_cast<unsigned char>(x * 255 / w);  // B ramps left to right
      p[1] = 100;
      p[2] = static_cast<unsigned char>(y * 255 / h);  // R ramps top to bottom
    }
  }
  tjhandle tj = tjInitCompress();
  unsigned char* out = nullptr;
  unsigned long size = 0;
  EXPECT_EQ(tjCompress2(tj, bgr.data(), w, w * 3, h, TJPF_BGR, &out, &size, TJSAMP_422, 90, 0), 0);
  std::vector<unsigned char> jpeg(out, out + size);
  tjFree(out);
  tjDestroy(tj);
  return jpeg;
}

TEST(V4l2Devices, TheFirstNodeWithAReadableFormatIsPicked) {
  V4l2DeviceInfo bayer{"/dev/video0", "unicam", "unicam", "", true, true, {"pRAA", "RG10"}};
  V4l2DeviceInfo meta{"/dev/video1", "unicam", "unicam", "", false, true, {}};
  V4l2DeviceInfo usb{"/dev/video2", "uvcvideo", "cam", "", true, true, {"MJPG", "YUYV"}};
  EXPECT_EQ(V4l2Source::pickDevice({bayer, meta, usb}), "/dev/video2");
  // None readable: the first capture node, whose open() says why not.
  EXPECT_EQ(V4l2Source::pickDevice({meta, bayer}), "/dev/video0");
  EXPECT_EQ(V4l2Source::pickDevice({meta}), "");
  EXPECT_EQ(V4l2Source::pickDevice({}), "");
  // A node that could not be opened to look at (no permission): picked, so that its
  // open() says why ("is the user in group 'video'?") instead of "no camera".
  V4l2DeviceInfo locked{"/dev/video3", "", "", "", false, false, {}};
  EXPECT_EQ(V4l2Source::pickDevice({meta, locked}), "/dev/video3");
  EXPECT_EQ(V4l2Source::pickDevice({locked, usb}), "/dev/video2");
  // A multi-planar node with a format we read is passed over for a single-planar
  // camera (open() refuses multi-planar), and picked only when nothing else captures.
  V4l2DeviceInfo mplane{"/dev/video4", "pispbe", "isp", "", true, true, {"NV12"}, true};
  EXPECT_EQ(V4l2Source::pickDevice({mplane, usb}), "/dev/video2");
  EXPECT_EQ(V4l2Source::pickDevice({mplane, bayer}), "/dev/video0");
  EXPECT_EQ(V4l2Source::pickDevice({meta, mplane}), "/dev/video4");
}

TEST(MjpegDecoder, DecodesToBgr) {
  const auto jpeg = encodeJpeg(64, 48);
  MjpegDecoder dec;
  std::string err;
  ASSERT_TRUE(dec.decode(jpeg.data(), jpeg.size(), err)) << err;
  EXPECT_EQ(dec.width(), 64);
  EXPECT_EQ(dec.height(), 48);
  EXPECT_EQ(dec.stride(), 64 * 3);
  const std::uint8_t* mid = dec.bgr() + (24 * 64 + 60) * 3;
  EXPECT_NEAR(mid[0], 60 * 255 / 64, 12);
  EXPECT_NEAR(mid[1], 100, 12);
  EXPECT_NEAR(mid[2], 24 * 255 / 48, 12);
}

TEST(MjpegDecoder, RejectsGarbageWithOneLineError) {
  MjpegDecoder dec;
  std::string err;
  const std::vector<std::uint8_t> zeros(100, 0);
  EXPECT_FALSE(dec.decode(zeros.data(), zeros.size(), err));
  EXPECT_NE(err.find("not a JPEG"), std::string::npos) << err;
  auto jpeg = encodeJpeg(32, 32);
  jpeg.resize(20);  // SOI and part of a header
  EXPECT_FALSE(dec.decode(jpeg.data(), jpeg.size(), err));
  EXPECT_EQ(err.find('\n'), std::string::npos);
}

TEST(MjpegDecoder, AFrameCutShortIsRefusedAndPaddingAfterTheEndIsNot) {
  const auto jpeg = encodeJpeg(64, 48);
  MjpegDecoder dec;
  std::string err;
  // Cut in the entropy-coded data (a USB transfer lost): libjpeg-turbo only warns
  // and fills the rest with grey; without the end marker the frame is refused.
  const std::vector<std::uint8_t> cut(jpeg.begin(), jpeg.begin() + jpeg.size() * 3 / 4);
  EXPECT_FALSE(dec.decode(cut.data(), cut.size(), err, 64, 48));
  EXPECT_NE(err.find("cut short"), std::string::npos) << err;
  // Zeros after the end marker, as some drivers pad a frame: a good frame.
  std::vector<std::uint8_t> padded(jpeg);
  padded.resize(jpeg.size() + 1000, 0);
  EXPECT_TRUE(dec.decode(padded.data(), padded.size(), err, 64, 48)) << err;
  // And read through the buffer step, the reason is kept for the caller.
  Frame f;
  std::string why;
  const V4l2Source::StreamLayout mjpeg{V4L2_PIX_FMT_MJPEG, PixelFormat::BGR24, 64, 48, 0};
  EXPECT_EQ(V4l2Source::readBuffer(mjpeg, cut.data(), cut.size(), cut.size(), 0, dec, f, &why),
            V4l2Source::BufferUse::Corrupt);
  EXPECT_NE(why.find("cut short"), std::string::npos) << why;
  EXPECT_EQ(V4l2Source::readBuffer(mjpeg, jpeg.data(), jpeg.size(), jpeg.size(),
                                   V4L2_BUF_FLAG_ERROR, dec, f, &why),
            V4l2Source::BufferUse::Corrupt);
  EXPECT_EQ(why, "the driver flagged the buffer ERROR");
}

TEST(MjpegDecoder, AHeaderClaimingAHugePictureIsRefusedBeforeDecoding) {
  auto jpeg = encodeJpeg(64, 48);
  // SOF0 (FF C0): length (2), precision (1), height (2), width (2).
  std::size_t sof = 0;
  for (std::size_t i = 2; i + 8 < jpeg.size(); ++i) {
    if (jpeg[i] == 0xFF && (jpeg[i + 1] == 0xC0 || jpeg[i + 1] == 0xC1)) {
      sof = i;
      break;
    }
  }
  ASSERT_GT(sof, 0u);
  // 60000 x 60000 (10 GB of BGR), under libjpeg-turbo's own limit of 65500.
  for (std::size_t k : {5u, 7u}) jpeg[sof + k] = 0xEA;
  for (std::size_t k : {6u, 8u}) jpeg[sof + k] = 0x60;
  MjpegDecoder dec;
  std::string err;
  EXPECT_FALSE(dec.decode(jpeg.data(), jpeg.size(), err, 64, 48));
  EXPECT_NE(err.find("60000x60000, not 64x48"), std::string::npos) << err;
  EXPECT_EQ(dec.bgr(), nullptr) << "nothing allocated for it";
}

// The per-buffer step of V4l2Source::next(), with buffers made up in memory.
using Use = V4l2Source::BufferUse;
const V4l2Source::StreamLayout kMjpeg64x48{V4L2_PIX_FMT_MJPEG, PixelFormat::BGR24, 64, 48, 0};

TEST(V4l2Buffer, MjpegIsDecodedToBgrOfTheNegotiatedSize) {
  const auto jpeg = encodeJpeg(64, 48);
  std::vector<std::uint8_t> buffer(jpeg.begin(), jpeg.end());
  buffer.resize(buffer.size() + 4096, 0);  // a driver buffer is larger than its JPEG
  MjpegDecoder dec;
  Frame f;
  ASSERT_EQ(
      V4l2Source::readBuffer(kMjpeg64x48, buffer.data(), jpeg.size(), buffer.size(), 0, dec, f),
      Use::Frame);
  EXPECT_EQ(f.format, PixelFormat::BGR24);
  EXPECT_EQ(f.data, dec.bgr());  // the picture lives in the decoder, not the buffer
  EXPECT_EQ(f.width, 64);
  EXPECT_EQ(f.height, 48);
  EXPECT_EQ(f.stride, 64 * 3);
  const std::uint8_t* mid = f.data + (24 * 64 + 60) * 3;
  EXPECT_NEAR(mid[2], 24 * 255 / 48, 12);
}

TEST(V4l2Buffer, MjpegOfAnotherSizeOrUndecodableOrFlaggedIsCorrupt) {
  MjpegDecoder dec;
  Frame f;
  const auto small = encodeJpeg(32, 32);  // the camera changed size under us
  EXPECT_EQ(
      V4l2Source::readBuffer(kMjpeg64x48, small.data(), small.size(), small.size(), 0, dec, f),
      Use::Corrupt);
  const auto good = encodeJpeg(64, 48);
  EXPECT_EQ(V4l2Source::readBuffer(kMjpeg64x48, good.data(), 40, good.size(), 0, dec, f),
            Use::Corrupt);  // cut short: bytesused says 40
  const std::vector<std::uint8_t> zeros(4096, 0);
  EXPECT_EQ(
      V4l2Source::readBuffer(kMjpeg64x48, zeros.data(), zeros.size(), zeros.size(), 0, dec, f),
      Use::Corrupt);
  EXPECT_EQ(V4l2Source::readBuffer(kMjpeg64x48, good.data(), good.size(), good.size(),
                                   V4L2_BUF_FLAG_ERROR, dec, f),
            Use::Corrupt);
  // bytesused larger than the buffer: only the buffer is read.
  EXPECT_EQ(
      V4l2Source::readBuffer(kMjpeg64x48, good.data(), good.size() * 4, good.size(), 0, dec, f),
      Use::Frame);
}

TEST(V4l2Buffer, RawFramesPointIntoTheBufferAndShortOnesAreCorrupt) {
  const V4l2Source::StreamLayout nv12{V4L2_PIX_FMT_NV12, PixelFormat::NV12, 6, 4, 8};
  std::vector<std::uint8_t> buffer(8 * 4 * 3 / 2);
  MjpegDecoder dec;
  Frame f;
  ASSERT_EQ(V4l2Source::readBuffer(nv12, buffer.data(), buffer.size(), buffer.size(), 0, dec, f),
            Use::Frame);
  EXPECT_EQ(f.data, buffer.data());
  EXPECT_EQ(f.format, PixelFormat::NV12);
  EXPECT_EQ(f.stride, 8);
  EXPECT_EQ(V4l2Source::readBuffer(nv12, buffer.data(), 40, buffer.size(), 0, dec, f),
            Use::Corrupt);  // the chroma plane is missing
  const V4l2Source::StreamLayout yuyv{V4L2_PIX_FMT_YUYV, PixelFormat::YUYV, 6, 4, 12};
  EXPECT_EQ(V4l2Source::readBuffer(yuyv, buffer.data(), 48, 48, 0, dec, f), Use::Frame);
  EXPECT_EQ(V4l2Source::readBuffer(yuyv, buffer.data(), 48, 47, 0, dec, f), Use::Corrupt);
}

}  // namespace
}  // namespace keyframed
