#include <algorithm>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "tagging/jpeg_encoder.h"

namespace keyframed {
namespace {

// A real aerial photo, cropped to a size whose chroma planes are not trivially aligned.
cv::Mat photo() {
  const cv::Mat img = cv::imread(KEYFRAMED_PHOTO_DIR "/aero1.jpg", cv::IMREAD_COLOR);
  if (img.empty()) return img;
  return img(cv::Rect(0, 0, std::min(img.cols, 642), std::min(img.rows, 482))).clone();
}

cv::Mat decode(const std::vector<std::uint8_t>& jpeg, int flags) {
  return cv::imdecode(
      cv::Mat(1, static_cast<int>(jpeg.size()), CV_8UC1, const_cast<std::uint8_t*>(jpeg.data())),
      flags);
}

class JpegEncoderTest : public testing::Test {
 protected:
  void SetUp() override {
    bgr_ = photo();
    if (bgr_.empty()) GTEST_SKIP() << "aero1.jpg not found in " KEYFRAMED_PHOTO_DIR;
  }

  // Encodes at quality 95 and compares the decoded image with `expected`.
  void roundTrip(const Frame& f, const cv::Mat& expected, int flags) {
    std::vector<std::uint8_t> out;
    std::string error;
    ASSERT_TRUE(encoder_.encode(f, 95, out, error)) << error;
    const cv::Mat back = decode(out, flags);
    ASSERT_FALSE(back.empty());
    ASSERT_EQ(back.size(), expected.size());
    EXPECT_GT(cv::PSNR(back, expected), 35.0) << toString(f.format);
  }

  cv::Mat bgr_;
  JpegEncoder encoder_;
};

TEST_F(JpegEncoderTest, Gray8) {
  cv::Mat gray;
  cv::cvtColor(bgr_, gray, cv::COLOR_BGR2GRAY);
  roundTrip(Frame::ofGray(gray, 0, 0), gray, cv::IMREAD_GRAYSCALE);
}

TEST_F(JpegEncoderTest, Bgr24AndMatOverload) {
  roundTrip(Frame::ofBgr(bgr_, 0, 0), bgr_, cv::IMREAD_COLOR);
  std::vector<std::uint8_t> out;
  std::string error;
  ASSERT_TRUE(encoder_.encode(bgr_, 95, out, error)) << error;
  EXPECT_GT(cv::PSNR(decode(out, cv::IMREAD_COLOR), bgr_), 35.0);
}

TEST_F(JpegEncoderTest, Yuv420) {
  cv::Mat i420;  // (h * 3/2) x w: Y, then U, then V
  cv::cvtColor(bgr_, i420, cv::COLOR_BGR2YUV_I420);
  const Frame f{PixelFormat::YUV420, i420.data, bgr_.cols, bgr_.rows, bgr_.cols, 0, 0};
  roundTrip(f, bgr_, cv::IMREAD_COLOR);
}

TEST_F(JpegEncoderTest, Yuv420WithAnOddRowStride) {
  // Rows padded to an odd stride, chroma rows stride / 2 apart (rounded down, as
  // planeSizes and the capture lay them out), in a buffer of exactly that size.
  cv::Mat i420;
  cv::cvtColor(bgr_, i420, cv::COLOR_BGR2YUV_I420);
  const int w = bgr_.cols, h = bgr_.rows, cw = w / 2, ch = h / 2;
  const int stride = w + 1, cs = stride / 2;
  ASSERT_EQ(cs, cw);
  std::vector<std::uint8_t> padded(static_cast<std::size_t>(stride) * h +
                                   2 * static_cast<std::size_t>(cs) * ch);
  for (int r = 0; r < h; ++r) std::copy_n(i420.data + r * w, w, padded.data() + r * stride);
  const std::uint8_t* u = i420.data + w * h;
  const std::uint8_t* v = u + cw * ch;
  std::uint8_t* pu = padded.data() + static_cast<std::size_t>(stride) * h;
  std::uint8_t* pv = pu + static_cast<std::size_t>(cs) * ch;
  for (int r = 0; r < ch; ++r) {
    std::copy_n(u + r * cw, cw, pu + r * cs);
    std::copy_n(v + r * cw, cw, pv + r * cs);
  }
  roundTrip(Frame{PixelFormat::YUV420, padded.data(), w, h, stride, 0, 0}, bgr_, cv::IMREAD_COLOR);
}

TEST_F(JpegEncoderTest, Nv12) {
  cv::Mat i420;
  cv::cvtColor(bgr_, i420, cv::COLOR_BGR2YUV_I420);
  // Interleave U and V into NV12 by hand (OpenCV has no BGR -> NV12 conversion).
  const int w = bgr_.cols, h = bgr_.rows, cw = w / 2, ch = h / 2;
  std::vector<std::uint8_t> nv12(static_cast<std::size_t>(w) * h * 3 / 2);
  std::copy(i420.data, i420.data + w * h, nv12.begin());
  const std::uint8_t* u = i420.data + w * h;
  const std::uint8_t* v = u + cw * ch;
  for (int i = 0; i < cw * ch; ++i) {
    nv12[w * h + 2 * i] = u[i];
    nv12[w * h + 2 * i + 1] = v[i];
  }
  roundTrip(Frame{PixelFormat::NV12, nv12.data(), w, h, w, 0, 0}, bgr_, cv::IMREAD_COLOR);
}

TEST_F(JpegEncoderTest, Yuyv) {
  // Limited-range BT.601 4:2:2 built from OpenCV's I420 (each chroma row serves two).
  cv::Mat i420;
  cv::cvtColor(bgr_, i420, cv::COLOR_BGR2YUV_I420);
  const int w = bgr_.cols, h = bgr_.rows, cw = w / 2;
  const std::uint8_t* u = i420.data + w * h;
  const std::uint8_t* v = u + cw * (h / 2);
  cv::Mat yuyv(h, w, CV_8UC2);
  for (int y = 0; y < h; ++y) {
    std::uint8_t* row = yuyv.ptr<std::uint8_t>(y);
    for (int c = 0; c < cw; ++c) {
      row[4 * c] = i420.data[y * w + 2 * c];
      row[4 * c + 1] = u[(y / 2) * cw + c];
      row[4 * c + 2] = i420.data[y * w + 2 * c + 1];
      row[4 * c + 3] = v[(y / 2) * cw + c];
    }
  }
  roundTrip(Frame{PixelFormat::YUYV, yuyv.data, w, h, static_cast<int>(yuyv.step[0]), 0, 0}, bgr_,
            cv::IMREAD_COLOR);
}

TEST_F(JpegEncoderTest, FullRangeYuvIsNotExpanded) {
  // JPEG's own full-range YCbCr (OpenCV's YCrCb, planes reordered to I420).
  cv::Mat ycrcb;
  cv::cvtColor(bgr_, ycrcb, cv::COLOR_BGR2YCrCb);
  const int w = bgr_.cols, h = bgr_.rows, cw = w / 2, ch = h / 2;
  std::vector<std::uint8_t> i420(static_cast<std::size_t>(w) * h * 3 / 2);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) i420[y * w + x] = ycrcb.at<cv::Vec3b>(y, x)[0];
  for (int y = 0; y < ch; ++y) {
    for (int x = 0; x < cw; ++x) {
      const cv::Vec3b p = ycrcb.at<cv::Vec3b>(2 * y, 2 * x);
      i420[w * h + y * cw + x] = p[2];            // Cb
      i420[w * h + cw * ch + y * cw + x] = p[1];  // Cr
    }
  }
  encoder_.setYuvRange(YuvRange::Full);
  roundTrip(Frame{PixelFormat::YUV420, i420.data(), w, h, w, 0, 0}, bgr_, cv::IMREAD_COLOR);
}

TEST_F(JpegEncoderTest, ReusesTheOutputBuffer) {
  std::vector<std::uint8_t> out;
  std::string error;
  ASSERT_TRUE(encoder_.encode(bgr_, 90, out, error));
  const std::uint8_t* first = out.data();
  const std::size_t capacity = out.capacity();
  ASSERT_TRUE(encoder_.encode(bgr_, 90, out, error));
  EXPECT_EQ(out.data(), first);  // no reallocation in steady state
  EXPECT_EQ(out.capacity(), capacity);
}

TEST_F(JpegEncoderTest, RejectsBadInput) {
  std::vector<std::uint8_t> out;
  std::string error;
  EXPECT_FALSE(encoder_.encode(bgr_, 0, out, error));
  EXPECT_FALSE(encoder_.encode(cv::Mat(), 90, out, error));
  EXPECT_FALSE(encoder_.encode(Frame{PixelFormat::BGR24, bgr_.data, bgr_.cols, bgr_.rows, 10, 0, 0},
                               90, out, error));
  EXPECT_FALSE(error.empty());
}

}  // namespace
}  // namespace keyframed
