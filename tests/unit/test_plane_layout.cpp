#include "capture/plane_layout.h"

#include <cstdint>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "capture/frame_queue.h"

namespace keyframed {
namespace {

constexpr int kStride = 8;  // luma row bytes (width 6 + 2 of row padding)
constexpr int kHeight = 4;

// Plane i filled with 10*(i+1) + byte index, so a byte says where it came from.
std::vector<std::uint8_t> plane(int i, std::size_t bytes) {
  std::vector<std::uint8_t> p(bytes);
  for (std::size_t k = 0; k < bytes; ++k) p[k] = static_cast<std::uint8_t>(10 * (i + 1) + k);
  return p;
}

std::vector<std::size_t> sizes(const PlaneSizes& p) {
  return {p.begin(), p.end()};
}

TEST(PlaneLayout, SizesPerFormat) {
  EXPECT_EQ(sizes(planeSizes(PixelFormat::NV12, 8, 4)), (std::vector<std::size_t>{32, 16}));
  EXPECT_EQ(sizes(planeSizes(PixelFormat::YUV420, 8, 4)), (std::vector<std::size_t>{32, 8, 8}));
  EXPECT_EQ(sizes(planeSizes(PixelFormat::YUV420, 8, 5)), (std::vector<std::size_t>{40, 12, 12}));
  EXPECT_EQ(sizes(planeSizes(PixelFormat::YUYV, 16, 4)), (std::vector<std::size_t>{64}));
}

TEST(PlaneLayout, BackToBackPlanesAreUsedInPlace) {
  // One dmabuf, NV12 with the UV plane right after Y: no copy.
  std::vector<std::uint8_t> buf(48, 7);
  std::vector<std::uint8_t> packed;
  std::string error;
  const PlaneSpan planes[] = {{buf.data(), 32}, {buf.data() + 32, 16}};
  EXPECT_EQ(contiguousFrame(PixelFormat::NV12, kStride, kHeight, planes, packed, error),
            buf.data());
  EXPECT_TRUE(packed.empty());
}

TEST(PlaneLayout, PaddedPlanesInOneBufferArePacked) {
  // YUV420 in one dmabuf with 64-byte aligned plane offsets (Y 32 bytes, U at 64, V at
  // 128): reading 1.5 x stride x height from plane 0 would take padding for chroma.
  std::vector<std::uint8_t> buf(192, 0xEE);
  const auto y = plane(0, 32), u = plane(1, 8), v = plane(2, 8);
  std::copy(y.begin(), y.end(), buf.begin());
  std::copy(u.begin(), u.end(), buf.begin() + 64);
  std::copy(v.begin(), v.end(), buf.begin() + 128);
  const PlaneSpan planes[] = {{buf.data(), 64}, {buf.data() + 64, 64}, {buf.data() + 128, 64}};
  std::vector<std::uint8_t> packed;
  std::string error;
  const std::uint8_t* data =
      contiguousFrame(PixelFormat::YUV420, kStride, kHeight, planes, packed, error);
  ASSERT_EQ(data, packed.data()) << error;
  std::vector<std::uint8_t> want;
  for (const auto* p : {&y, &u, &v}) {
    for (std::uint8_t b : *p) want.push_back(b);
  }
  ASSERT_GE(packed.size(), want.size());
  EXPECT_EQ(std::vector<std::uint8_t>(packed.begin(), packed.begin() + 48), want);

  // What the capture thread then copies is exactly the picture, no padding byte.
  Frame f{PixelFormat::YUV420, data, 6, kHeight, kStride, 0, 0};
  FrameBuffer copy;
  copyFrame(f, copy);
  EXPECT_EQ(copy.pixels, want);
}

TEST(PlaneLayout, PlanesInSeparateBuffersArePacked) {
  const auto y = plane(0, 32), uv = plane(1, 16);
  const PlaneSpan planes[] = {{y.data(), y.size()}, {uv.data(), uv.size()}};
  std::vector<std::uint8_t> packed;
  std::string error;
  const std::uint8_t* data =
      contiguousFrame(PixelFormat::NV12, kStride, kHeight, planes, packed, error);
  ASSERT_NE(data, nullptr) << error;
  EXPECT_EQ(std::vector<std::uint8_t>(data, data + 32), y);
  EXPECT_EQ(std::vector<std::uint8_t>(data + 32, data + 48), uv);
  // The next frame reuses the buffer: no allocation per frame.
  const std::uint8_t* again =
      contiguousFrame(PixelFormat::NV12, kStride, kHeight, planes, packed, error);
  EXPECT_EQ(again, data);
}

TEST(PlaneLayout, OneWholePlaneIsUsedAsIs) {
  std::vector<std::uint8_t> buf(48);
  const PlaneSpan planes[] = {{buf.data(), buf.size()}};
  std::vector<std::uint8_t> packed;
  std::string error;
  EXPECT_EQ(contiguousFrame(PixelFormat::NV12, kStride, kHeight, planes, packed, error),
            buf.data());
}

TEST(PlaneLayout, ShortOrMissingPlanesAreAOneLineError) {
  std::vector<std::uint8_t> buf(48);
  std::vector<std::uint8_t> packed;
  std::string error;
  const PlaneSpan shortUv[] = {{buf.data(), 32}, {buf.data() + 32, 8}};
  EXPECT_EQ(contiguousFrame(PixelFormat::NV12, kStride, kHeight, shortUv, packed, error), nullptr);
  EXPECT_EQ(error, "plane 1 holds 8 bytes, NV12 needs 16");
  const PlaneSpan onlyY[] = {{buf.data(), 32}};
  EXPECT_EQ(contiguousFrame(PixelFormat::YUV420, kStride, kHeight, onlyY, packed, error), nullptr);
  EXPECT_EQ(error, "frame buffer has 1 planes, YUV420 needs 3");
}

}  // namespace
}  // namespace keyframed
