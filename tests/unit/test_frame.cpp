#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include "core/frame.h"

namespace keyframed {
namespace {

TEST(Frame, Nv12LumaIsAViewWithoutACopy) {
  std::vector<std::uint8_t> nv12(64 * 48 * 3 / 2, 0);
  for (std::size_t i = 0; i < 64 * 48; ++i) nv12[i] = static_cast<std::uint8_t>(i);
  Frame f{PixelFormat::NV12, nv12.data(), 64, 48, 64, 0, 0};
  LumaExtractor x;
  const GrayView v = x.luma(f);
  EXPECT_EQ(v.data, nv12.data());
  EXPECT_EQ(v.width, 64);
  EXPECT_EQ(v.stride, 64);
}

TEST(Frame, Yuv420LumaIsAViewOfThePaddedYPlane) {
  // I420 with padded rows (stride 80 for a 64-px-wide image), as cameras deliver.
  std::vector<std::uint8_t> i420(80 * 48 * 3 / 2, 0);
  for (int y = 0; y < 48; ++y)
    for (int x = 0; x < 64; ++x)
      i420[static_cast<std::size_t>(y * 80 + x)] = static_cast<std::uint8_t>(x + y);
  Frame f{PixelFormat::YUV420, i420.data(), 64, 48, 80, 0, 0};
  LumaExtractor x;
  const GrayView v = x.luma(f);
  EXPECT_EQ(v.data, i420.data());
  EXPECT_EQ(v.width, 64);
  EXPECT_EQ(v.height, 48);
  EXPECT_EQ(v.stride, 80);
  EXPECT_EQ(v.row(7)[9], 16);
}

TEST(Frame, BgrIsConvertedOnceIntoAReusedBuffer) {
  cv::Mat bgr(48, 64, CV_8UC3, cv::Scalar(10, 20, 30));
  LumaExtractor x;
  const GrayView a = x.luma(Frame::ofBgr(bgr, 0, 0));
  const GrayView b = x.luma(Frame::ofBgr(bgr, 1, 0));
  EXPECT_EQ(a.data, b.data);  // same buffer, no new allocation
  cv::Mat expect;
  cv::cvtColor(bgr, expect, cv::COLOR_BGR2GRAY);
  EXPECT_EQ(a.row(5)[5], expect.at<uchar>(5, 5));
}

TEST(Frame, YuyvLumaTakesEveryOtherByte) {
  cv::Mat yuyv(4, 4, CV_8UC2);
  for (int y = 0; y < 4; ++y)
    for (int x = 0; x < 4; ++x)
      yuyv.at<cv::Vec2b>(y, x) = cv::Vec2b(static_cast<uchar>(y * 4 + x), 200);
  Frame f{PixelFormat::YUYV, yuyv.data, 4, 4, static_cast<int>(yuyv.step[0]), 0, 0};
  LumaExtractor x;
  const GrayView v = x.luma(f);
  EXPECT_EQ(v.row(2)[3], 11);
}

}  // namespace
}  // namespace keyframed
