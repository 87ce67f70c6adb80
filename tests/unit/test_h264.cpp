#include <cstdint>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "output/h264.h"
#include "photos.h"

namespace keyframed {
namespace {

// A camera panning over real photographs: `count` grey-ish I420 pictures of w x h,
// moving 3 px a picture, with colour (the chroma planes from the photo too).
std::vector<std::vector<std::uint8_t>> panning(int count, int w, int h) {
  cv::Mat strip = test::photo("fruits.jpg", cv::IMREAD_COLOR);
  std::vector<std::vector<std::uint8_t>> out;
  if (strip.empty()) return out;
  cv::resize(strip, strip, cv::Size(w * 2, h), 0, 0, cv::INTER_AREA);
  for (int i = 0; i < count; ++i) {
    cv::Mat i420;
    cv::cvtColor(strip(cv::Rect(i * 3 % w, 0, w, h)), i420, cv::COLOR_BGR2YUV_I420);
    out.emplace_back(i420.datastart, i420.dataend);
  }
  return out;
}

// Picture i's time in a 30 fps stream.
std::int64_t at(std::size_t i) {
  return static_cast<std::int64_t>(i) * 1'000'000'000 / 30;
}

double psnr(const std::vector<std::uint8_t>& a, const std::vector<std::uint8_t>& b) {
  if (a.size() != b.size()) return 0.0;
  return cv::PSNR(
      cv::Mat(1, static_cast<int>(a.size()), CV_8UC1, const_cast<std::uint8_t*>(a.data())),
      cv::Mat(1, static_cast<int>(b.size()), CV_8UC1, const_cast<std::uint8_t*>(b.data())));
}

TEST(H264, EveryPictureIsOnePacketAndDecodesBackWithAnIdrEverySecond) {
  constexpr int w = 192, h = 108;
  const auto pictures = panning(65, w, h);
  ASSERT_EQ(pictures.size(), 65U);
  H264Encoder encoder({.keyframeIntervalNs = 1'000'000'000, .crf = 23, .fps = 30});
  H264Decoder decoder;
  std::vector<std::uint8_t> packet, back;
  std::string error;
  double worst = 100.0;
  for (std::size_t i = 0; i < pictures.size(); ++i) {
    SCOPED_TRACE("picture " + std::to_string(i));
    ASSERT_TRUE(encoder.encode({pictures[i].data(), w, h}, at(i), packet, error)) << error;
    ASSERT_FALSE(packet.empty());
    // Annex B, an IDR (with its SPS) exactly at 0, 30, 60: a reader can start there.
    EXPECT_EQ(packet[0] == 0 && packet[1] == 0 && (packet[2] == 1 || packet[3] == 1), true);
    const bool idr = i % 30 == 0;
    EXPECT_EQ(h264HasIdr(packet), idr);
    EXPECT_EQ(encoder.lastWasKeyframe(), idr);
    // No picture held back: each packet decodes to its own picture at once.
    int bw = 0, bh = 0;
    ASSERT_TRUE(decoder.decode(packet, back, bw, bh, error)) << error;
    EXPECT_EQ(bw, w);
    EXPECT_EQ(bh, h);
    worst = std::min(worst, psnr(back, pictures[i]));
  }
  EXPECT_GT(worst, 32.0);  // CRF 23 on a textured pan
}

TEST(H264, ADecoderStartsOnlyAtAnIdrPicture) {
  constexpr int w = 64, h = 48;
  const auto pictures = panning(32, w, h);
  ASSERT_EQ(pictures.size(), 32U);
  H264Encoder encoder({.keyframeIntervalNs = 1'000'000'000, .crf = 23, .fps = 30});
  std::vector<std::vector<std::uint8_t>> packets(pictures.size());
  std::string error;
  for (std::size_t i = 0; i < pictures.size(); ++i)
    ASSERT_TRUE(encoder.encode({pictures[i].data(), w, h}, at(i), packets[i], error)) << error;
  H264Decoder decoder;
  std::vector<std::uint8_t> back;
  int bw = 0, bh = 0;
  EXPECT_FALSE(decoder.decode(packets[5], back, bw, bh, error));  // no SPS, no reference
  EXPECT_FALSE(error.empty());
  ASSERT_TRUE(decoder.decode(packets[30], back, bw, bh, error)) << error;
  ASSERT_TRUE(decoder.decode(packets[31], back, bw, bh, error)) << error;
  EXPECT_GT(psnr(back, pictures[31]), 30.0);
}

TEST(H264, BadInputIsAnErrorNotACrash) {
  H264Encoder encoder({});
  std::vector<std::uint8_t> packet;
  std::string error;
  const std::vector<std::uint8_t> odd(33 * 25 * 3 / 2, 128);
  EXPECT_FALSE(encoder.encode({odd.data(), 33, 25}, 0, packet, error));
  EXPECT_NE(error.find("even size"), std::string::npos) << error;
  const std::vector<std::uint8_t> small(32 * 24 * 3 / 2, 128), big(64 * 48 * 3 / 2, 128);
  ASSERT_TRUE(encoder.encode({small.data(), 32, 24}, 0, packet, error)) << error;
  EXPECT_FALSE(encoder.encode({big.data(), 64, 48}, at(1), packet, error));
  EXPECT_NE(error.find("size changed from 32x24 to 64x48"), std::string::npos) << error;

  // Garbage, an empty packet and an IDR cut in half: refused or concealed, never a crash.
  H264Decoder decoder;
  std::vector<std::uint8_t> back;
  int w = 0, h = 0;
  EXPECT_FALSE(decoder.decode({}, back, w, h, error));
  cv::RNG rng(7);
  std::vector<std::uint8_t> garbage(4000);
  for (auto& b : garbage) b = static_cast<std::uint8_t>(rng.uniform(0, 256));
  EXPECT_FALSE(decoder.decode(garbage, back, w, h, error));
  H264Encoder again({});
  ASSERT_TRUE(again.encode({big.data(), 64, 48}, 0, packet, error)) << error;
  H264Decoder fresh;
  const std::vector<std::uint8_t> cut(packet.begin(), packet.begin() + packet.size() / 2);
  error.clear();
  if (fresh.decode(cut, back, w, h, error)) {  // concealed: still the stream's size
    EXPECT_EQ(w, 64);
    EXPECT_EQ(h, 48);
    EXPECT_EQ(back.size(), 64u * 48u * 3u / 2u);
  } else {
    EXPECT_FALSE(error.empty());  // refused, saying why
  }
}

TEST(H264, IdrIsFoundByItsNalUnitType) {
  const std::vector<std::uint8_t> idr = {0, 0,    0, 1, 0x67, 1, 2,    0, 0,
                                         1, 0x68, 3, 0, 0,    1, 0x65, 9};
  const std::vector<std::uint8_t> p = {0, 0, 0, 1, 0x41, 0x65, 0x65, 0, 0, 1, 0x06, 5};
  EXPECT_TRUE(h264HasIdr(idr));
  EXPECT_FALSE(h264HasIdr(p));  // 0x65 bytes inside a slice are not a NAL header
  EXPECT_FALSE(h264HasIdr({}));
  EXPECT_FALSE(h264HasIdr(std::vector<std::uint8_t>{0, 0, 1}));
}

}  // namespace
}  // namespace keyframed
