#include <cstdlib>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <libcamera/formats.h>
#include <libcamera/version.h>

#include "capture/libcamera_compat.h"
#include "capture/libcamera_select.h"
#include "capture/libcamera_source.h"

namespace keyframed {
namespace {

namespace fmt = libcamera::formats;
using libcamera::Size;

// libcamera logs INFO lines to stderr by default; keep test output readable.
struct QuietLibcamera {
  QuietLibcamera() { setenv("LIBCAMERA_LOG_LEVELS", "*:ERROR", 0); }
} quiet;

TEST(LibcameraCompat, VersionMacrosMatchTheHeaders) {
  EXPECT_EQ(
      libcamera_compat::kVersion,
      LIBCAMERA_VERSION_MAJOR * 1000000 + LIBCAMERA_VERSION_MINOR * 1000 + LIBCAMERA_VERSION_PATCH);
  EXPECT_EQ(KEYFRAMED_LIBCAMERA_VERSION(0, 2, 0), 2000);
  EXPECT_LT(KEYFRAMED_LIBCAMERA_VERSION(0, 9, 9), KEYFRAMED_LIBCAMERA_VERSION(1, 0, 0));
  EXPECT_TRUE(KEYFRAMED_LIBCAMERA_AT_LEAST(0, 0));
  // The features follow the version, and imply one another in release order.
  EXPECT_EQ(libcamera_compat::kStreamRoleSpan, libcamera_compat::kVersion >= 1000);
  EXPECT_EQ(libcamera_compat::kOrientation, libcamera_compat::kVersion >= 2000);
  EXPECT_EQ(libcamera_compat::kConstMetadata, libcamera_compat::kVersion >= 7000);
  EXPECT_TRUE(!libcamera_compat::kConstMetadata || libcamera_compat::kOrientation);
  EXPECT_TRUE(!libcamera_compat::kOrientation || libcamera_compat::kStreamRoleSpan);
}

TEST(LibcameraSelect, PrefersNv12ThenYuv420ThenYuyv) {
  std::string err;
  EXPECT_EQ(chooseLibcameraFormat({fmt::YUYV, fmt::YUV420, fmt::NV12}, "", err), fmt::NV12);
  EXPECT_EQ(chooseLibcameraFormat({fmt::YUYV, fmt::YUV420}, "", err), fmt::YUV420);
  EXPECT_EQ(chooseLibcameraFormat({fmt::RGB888, fmt::YUYV}, "", err), fmt::YUYV);
  EXPECT_FALSE(chooseLibcameraFormat({fmt::RGB888, fmt::SBGGR10}, "", err).isValid());
  EXPECT_NE(err.find("no supported pixel format"), std::string::npos) << err;
  EXPECT_NE(err.find("RGB888"), std::string::npos) << err;
}

TEST(LibcameraSelect, HonoursARequestedFormat) {
  std::string err;
  EXPECT_EQ(chooseLibcameraFormat({fmt::NV12, fmt::YUYV}, "yuyv", err), fmt::YUYV);
  EXPECT_EQ(chooseLibcameraFormat({fmt::NV12, fmt::YUV420}, "I420", err), fmt::YUV420);
  EXPECT_FALSE(chooseLibcameraFormat({fmt::NV12}, "YUYV", err).isValid());
  EXPECT_NE(err.find("does not offer YUYV"), std::string::npos) << err;
  EXPECT_FALSE(chooseLibcameraFormat({fmt::NV12}, "H264", err).isValid());
  EXPECT_NE(err.find("unknown pixel format 'H264'"), std::string::npos) << err;
}

TEST(LibcameraSelect, SizeExactElseSmallestCoveringElseLargest) {
  // A sensor's discrete modes (the simple and UVC pipelines).
  const libcamera::StreamFormats discrete(
      {{fmt::NV12,
        {libcamera::SizeRange(Size(640, 480)), libcamera::SizeRange(Size(1280, 720)),
         libcamera::SizeRange(Size(1920, 1080)), libcamera::SizeRange(Size(4056, 3040))}}});
  const Size current{1920, 1080};
  EXPECT_EQ(chooseLibcameraSize(discrete, fmt::NV12, {1280, 720}, current), Size(1280, 720));
  EXPECT_EQ(chooseLibcameraSize(discrete, fmt::NV12, {1000, 700}, current), Size(1280, 720));
  EXPECT_EQ(chooseLibcameraSize(discrete, fmt::NV12, {8000, 6000}, current), Size(4056, 3040));
  EXPECT_EQ(chooseLibcameraSize(discrete, fmt::NV12, {0, 0}, current), current);
  const libcamera::StreamFormats one({{fmt::NV12, {libcamera::SizeRange(Size(1920, 1080))}}});
  EXPECT_EQ(chooseLibcameraSize(one, fmt::NV12, {1280, 720}, current), Size(1920, 1080));
  EXPECT_EQ(chooseLibcameraSize(libcamera::StreamFormats(), fmt::NV12, {800, 600}, current),
            Size(800, 600));
}

TEST(LibcameraSelect, ASizeWithinAScalersRangeIsAskedForAsIs) {
  // The Pi's ISP output: one range (HQ camera: up to 4056x3040 in steps of 2).
  // libcamera's own sizes() of it is its list of common sizes, which holds neither
  // the HQ camera's 2028x1520 binned mode nor Camera Module 3's 2304x1296.
  const libcamera::StreamFormats isp(
      {{fmt::YUV420, {libcamera::SizeRange(Size(64, 64), Size(4056, 3040), 2, 2)}}});
  const std::vector<Size> common = isp.sizes(fmt::YUV420);
  ASSERT_FALSE(common.empty());
  for (const Size& s : common) EXPECT_NE(s, Size(2028, 1520));
  const Size current{1920, 1080};
  EXPECT_EQ(chooseLibcameraSize(isp, fmt::YUV420, {2028, 1520}, current), Size(2028, 1520));
  EXPECT_EQ(chooseLibcameraSize(isp, fmt::YUV420, {2304, 1296}, current), Size(2304, 1296));
  // Beyond the range: the largest size offered, as among discrete sizes.
  const Size big = chooseLibcameraSize(isp, fmt::YUV420, {8000, 6000}, current);
  EXPECT_LE(big.width, 4056U);
  EXPECT_LE(big.height, 3040U);
}

TEST(LibcameraSelect, FrameFormats) {
  PixelFormat f = PixelFormat::Gray8;
  EXPECT_TRUE(toFrameFormat(fmt::NV12, f));
  EXPECT_EQ(f, PixelFormat::NV12);
  EXPECT_TRUE(toFrameFormat(fmt::YUV420, f));
  EXPECT_EQ(f, PixelFormat::YUV420);
  EXPECT_TRUE(toFrameFormat(fmt::YUYV, f));
  EXPECT_EQ(f, PixelFormat::YUYV);
  EXPECT_FALSE(toFrameFormat(fmt::MJPEG, f));
}

TEST(LibcameraSelect, NoCameraIsAOneLineError) {
  std::string err;
  EXPECT_EQ(selectCamera({}, "", err), nullptr);
  EXPECT_EQ(err, "no camera found");
  EXPECT_EQ(selectCamera({}, "imx477", err), nullptr);
  EXPECT_EQ(err, "no camera found");
}

// The real CameraManager. Machines without a camera (CI, this VM host) see
// none and get the plain error; machines with one open and capture.
TEST(LibcameraSource, OpenWithoutCameraSaysNoCameraFound) {
  std::string err;
  const std::vector<std::string> ids = LibcameraSource::listCameras(err);
  if (!ids.empty()) GTEST_SKIP() << "a camera is present: " << ids.front();
  LibcameraOptions opt;
  auto src = LibcameraSource::open(opt, err);
  EXPECT_EQ(src, nullptr);
  EXPECT_EQ(err, "no camera found");
}

TEST(LibcameraHardware, CapturesFramesWithIncreasingTimestamps) {
  std::string err;
  const std::vector<std::string> ids = LibcameraSource::listCameras(err);
  if (ids.empty())
    GTEST_SKIP() << "no camera: libcamera lists none" << (err.empty() ? "" : ": ") << err;
  LibcameraOptions opt;
  opt.width = 640;
  opt.height = 480;
  opt.fps = 15.0;
  auto src = LibcameraSource::open(opt, err);
  ASSERT_TRUE(src) << err;
  EXPECT_GT(src->info().width, 0);
  Frame f;
  std::int64_t last = -1;
  for (int i = 0; i < 10; ++i) {
    ASSERT_EQ(src->next(f, err), ReadStatus::Frame) << err;
    EXPECT_EQ(f.index, i);
    EXPECT_GT(f.timestampNs, last);
    EXPECT_NE(f.data, nullptr);
    last = f.timestampNs;
  }
}

}  // namespace
}  // namespace keyframed
