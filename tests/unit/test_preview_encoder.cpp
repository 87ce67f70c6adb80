#include <cstring>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "app/preview_encoder.h"
#include "output/h264.h"
#include "photos.h"

namespace keyframed {
namespace {

cv::Mat decode(const std::vector<std::uint8_t>& data) {
  return cv::imdecode(
      cv::Mat(1, static_cast<int>(data.size()), CV_8UC1, const_cast<std::uint8_t*>(data.data())),
      cv::IMREAD_COLOR);
}

// A camera's frame of `bgr` in YUV420 (I420) or NV12, rows `stride` bytes apart
// (padding filled with a value no picture sample has nearby, so reading it shows).
struct CameraFrame {
  std::vector<std::uint8_t> bytes;
  Frame frame;
};

CameraFrame cameraFrame(const cv::Mat& bgr, PixelFormat format, int stride) {
  cv::Mat i420;
  cv::cvtColor(bgr, i420, cv::COLOR_BGR2YUV_I420);
  const int w = bgr.cols, h = bgr.rows, cw = w / 2, ch = h / 2;
  const std::uint8_t* y = i420.data;
  const std::uint8_t* u = y + static_cast<std::size_t>(w) * h;
  const std::uint8_t* v = u + static_cast<std::size_t>(cw) * ch;
  CameraFrame c;
  if (format == PixelFormat::YUYV) {  // 4:2:2, `stride` bytes a row: each chroma row twice
    c.bytes.assign(static_cast<std::size_t>(stride) * h, 255);
    for (int r = 0; r < h; ++r) {
      std::uint8_t* row = &c.bytes[std::size_t(r) * stride];
      for (int x = 0; x < cw; ++x) {
        row[4 * x] = y[r * w + 2 * x];
        row[4 * x + 1] = u[(r / 2) * cw + x];
        row[4 * x + 2] = y[r * w + 2 * x + 1];
        row[4 * x + 3] = v[(r / 2) * cw + x];
      }
    }
    c.frame = Frame{format, c.bytes.data(), w, h, stride, 0, 0};
    return c;
  }
  // Exactly as long as the frame's planes (frameBytes): reading past them shows under
  // AddressSanitizer.
  const std::size_t chromaBytes = format == PixelFormat::NV12
                                      ? static_cast<std::size_t>(stride) * ch
                                      : 2 * static_cast<std::size_t>(stride / 2) * ch;
  c.bytes.assign(static_cast<std::size_t>(stride) * h + chromaBytes, 255);
  for (int r = 0; r < h; ++r) std::memcpy(&c.bytes[std::size_t(r) * stride], y + r * w, w);
  std::uint8_t* chroma = c.bytes.data() + static_cast<std::size_t>(stride) * h;
  if (format == PixelFormat::NV12) {
    for (int r = 0; r < ch; ++r)
      for (int x = 0; x < cw; ++x) {
        chroma[r * stride + 2 * x] = u[r * cw + x];
        chroma[r * stride + 2 * x + 1] = v[r * cw + x];
      }
  } else {
    const int cs = stride / 2;  // as planeSizes() lays out an I420 frame's chroma
    for (int r = 0; r < ch; ++r) {
      std::memcpy(chroma + r * cs, u + r * cw, cw);
      std::memcpy(chroma + cs * ch + r * cs, v + r * cw, cw);
    }
  }
  c.frame.format = format;
  c.frame.data = c.bytes.data();
  c.frame.width = w;
  c.frame.height = h;
  c.frame.stride = stride;
  return c;
}

class PreviewEncoderTest : public testing::Test {
 protected:
  void SetUp() override {
    const cv::Mat img = test::photo("fruits.jpg", cv::IMREAD_COLOR);  // strong colours
    if (img.empty()) GTEST_SKIP() << "fruits.jpg missing";
    bgr_ = img(cv::Rect(0, 0, 500, 480)).clone();
  }
  // The preview compared with the photo scaled the plain way.
  double psnr(const std::vector<std::uint8_t>& preview, cv::Size expected) {
    return psnr(decode(preview), expected);
  }
  double psnr(const cv::Mat& back, cv::Size expected) {
    EXPECT_EQ(back.size(), expected);
    if (back.size() != expected) return 0.0;
    cv::Mat reference;
    cv::resize(bgr_, reference, expected, 0, 0, cv::INTER_AREA);
    return cv::PSNR(back, reference);
  }
  cv::Mat bgr_;
};

TEST_F(PreviewEncoderTest, CameraYuvIsScaledPlaneByPlaneToTheSamePicture) {
  PreviewEncoder preview(160);
  const cv::Size size = preview.sizeFor(bgr_.cols, bgr_.rows);
  EXPECT_EQ(size, cv::Size(160, 152));  // 480 * 160 / 500 = 153.6, even for 4:2:0 chroma
  std::vector<std::uint8_t> out;
  ASSERT_TRUE(preview.encode(Frame::ofBgr(bgr_, 0, 0), out));
  EXPECT_STREQ(preview.format(), "jpeg");
  const double fromBgr = psnr(out, size);
  EXPECT_GT(fromBgr, 24.0);
  for (PixelFormat format : {PixelFormat::YUV420, PixelFormat::NV12}) {
    // Tight, padded rows as drivers give them, and an odd stride (chroma rows half
    // of it, rounded down).
    for (int stride : {500, 532, 501}) {
      SCOPED_TRACE(std::string(toString(format)) + " stride " + std::to_string(stride));
      const CameraFrame cam = cameraFrame(bgr_, format, stride);
      // Swapped or misplaced chroma, or padding read as picture, costs far more
      // than the 4:2:0 round trip does.
      ASSERT_TRUE(preview.encode(cam.frame, out));
      EXPECT_STREQ(preview.format(), "jpeg");
      EXPECT_GT(psnr(out, size), fromBgr - 2.0);
    }
  }
  // YUYV (a USB camera's 4:2:2): de-interleaved, then scaled like the planes above.
  for (int stride : {1000, 1064}) {
    SCOPED_TRACE("YUYV stride " + std::to_string(stride));
    const CameraFrame cam = cameraFrame(bgr_, PixelFormat::YUYV, stride);
    ASSERT_TRUE(preview.encode(cam.frame, out));
    EXPECT_STREQ(preview.format(), "jpeg");
    EXPECT_GT(psnr(out, size), fromBgr - 2.0);
  }
}

TEST_F(PreviewEncoderTest, FullWidthIsLosslessPng) {
  PreviewEncoder preview(10000);
  std::vector<std::uint8_t> out;
  ASSERT_TRUE(preview.encode(Frame::ofBgr(bgr_, 0, 0), out));
  EXPECT_STREQ(preview.format(), "png");
  const cv::Mat back = decode(out);
  ASSERT_EQ(back.size(), bgr_.size());
  EXPECT_EQ(cv::norm(back, bgr_, cv::NORM_INF), 0.0);
  // A camera frame at full width: the PNG holds its colour conversion, unscaled.
  const CameraFrame cam = cameraFrame(bgr_, PixelFormat::NV12, 512);
  ASSERT_TRUE(preview.encode(cam.frame, out));
  EXPECT_STREQ(preview.format(), "png");
  EXPECT_EQ(decode(out).size(), bgr_.size());
}

// An H.264 picture decoded back to BGR.
cv::Mat decodeH264(H264Decoder& decoder, const std::vector<std::uint8_t>& packet) {
  std::vector<std::uint8_t> i420;
  int w = 0, h = 0;
  std::string error;
  if (!decoder.decode(packet, i420, w, h, error)) {
    ADD_FAILURE() << error;
    return {};
  }
  cv::Mat bgr;
  cv::cvtColor(cv::Mat(h * 3 / 2, w, CV_8UC1, i420.data()), bgr, cv::COLOR_YUV2BGR_I420);
  return bgr;
}

TEST_F(PreviewEncoderTest, H264IsOneStreamOfTheSameScaledPictures) {
  PreviewEncoder preview(160, PreviewEncoder::Format::H264, 30);
  const cv::Size size = preview.sizeFor(bgr_.cols, bgr_.rows);
  H264Decoder decoder;
  std::vector<std::uint8_t> out;
  ASSERT_TRUE(preview.encode(Frame::ofBgr(bgr_, 0, 0), out)) << preview.error();
  EXPECT_STREQ(preview.format(), "h264");
  EXPECT_TRUE(h264HasIdr(out));  // the stream opens with an IDR picture
  const double fromBgr = psnr(decodeH264(decoder, out), size);
  EXPECT_GT(fromBgr, 24.0);
  // The JPEG still for Zenoh: the same picture.
  std::vector<std::uint8_t> still;
  ASSERT_TRUE(preview.lastAsJpeg(still));
  EXPECT_GT(psnr(still, size), 24.0);
  for (PixelFormat format : {PixelFormat::YUV420, PixelFormat::NV12}) {
    SCOPED_TRACE(toString(format));
    const CameraFrame cam = cameraFrame(bgr_, format, 532);
    ASSERT_TRUE(preview.encode(cam.frame, out)) << preview.error();
    EXPECT_FALSE(h264HasIdr(out));  // the same stream goes on
    EXPECT_GT(psnr(decodeH264(decoder, out), size), fromBgr - 2.0);
  }
  // A JPEG preview has no still of its own to give.
  EXPECT_FALSE(PreviewEncoder(160).lastAsJpeg(still));
}

TEST_F(PreviewEncoderTest, H264OpensAGroupEverySecondOfFrameTime) {
  // A 30 fps camera whose frames the analysis takes at 10 fps (it skips two in three),
  // and one at its own rate: an IDR picture every second of frame time in both.
  for (const auto& [stepNs, every] : {std::pair{100'000'000LL, 10}, {33'333'333LL, 30}}) {
    SCOPED_TRACE(stepNs);
    PreviewEncoder preview(64, PreviewEncoder::Format::H264, 30);
    std::vector<std::uint8_t> out;
    std::vector<int> idr;
    for (int i = 0; i < 3 * every + 1; ++i) {
      ASSERT_TRUE(preview.encode(Frame::ofBgr(bgr_, i, i * stepNs), out)) << preview.error();
      if (h264HasIdr(out)) idr.push_back(i);
    }
    EXPECT_EQ(idr, (std::vector<int>{0, every, 2 * every, 3 * every}));
  }
}

TEST_F(PreviewEncoderTest, H264AtFullWidthKeepsTheFrameSize) {
  PreviewEncoder preview(10000, PreviewEncoder::Format::H264, 30);
  std::vector<std::uint8_t> out;
  ASSERT_TRUE(preview.encode(Frame::ofBgr(bgr_, 0, 0), out)) << preview.error();
  H264Decoder decoder;
  EXPECT_GT(psnr(decodeH264(decoder, out), bgr_.size()), 30.0);
}

TEST_F(PreviewEncoderTest, AStillIsAJpegOfThePreviewSizeInEveryFormat) {
  std::vector<std::uint8_t> still;
  for (const auto format : {PreviewEncoder::Format::Jpeg, PreviewEncoder::Format::H264}) {
    PreviewEncoder preview(160, format, 30);
    const cv::Size size = preview.sizeFor(bgr_.cols, bgr_.rows);
    ASSERT_TRUE(preview.still(Frame::ofBgr(bgr_, 0, 0), still)) << preview.error();
    EXPECT_GT(psnr(still, size), 24.0);
    const CameraFrame cam = cameraFrame(bgr_, PixelFormat::NV12, 532);
    ASSERT_TRUE(preview.still(cam.frame, still)) << preview.error();
    EXPECT_GT(psnr(still, size), 24.0);
  }
  // At full width (a lossless PNG stream), the still is a JPEG of the whole frame.
  PreviewEncoder full(10000);
  ASSERT_TRUE(full.still(Frame::ofBgr(bgr_, 0, 0), still)) << full.error();
  EXPECT_GT(psnr(still, bgr_.size()), 30.0);
  EXPECT_FALSE(PreviewEncoder(0).still(Frame::ofBgr(bgr_, 0, 0), still));
}

// A width under 2 (the configuration refuses one under 16) still makes a picture: 2
// wide, as 4:2:0 chroma needs, never an empty size that OpenCV throws on.
TEST(PreviewEncoder, ATinyWidthMakesATwoPixelWidePicture) {
  std::vector<std::uint8_t> out;
  const cv::Mat bgr(48, 64, CV_8UC3, cv::Scalar(10, 100, 200));
  PreviewEncoder preview(1);
  ASSERT_TRUE(preview.encode(Frame::ofBgr(bgr, 0, 0), out));
  EXPECT_EQ(decode(out).size(), cv::Size(2, 2));
}

TEST(PreviewEncoder, OffOrEmptyEncodesNothing) {
  std::vector<std::uint8_t> out;
  const cv::Mat grey(48, 64, CV_8UC1, cv::Scalar(100));
  EXPECT_FALSE(PreviewEncoder(0).encode(Frame::ofGray(grey, 0, 0), out));
  EXPECT_FALSE(PreviewEncoder(32).encode(Frame{}, out));
  PreviewEncoder preview(32);
  ASSERT_TRUE(preview.encode(Frame::ofGray(grey, 0, 0), out));
  EXPECT_EQ(decode(out).size(), cv::Size(32, 24));
}

}  // namespace
}  // namespace keyframed
