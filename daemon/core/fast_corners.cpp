#include "core/fast_corners.h"

#include <algorithm>
#include <bit>
#include <cstring>

#include <opencv2/core/hal/intrin.hpp>

namespace keyframed {

namespace {

// The radius-3 circle, clockwise from the top.
constexpr int kCircleX[16] = {0, 1, 2, 3, 3, 3, 2, 1, 0, -1, -2, -3, -3, -3, -2, -1};
constexpr int kCircleY[16] = {-3, -3, -2, -1, 0, 1, 2, 3, 3, 3, 2, 1, 0, -1, -2, -3};

#if CV_SIMD128
// Per lane, the largest minimum over the 16 arcs of 9 of the circle points'
// saturated differences from the centre (brighter: point - centre).
cv::v_uint8x16 bestArc(const std::uint8_t* p, const int* circle, const cv::v_uint8x16& center,
                       bool brighter) {
  cv::v_uint8x16 d[16];
  for (int k = 0; k < 16; ++k) {
    const cv::v_uint8x16 v = cv::v_load(p + circle[k]);
    d[k] = brighter ? v - center : center - v;  // saturating
  }
  cv::v_uint8x16 m3[16];  // runs of 3; an arc of 9 is three of them
  for (int k = 0; k < 16; ++k) m3[k] = cv::v_min(cv::v_min(d[k], d[(k + 1) & 15]), d[(k + 2) & 15]);
  cv::v_uint8x16 best = cv::v_setzero_u8();
  for (int k = 0; k < 16; ++k)
    best = cv::v_max(best, cv::v_min(cv::v_min(m3[k], m3[(k + 3) & 15]), m3[(k + 6) & 15]));
  return best;
}
#endif

}  // namespace

FastCorners::FastCorners(int threshold, bool nonmaxSuppression)
    : threshold_(std::clamp(threshold, 0, 255)), nonmax_(nonmaxSuppression) {}

int FastCorners::score(const std::uint8_t* p, const int* circle, bool brighter) {
  // d around the circle (negated for darker corners), wrapped so that every
  // arc of 9 is contiguous. Only the corner's own polarity can reach the
  // threshold: two arcs of 9 of 16 overlap.
  alignas(16) std::int16_t d[24];
  const int c = p[0];
  for (int k = 0; k < 16; ++k)
    d[k] = static_cast<std::int16_t>(brighter ? p[circle[k]] - c : c - p[circle[k]]);
  for (int k = 0; k < 8; ++k) d[16 + k] = d[k];
  // Lane s: the minimum over the arc starting at s (s and s + 8).
  cv::v_int16x8 m0 = cv::v_load(d), m1 = cv::v_load(d + 8);
  for (int k = 1; k <= 8; ++k) {
    m0 = cv::v_min(m0, cv::v_load(d + k));
    m1 = cv::v_min(m1, cv::v_load(d + 8 + k));
  }
  // The largest threshold t with every pixel of some arc beyond t.
  return cv::v_reduce_max(cv::v_max(m0, m1)) - 1;
}

void FastCorners::detect(GrayView image, std::vector<cv::KeyPoint>& out) {
  out.clear();
  const int w = image.width;
  const int h = image.height;
  if (w < 7 || h < 7) return;
  const auto rowLen = static_cast<std::size_t>(w);
  if (scores_.size() != 3 * rowLen) {
    scores_.assign(3 * rowLen, 0);
    cols_.assign(3 * rowLen, 0);
  } else {
    std::fill(scores_.begin(), scores_.end(), std::uint8_t{0});
  }
  std::fill(std::begin(count_), std::end(count_), 0);
  int circle[16];
  for (int k = 0; k < 16; ++k) circle[k] = kCircleY[k] * image.stride + kCircleX[k];
  const int t = threshold_;

  // Row i is detected at step i and its corners are kept or suppressed at step
  // i + 1, once the row below has its responses (as cv::FAST, so the order
  // matches).
  for (int i = 3; i <= h - 3; ++i) {
    const int ci = i % 3;
    std::uint8_t* curr = scores_.data() + static_cast<std::size_t>(ci) * rowLen;
    std::int32_t* currCols = cols_.data() + static_cast<std::size_t>(ci) * rowLen;
    std::memset(curr, 0, rowLen);
    int n = 0;
    if (i < h - 3) {
      const std::uint8_t* row = image.row(i);
      int x = 3;
#if CV_SIMD128
      // 16 pixels at a time. Quick rejection first: an arc of 9 holds two
      // neighbouring points of {0, 4, 8, 12} and two of {2, 6, 10, 14}.
      const cv::v_uint8x16 vt = cv::v_setall_u8(static_cast<std::uint8_t>(t));
      for (; x + 16 <= w - 3; x += 16) {
        const std::uint8_t* p = row + x;
        const cv::v_uint8x16 center = cv::v_load(p);
        const cv::v_uint8x16 hi = center + vt;  // saturating
        const cv::v_uint8x16 lo = center - vt;
        cv::v_uint8x16 b[8], dk[8];
        for (int k = 0; k < 8; ++k) {
          const cv::v_uint8x16 v = cv::v_load(p + circle[2 * k]);
          b[k] = v > hi;
          dk[k] = v < lo;
        }
        // b[k] is circle point 2k: {0, 4, 8, 12} are even k, {2, 6, 10, 14} odd k.
        const cv::v_uint8x16 b1 = (b[0] & b[2]) | (b[2] & b[4]) | (b[4] & b[6]) | (b[6] & b[0]);
        const cv::v_uint8x16 b2 = (b[1] & b[3]) | (b[3] & b[5]) | (b[5] & b[7]) | (b[7] & b[1]);
        const cv::v_uint8x16 d1 =
            (dk[0] & dk[2]) | (dk[2] & dk[4]) | (dk[4] & dk[6]) | (dk[6] & dk[0]);
        const cv::v_uint8x16 d2 =
            (dk[1] & dk[3]) | (dk[3] & dk[5]) | (dk[5] & dk[7]) | (dk[7] & dk[1]);
        if (cv::v_signmask((b1 & b2) | (d1 & d2)) == 0) continue;
        // Responses of all 16 pixels, with saturating differences: an arc
        // holding a pixel not beyond the centre has minimum 0, so the best arc
        // of a corner (minimum >= 1) is exact, and the other polarity gives 0.
        const cv::v_uint8x16 best =
            cv::v_max(bestArc(p, circle, center, true), bestArc(p, circle, center, false));
        const cv::v_uint8x16 corner = best > vt;
        const auto bits = static_cast<unsigned>(cv::v_signmask(corner));
        if (bits == 0) continue;
        cv::v_store(curr + x, (best - cv::v_setall_u8(1)) & corner);
        for (unsigned m = bits; m != 0; m &= m - 1) currCols[n++] = x + std::countr_zero(m);
      }
#endif
      for (; x < w - 3; ++x) {
        const int sc = std::max(score(row + x, circle, true), score(row + x, circle, false));
        if (sc >= t) {
          curr[x] = static_cast<std::uint8_t>(sc);
          currCols[n++] = x;
        }
      }
    }
    count_[ci] = n;

    const int py = i - 1;
    if (py < 3) continue;
    const int pi = py % 3;
    const std::uint8_t* prev = scores_.data() + static_cast<std::size_t>(pi) * rowLen;
    const std::uint8_t* pprev = scores_.data() + static_cast<std::size_t>((py - 1) % 3) * rowLen;
    const std::int32_t* prevCols = cols_.data() + static_cast<std::size_t>(pi) * rowLen;
    for (int k = 0; k < count_[pi]; ++k) {
      const int x = prevCols[k];
      const int s = prev[x];
      if (nonmax_ && !(s > prev[x - 1] && s > prev[x + 1] && s > pprev[x - 1] && s > pprev[x] &&
                       s > pprev[x + 1] && s > curr[x - 1] && s > curr[x] && s > curr[x + 1]))
        continue;
      out.emplace_back(static_cast<float>(x), static_cast<float>(py), 7.0f, -1.0f,
                       static_cast<float>(s));
    }
  }
}

}  // namespace keyframed
