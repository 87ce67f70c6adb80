#include "core/resize.h"

#include <algorithm>
#include <cmath>

#include <opencv2/core/hal/intrin.hpp>

namespace keyframed {

void halveArea(GrayView src, cv::Mat& dst) {
  const int w = src.width / 2;
  const int h = src.height / 2;
  dst.create(h, w, CV_8UC1);
  for (int y = 0; y < h; ++y) {
    const std::uint8_t* a = src.row(2 * y);
    const std::uint8_t* b = src.row(2 * y + 1);
    std::uint8_t* d = dst.ptr<std::uint8_t>(y);
    int x = 0;
#if CV_SIMD128
    // 16 bytes read as 8 little-endian 16-bit lanes hold 8 horizontal pairs:
    // low byte + high byte is the pair's sum. 16 outputs a step.
    const cv::v_uint16x8 lowByte = cv::v_setall_u16(0xFF), two = cv::v_setall_u16(2);
    for (; x + 16 <= w; x += 16) {
      const cv::v_uint16x8 a0 = cv::v_reinterpret_as_u16(cv::v_load(a + 2 * x));
      const cv::v_uint16x8 a1 = cv::v_reinterpret_as_u16(cv::v_load(a + 2 * x + 16));
      const cv::v_uint16x8 b0 = cv::v_reinterpret_as_u16(cv::v_load(b + 2 * x));
      const cv::v_uint16x8 b1 = cv::v_reinterpret_as_u16(cv::v_load(b + 2 * x + 16));
      const cv::v_uint16x8 s0 =
          ((a0 & lowByte) + (a0 >> 8) + (b0 & lowByte) + (b0 >> 8) + two) >> 2;
      const cv::v_uint16x8 s1 =
          ((a1 & lowByte) + (a1 >> 8) + (b1 & lowByte) + (b1 >> 8) + two) >> 2;
      cv::v_store(d + x, cv::v_pack(s0, s1));
    }
#endif
    for (; x < w; ++x)
      d[x] =
          static_cast<std::uint8_t>((a[2 * x] + a[2 * x + 1] + b[2 * x] + b[2 * x + 1] + 2) >> 2);
  }
}

namespace {

// cv::resize's INTER_LINEAR source position for destination index d: pixel
// centres aligned, clamped to the image. Returns the left/top index and the
// fraction towards the next one.
void linearPosition(int d, double scale, int n, int& i0, int& i1, float& frac) {
  float f = static_cast<float>((d + 0.5) * scale - 0.5);
  int i = static_cast<int>(std::floor(f));
  f -= static_cast<float>(i);
  if (i < 0) {
    i = 0;
    f = 0.f;
  }
  if (i >= n - 1) {
    i = n - 1;
    f = 0.f;
  }
  i0 = i;
  i1 = std::min(i + 1, n - 1);
  frac = f;
}

}  // namespace

void BilinearResizer::prepare(cv::Size src, cv::Size dst) {
  if (src == src_ && dst == dst_) return;
  src_ = src;
  dst_ = dst;
  const auto dw = static_cast<std::size_t>(dst.width);
  const auto dh = static_cast<std::size_t>(dst.height);
  x0_.resize(dw);
  wx_.resize(dw);
  y0_.resize(dh);
  y1_.resize(dh);
  wy_.resize(dh);
  // One more than the source width: the last column's right neighbour (weight
  // 0) is read without a branch.
  rowV_.assign(static_cast<std::size_t>(src.width) + 1, 0);
  const double sx = static_cast<double>(src.width) / dst.width;
  const double sy = static_cast<double>(src.height) / dst.height;
  float f = 0.f;
  int x1 = 0;
  for (std::size_t i = 0; i < dw; ++i) {
    linearPosition(static_cast<int>(i), sx, src.width, x0_[i], x1, f);
    wx_[i] = static_cast<std::uint16_t>(std::lround(f * 2048.f));
  }
  for (std::size_t i = 0; i < dh; ++i) {
    linearPosition(static_cast<int>(i), sy, src.height, y0_[i], y1_[i], f);
    wy_[i] = static_cast<std::uint16_t>(std::lround(f * 256.f));
  }
  // 3:2 (960 -> 640, the step after halving 1080p or 4K): the columns and
  // weights repeat every two outputs, which vectorises without gathers.
  threeHalves_ = src.width * 2 == dst.width * 3 && dw >= 2;
  for (std::size_t i = 0; threeHalves_ && i < dw; ++i)
    threeHalves_ = x0_[i] == static_cast<int>(i / 2 * 3 + i % 2) && wx_[i] == wx_[i % 2];
  if (threeHalves_) {
    // Fractions of 65536 (65535 for 1): v_mul_hi keeps the high half.
    auto frac = [](unsigned w2048) {
      return static_cast<std::uint16_t>(std::min(65535u, w2048 * 32u));
    };
    evenW_[0] = frac(2048u - wx_[0]);
    evenW_[1] = frac(wx_[0]);
    oddW_[0] = frac(2048u - wx_[1]);
    oddW_[1] = frac(wx_[1]);
  }
}

void BilinearResizer::resize(GrayView src, cv::Size size, cv::Mat& dst) {
  prepare(cv::Size(src.width, src.height), size);
  dst.create(size, CV_8UC1);
  const int sw = src.width;
  std::uint16_t* v = rowV_.data();
  for (int dy = 0; dy < size.height; ++dy) {
    // Vertical first, over whole contiguous rows (vectorised by the compiler;
    // 255 * 256 fits 16 bits), then the horizontal step gathers from it.
    const std::uint8_t* r0 = src.row(y0_[static_cast<std::size_t>(dy)]);
    const std::uint8_t* r1 = src.row(y1_[static_cast<std::size_t>(dy)]);
    const std::uint16_t b1 = wy_[static_cast<std::size_t>(dy)];
    const auto b0 = static_cast<std::uint16_t>(256 - b1);
    int x = 0;
#if CV_SIMD128
    const cv::v_uint16x8 vb0 = cv::v_setall_u16(b0), vb1 = cv::v_setall_u16(b1);
    for (; x + 8 <= sw; x += 8)
      cv::v_store(v + x, cv::v_mul_wrap(cv::v_load_expand(r0 + x), vb0) +
                             cv::v_mul_wrap(cv::v_load_expand(r1 + x), vb1));
#endif
    for (; x < sw; ++x) v[x] = static_cast<std::uint16_t>(r0[x] * b0 + r1[x] * b1);
    std::uint8_t* d = dst.ptr<std::uint8_t>(dy);
    int dx = 0;
#if CV_SIMD128
    if (threeHalves_) {
      // Output 2k from columns 3k, 3k + 1 and output 2k + 1 from 3k + 1, 3k + 2,
      // with one weight each: 16 outputs from 24 columns a step. The weights
      // as 16-bit fractions; the high half of each product is the value x256.
      const cv::v_uint16x8 e0 = cv::v_setall_u16(evenW_[0]), e1 = cv::v_setall_u16(evenW_[1]);
      const cv::v_uint16x8 o0 = cv::v_setall_u16(oddW_[0]), o1 = cv::v_setall_u16(oddW_[1]);
      const cv::v_uint16x8 half = cv::v_setall_u16(128);
      for (; dx + 16 <= size.width; dx += 16) {
        cv::v_uint16x8 c0, c1, c2;
        cv::v_load_deinterleave(v + dx / 2 * 3, c0, c1, c2);
        const cv::v_uint16x8 even = (cv::v_mul_hi(c0, e0) + cv::v_mul_hi(c1, e1) + half) >> 8;
        const cv::v_uint16x8 odd = (cv::v_mul_hi(c1, o0) + cv::v_mul_hi(c2, o1) + half) >> 8;
        cv::v_uint16x8 lo, hi;
        cv::v_zip(even, odd, lo, hi);
        cv::v_store(d + dx, cv::v_pack(lo, hi));
      }
    }
#endif
    const std::int32_t* xs = x0_.data();
    const std::uint16_t* ws = wx_.data();
    for (; dx < size.width; ++dx) {
      const std::uint16_t* p = v + xs[dx];
      const std::uint32_t a1 = ws[dx];
      d[dx] = static_cast<std::uint8_t>((p[0] * (2048u - a1) + p[1] * a1 + (1u << 18)) >> 19);
    }
  }
}

GrayView DownScaler::scaleToWidth(GrayView src, int width) {
  if (width <= 0 || src.width <= width) return src;
  // At least a row (a 1920x1 frame would round to none).
  const int h = std::max(
      1, static_cast<int>(std::lround(static_cast<double>(src.height) * width / src.width)));
  return scale(src, width, h);
}

GrayView DownScaler::scale(GrayView src, int width, int height) {
  if (src.width <= width) return src;
  std::size_t level = 0;
  // (Never down to no rows: a frame a few rows high is scaled in one bilinear step.)
  while (src.width / 2 >= width && src.height / 2 >= std::max(height, 1)) {
    if (halves_.size() <= level) halves_.emplace_back();
    halveArea(src, halves_[level]);
    src = GrayView::of(halves_[level++]);
  }
  if (src.width != width) {
    bilinear_.resize(src, cv::Size(width, height), out_);
    src = GrayView::of(out_);
  }
  return src;
}

}  // namespace keyframed
