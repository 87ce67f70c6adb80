#include "core/lk_tracker.h"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstring>
#include <utility>

namespace keyframed {

namespace {

// Index i mirrored into [0, n) without repeating the edge (BORDER_REFLECT_101).
int reflect101(int i, int n) {
  if (n <= 1) return 0;  // (n = 0 would never end)
  while (i < 0 || i >= n) i = i < 0 ? -i : 2 * n - 2 - i;
  return i;
}

// Fills the border of a w x h image stored at (b, b) inside `m`.
void fillBorder(cv::Mat& m, int w, int h, int b) {
  for (int y = 0; y < h; ++y) {
    std::uint8_t* row = m.ptr<std::uint8_t>(y + b) + b;
    for (int k = 1; k <= b; ++k) {
      row[-k] = row[reflect101(-k, w)];
      row[w - 1 + k] = row[reflect101(w - 1 + k, w)];
    }
  }
  const auto rowBytes = static_cast<std::size_t>(w + 2 * b);
  for (int k = 1; k <= b; ++k) {
    std::memcpy(m.ptr<std::uint8_t>(b - k), m.ptr<std::uint8_t>(b + reflect101(-k, h)), rowBytes);
    std::memcpy(m.ptr<std::uint8_t>(b + h - 1 + k),
                m.ptr<std::uint8_t>(b + reflect101(h - 1 + k, h)), rowBytes);
  }
}

GrayView interior(const cv::Mat& padded, int b) {
  return GrayView{padded.ptr<std::uint8_t>(b) + b, padded.cols - 2 * b, padded.rows - 2 * b,
                  static_cast<int>(padded.step[0])};
}

}  // namespace

void LkPyramid::build(GrayView image, int maxLevel, int window) {
  // Reads reach one pixel beyond a window (rounded up to a row stride)
  // hanging `window` pixels over the edge, plus one for the gradient; pyrDown
  // needs two.
  border_ = LkTracker::rowStride(window) + 2;
  const int b = border_;
  if (padded_.size() < static_cast<std::size_t>(maxLevel + 1))
    padded_.resize(static_cast<std::size_t>(maxLevel + 1));

  padded_[0].create(image.height + 2 * b, image.width + 2 * b, CV_8UC1);
  for (int y = 0; y < image.height; ++y)
    std::memcpy(padded_[0].ptr<std::uint8_t>(y + b) + b, image.row(y),
                static_cast<std::size_t>(image.width));
  fillBorder(padded_[0], image.width, image.height, b);
  levels_ = 1;

  int w = image.width;
  int h = image.height;
  for (int level = 1; level <= maxLevel; ++level) {
    const int dw = (w + 1) / 2;
    const int dh = (h + 1) / 2;
    if (dw <= window || dh <= window) break;
    const GrayView src = interior(padded_[static_cast<std::size_t>(level - 1)], b);
    cv::Mat& dstPadded = padded_[static_cast<std::size_t>(level)];
    dstPadded.create(dh + 2 * b, dw + 2 * b, CV_8UC1);
    // Source columns -2 .. 2 * dw + 1 lie inside the border.
    const int n = 2 * dw + 4;
    if (rowSums_.size() < static_cast<std::size_t>(n)) rowSums_.resize(static_cast<std::size_t>(n));
    std::uint16_t* t = rowSums_.data();
    for (int y = 0; y < dh; ++y) {
      const std::uint8_t* r0 = src.row(2 * y - 2) - 2;
      const std::uint8_t* r1 = src.row(2 * y - 1) - 2;
      const std::uint8_t* r2 = src.row(2 * y) - 2;
      const std::uint8_t* r3 = src.row(2 * y + 1) - 2;
      const std::uint8_t* r4 = src.row(2 * y + 2) - 2;
      for (int x = 0; x < n; ++x)
        t[x] = static_cast<std::uint16_t>(r0[x] + r4[x] + 4 * (r1[x] + r3[x]) + 6 * r2[x]);
      std::uint8_t* d = dstPadded.ptr<std::uint8_t>(y + b) + b;
      for (int x = 0; x < dw; ++x) {
        const std::uint16_t* s = t + 2 * x;
        d[x] =
            static_cast<std::uint8_t>((s[0] + s[4] + 4u * (s[1] + s[3]) + 6u * s[2] + 128u) >> 8);
      }
    }
    fillBorder(dstPadded, dw, dh, b);
    w = dw;
    h = dh;
    levels_ = level + 1;
  }
}

GrayView LkPyramid::level(int i) const {
  return interior(padded_[static_cast<std::size_t>(i)], border_);
}

int LkTracker::rowStride(int window) {
  constexpr int kStep = 2 * kLanes;  // the next image is read 8 pixels at a time
  return (window + kStep - 1) / kStep * kStep;
}

LkTracker::LkTracker(const LkConfig& config) : config_(config), stride_(rowStride(config.window)) {
  const auto w = static_cast<std::size_t>(config.window);
  const auto s = static_cast<std::size_t>(stride_);
  patch_.resize((w + 2) * (s + 2));
  i_.resize(w * s);
  ix_.resize(w * s);
  iy_.resize(w * s);
  rows_.resize(2 * s / kLanes);
}

void LkTracker::track(const LkPyramid& prev, const LkPyramid& next,
                      const std::vector<cv::Point2f>& prevPts, std::vector<cv::Point2f>& nextPts,
                      std::vector<unsigned char>& status) {
  nextPts.resize(prevPts.size());
  status.resize(prevPts.size());
  const int levels = std::min({prev.levels(), next.levels(), config_.maxLevel + 1});
  for (std::size_t i = 0; i < prevPts.size(); ++i)
    status[i] = trackPoint(prev, next, levels, prevPts[i], nextPts[i]) ? 1 : 0;
}

bool LkTracker::trackPoint(const LkPyramid& prev, const LkPyramid& next, int levels,
                           cv::Point2f prevPt, cv::Point2f& nextPt) {
  using namespace cv;
  const int win = config_.window;
  const int ws = stride_;  // window row in floats, a whole number of vectors
  const int nv = ws / kLanes;
  const int b = prev.border();
  const float half = static_cast<float>(win - 1) * 0.5f;
  const auto area = static_cast<float>(win * win);
  const auto eps2 = static_cast<float>(config_.epsilon * config_.epsilon);
  // cv::calcOpticalFlowPyrLK's units: gradients x32 (Scharr), squared, / 2^20.
  const float eigScale = 1.0f / (1024.0f * area);
  float* patch = patch_.data();
  float* iv = i_.data();
  float* gx = ix_.data();
  float* gy = iy_.data();
  v_float32x4* rowA = rows_.data();  // the next image, interpolated along x
  v_float32x4* rowB = rowA + nv;
  const int pw = ws + 2;

  Point2f guess;
  for (int level = levels - 1; level >= 0; --level) {
    const float scale = 1.0f / static_cast<float>(1 << level);
    guess = level == levels - 1 ? prevPt * scale : guess * 2.0f;
    const GrayView I = prev.level(level);
    const GrayView J = next.level(level);

    // The window in the previous image, with a one-pixel ring for the
    // gradient, interpolated at the point's sub-pixel position.
    const Point2f p = prevPt * scale - Point2f(half, half);
    const int px = static_cast<int>(std::floor(p.x));
    const int py = static_cast<int>(std::floor(p.y));
    if (px - 1 < -b || py - 1 < -b || px + ws + 1 > I.width - 1 + b ||
        py + win + 1 > I.height - 1 + b) {
      if (level == 0) return false;
      continue;
    }
    {
      const float a = p.x - static_cast<float>(px);
      const float c = p.y - static_cast<float>(py);
      const float w00 = (1 - a) * (1 - c), w01 = a * (1 - c), w10 = (1 - a) * c, w11 = a * c;
      for (int r = 0; r < win + 2; ++r) {
        const std::uint8_t* s0 = I.row(py - 1 + r) + px - 1;
        const std::uint8_t* s1 = s0 + I.stride;
        float* d = patch + r * pw;
        for (int x = 0; x < pw; ++x)
          d[x] = w00 * s0[x] + w01 * s0[x + 1] + w10 * s1[x] + w11 * s1[x + 1];
      }
    }
    // Scharr gradients in grey levels per pixel; columns past the window are
    // zero so that they add nothing below.
    v_float32x4 s11 = v_setzero_f32(), s12 = v_setzero_f32(), s22 = v_setzero_f32();
    for (int r = 0; r < win; ++r) {
      const float* u = patch + r * pw;
      const float* m = u + pw;
      const float* d = m + pw;
      float* ir = iv + r * ws;
      float* xr = gx + r * ws;
      float* yr = gy + r * ws;
      for (int x = 0; x < win; ++x) {
        ir[x] = m[x + 1];
        xr[x] = (3.0f * (u[x + 2] - u[x] + d[x + 2] - d[x]) + 10.0f * (m[x + 2] - m[x])) *
                (1.0f / 32.0f);
        yr[x] = (3.0f * (d[x] - u[x] + d[x + 2] - u[x + 2]) + 10.0f * (d[x + 1] - u[x + 1])) *
                (1.0f / 32.0f);
      }
      for (int x = win; x < ws; ++x) ir[x] = xr[x] = yr[x] = 0.0f;
      for (int k = 0; k < nv; ++k) {
        const v_float32x4 vx = v_load(xr + k * kLanes), vy = v_load(yr + k * kLanes);
        s11 = v_fma(vx, vx, s11);
        s12 = v_fma(vx, vy, s12);
        s22 = v_fma(vy, vy, s22);
      }
    }
    const float a11 = v_reduce_sum(s11), a12 = v_reduce_sum(s12), a22 = v_reduce_sum(s22);
    const float det = a11 * a22 - a12 * a12;
    const float minEig =
        (a22 + a11 - std::sqrt((a11 - a22) * (a11 - a22) + 4.0f * a12 * a12)) * 0.5f * eigScale;
    if (!(minEig >= static_cast<float>(config_.minEigenvalue)) ||
        det * (1.0f / (1024.0f * 1024.0f)) < FLT_EPSILON) {
      if (level == 0) return false;
      continue;
    }
    const float invDet = 1.0f / det;

    Point2f q = guess - Point2f(half, half);
    Point2f prevDelta(0, 0);
    for (int it = 0; it < config_.maxIterations; ++it) {
      // A step off any image (or not a number) fails before it is cast to int.
      if (!(std::fabs(q.x) < 1e6f && std::fabs(q.y) < 1e6f)) return false;
      const int qx = static_cast<int>(std::floor(q.x));
      const int qy = static_cast<int>(std::floor(q.y));
      if (qx < -b || qy < -b || qx + ws > J.width - 1 + b || qy + win > J.height - 1 + b) {
        if (level == 0) return false;
        break;
      }
      // Bilinear samples of the next image: along x on each of win + 1 rows,
      // then between consecutive rows.
      const v_float32x4 a = v_setall_f32(q.x - static_cast<float>(qx));
      const v_float32x4 c = v_setall_f32(q.y - static_cast<float>(qy));
      v_float32x4 b1 = v_setzero_f32(), b2 = v_setzero_f32();
      for (int r = 0; r <= win; ++r) {
        const std::uint8_t* s = J.row(qy + r) + qx;
        // 8 pixels a step (v_load_expand reads 8 bytes: no misaligned int load).
        for (int k = 0; k < nv; k += 2) {
          v_uint32x4 x0lo, x0hi, x1lo, x1hi;
          v_expand(v_load_expand(s + k * kLanes), x0lo, x0hi);
          v_expand(v_load_expand(s + k * kLanes + 1), x1lo, x1hi);
          const v_float32x4 j0 = v_cvt_f32(v_reinterpret_as_s32(x0lo));
          const v_float32x4 j1 = v_cvt_f32(v_reinterpret_as_s32(x1lo));
          const v_float32x4 j2 = v_cvt_f32(v_reinterpret_as_s32(x0hi));
          const v_float32x4 j3 = v_cvt_f32(v_reinterpret_as_s32(x1hi));
          rowB[k] = v_fma(j1 - j0, a, j0);
          rowB[k + 1] = v_fma(j3 - j2, a, j2);
        }
        if (r > 0) {
          const float* ir = iv + (r - 1) * ws;
          const float* xr = gx + (r - 1) * ws;
          const float* yr = gy + (r - 1) * ws;
          for (int k = 0; k < nv; ++k) {
            const v_float32x4 diff = v_fma(rowB[k] - rowA[k], c, rowA[k]) - v_load(ir + k * kLanes);
            b1 = v_fma(diff, v_load(xr + k * kLanes), b1);
            b2 = v_fma(diff, v_load(yr + k * kLanes), b2);
          }
        }
        std::swap(rowA, rowB);
      }
      const float sb1 = v_reduce_sum(b1), sb2 = v_reduce_sum(b2);
      const Point2f delta((a12 * sb2 - a22 * sb1) * invDet, (a12 * sb1 - a11 * sb2) * invDet);
      q += delta;
      if (delta.dot(delta) <= eps2) break;
      if (it > 0 && std::abs(delta.x + prevDelta.x) < 0.01f &&
          std::abs(delta.y + prevDelta.y) < 0.01f) {
        // Oscillating between two positions: settle in the middle.
        q -= delta * 0.5f;
        break;
      }
      prevDelta = delta;
    }
    guess = q + Point2f(half, half);
  }
  nextPt = guess;
  return true;
}

}  // namespace keyframed
