#include "core/homography.h"

#include <algorithm>
#include <cmath>

#include <opencv2/core.hpp>

namespace keyframed {
namespace {

// Gaussian elimination with partial pivoting on an 8x8 system, in place.
bool solve8(double a[8][8], double b[8], double x[8]) {
  for (int c = 0; c < 8; ++c) {
    int p = c;
    for (int r = c + 1; r < 8; ++r)
      if (std::fabs(a[r][c]) > std::fabs(a[p][c])) p = r;
    if (std::fabs(a[p][c]) < 1e-12) return false;
    if (p != c) {
      for (int k = 0; k < 8; ++k) std::swap(a[c][k], a[p][k]);
      std::swap(b[c], b[p]);
    }
    for (int r = c + 1; r < 8; ++r) {
      const double f = a[r][c] / a[c][c];
      if (f == 0.0) continue;
      for (int k = c; k < 8; ++k) a[r][k] -= f * a[c][k];
      b[r] -= f * b[c];
    }
  }
  for (int r = 7; r >= 0; --r) {
    double s = b[r];
    for (int k = r + 1; k < 8; ++k) s -= a[r][k] * x[k];
    x[r] = s / a[r][r];
  }
  return std::isfinite(x[0]) && std::isfinite(x[7]);
}

// Hartley normalisation: centroid to the origin, mean distance sqrt(2).
cv::Matx33d normaliser(const std::vector<cv::Point2f>& pts) {
  double cx = 0, cy = 0;
  for (const auto& p : pts) {
    cx += p.x;
    cy += p.y;
  }
  const double n = static_cast<double>(pts.size());
  cx /= n;
  cy /= n;
  double d = 0;
  for (const auto& p : pts) d += std::hypot(p.x - cx, p.y - cy);
  d /= n;
  const double s = d > 1e-12 ? std::sqrt(2.0) / d : 1.0;
  return {s, 0, -s * cx, 0, s, -s * cy, 0, 0, 1};
}

std::uint64_t xorshift(std::uint64_t& s) {
  s ^= s << 13;
  s ^= s >> 7;
  s ^= s << 17;
  return s;
}

// Twice the signed area of the triangle p, q, r.
double cross(const cv::Point2d& p, const cv::Point2d& q, const cv::Point2d& r) {
  return (q.x - p.x) * (r.y - p.y) - (q.y - p.y) * (r.x - p.x);
}

// A sample four points can fit a homography to: no three nearly on a line (in the
// normalised coordinates, where the points spread over about 2 x 2), in either
// image, and each triangle turning the same way in both (a camera does not mirror
// the ground). Near-collinear samples, common when the texture is a road or a
// field edge, fit any homography at all.
bool goodSample(const cv::Point2d* a, const cv::Point2d* b, const int* idx) {
  constexpr double kMinCross = 1e-2;
  static constexpr int kTriangles[4][3] = {{0, 1, 2}, {0, 1, 3}, {0, 2, 3}, {1, 2, 3}};
  for (const auto& t : kTriangles) {
    const double ca = cross(a[idx[t[0]]], a[idx[t[1]]], a[idx[t[2]]]);
    const double cb = cross(b[idx[t[0]]], b[idx[t[1]]], b[idx[t[2]]]);
    if (std::fabs(ca) < kMinCross || std::fabs(cb) < kMinCross || (ca > 0) != (cb > 0))
      return false;
  }
  return true;
}

}  // namespace

bool solveHomography(const cv::Point2d* src, const cv::Point2d* dst, const int* idx, int n,
                     cv::Matx33d& out) {
  // Normal equations of the DLT rows (x y 1 0 0 0 -ux -uy | u) and
  // (0 0 0 x y 1 -vx -vy | v); exact for n == 4.
  double ata[8][8] = {};
  double atb[8] = {};
  for (int i = 0; i < n; ++i) {
    const cv::Point2d p = src[idx ? idx[i] : i];
    const cv::Point2d q = dst[idx ? idx[i] : i];
    const double r1[8] = {p.x, p.y, 1, 0, 0, 0, -q.x * p.x, -q.x * p.y};
    const double r2[8] = {0, 0, 0, p.x, p.y, 1, -q.y * p.x, -q.y * p.y};
    for (int r = 0; r < 8; ++r) {
      for (int c = r; c < 8; ++c) ata[r][c] += r1[r] * r1[c] + r2[r] * r2[c];
      atb[r] += r1[r] * q.x + r2[r] * q.y;
    }
  }
  for (int r = 0; r < 8; ++r)
    for (int c = 0; c < r; ++c) ata[r][c] = ata[c][r];
  double h[8];
  if (!solve8(ata, atb, h)) return false;
  out = cv::Matx33d(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0);
  return true;
}

HomographyFit RansacHomography::fit(const std::vector<cv::Point2f>& src,
                                    const std::vector<cv::Point2f>& dst, double thresholdPx,
                                    std::vector<unsigned char>& inlierMask, double confidence,
                                    int maxIterations) {
  HomographyFit best;
  const int n = static_cast<int>(std::min(src.size(), dst.size()));
  inlierMask.assign(static_cast<std::size_t>(n), 0);
  if (n < 4) return best;

  const cv::Matx33d ts = normaliser(src);
  const cv::Matx33d td = normaliser(dst);
  a_.resize(static_cast<std::size_t>(n));
  b_.resize(static_cast<std::size_t>(n));
  for (int i = 0; i < n; ++i) {
    const auto k = static_cast<std::size_t>(i);
    a_[k] = {ts(0, 0) * src[k].x + ts(0, 2), ts(1, 1) * src[k].y + ts(1, 2)};
    b_[k] = {td(0, 0) * dst[k].x + td(0, 2), td(1, 1) * dst[k].y + td(1, 2)};
  }
  const cv::Matx33d tdInv = td.inv();
  const double thr2 = thresholdPx * thresholdPx;

  // Inliers by transfer error in pixels.
  auto score = [&](const cv::Matx33d& hn, std::vector<unsigned char>& mask) {
    const cv::Matx33d h = tdInv * hn * ts;
    int count = 0;
    for (int i = 0; i < n; ++i) {
      const auto k = static_cast<std::size_t>(i);
      const double x = src[k].x, y = src[k].y;
      const double w = h(2, 0) * x + h(2, 1) * y + h(2, 2);
      bool in = false;
      if (w > 1e-9) {
        const double u = (h(0, 0) * x + h(0, 1) * y + h(0, 2)) / w - dst[k].x;
        const double v = (h(1, 0) * x + h(1, 1) * y + h(1, 2)) / w - dst[k].y;
        in = u * u + v * v < thr2;
      }
      mask[k] = in ? 1 : 0;
      count += in ? 1 : 0;
    }
    return count;
  };

  std::uint64_t seed = 0x9E3779B97F4A7C15ULL;
  bestMask_.assign(static_cast<std::size_t>(n), 0);
  int bestCount = 0;
  cv::Matx33d bestHn = cv::Matx33d::eye();
  int iterations = maxIterations;
  for (int it = 0; it < iterations; ++it) {
    int idx[4];
    for (int j = 0; j < 4; ++j) {
      bool fresh;
      do {
        idx[j] = static_cast<int>(xorshift(seed) % static_cast<std::uint64_t>(n));
        fresh = true;
        for (int k = 0; k < j; ++k) fresh &= idx[k] != idx[j];
      } while (!fresh);
    }
    if (!goodSample(a_.data(), b_.data(), idx)) continue;
    cv::Matx33d hn;
    if (!solveHomography(a_.data(), b_.data(), idx, 4, hn)) continue;
    const int count = score(hn, inlierMask);
    if (count > bestCount) {
      bestCount = count;
      bestHn = hn;
      std::swap(bestMask_, inlierMask);
      // Samples needed for `confidence` at this inlier ratio. A poor first sample
      // (a handful of inliers among hundreds) needs billions: compare as doubles,
      // an int would overflow and end the search at once.
      const double w = static_cast<double>(count) / n;
      const double denom = std::log(std::max(1e-12, 1.0 - w * w * w * w));
      if (denom < 0.0) {
        const double need = std::ceil(std::log(1.0 - confidence) / denom) + 1.0;
        if (need < static_cast<double>(iterations)) iterations = static_cast<int>(need);
      }
    }
  }
  if (bestCount < 4) return best;

  // Refit on all inliers (least squares), twice, re-selecting inliers each time.
  inlierMask = bestMask_;
  std::vector<unsigned char>& mask = inlierMask;
  for (int round = 0; round < 2; ++round) {
    inlierIdx_.clear();
    for (int i = 0; i < n; ++i)
      if (mask[static_cast<std::size_t>(i)]) inlierIdx_.push_back(i);
    cv::Matx33d hn;
    if (inlierIdx_.size() < 4 || !solveHomography(a_.data(), b_.data(), inlierIdx_.data(),
                                                  static_cast<int>(inlierIdx_.size()), hn))
      break;
    const int count = score(hn, bestMask_);
    if (count < bestCount) break;  // keep the better of sample and refit
    bestCount = count;
    bestHn = hn;
    std::swap(bestMask_, mask);
  }

  // The inliers must spread in both directions: along a line (one road, one edge)
  // they fix the mapping across it not at all. The smaller eigenvalue of their
  // covariance, in the normalised coordinates (variance about 1 a direction there).
  {
    double mx = 0, my = 0;
    int m = 0;
    for (int i = 0; i < n; ++i) {
      if (!inlierMask[static_cast<std::size_t>(i)]) continue;
      mx += a_[static_cast<std::size_t>(i)].x;
      my += a_[static_cast<std::size_t>(i)].y;
      ++m;
    }
    if (m < 4) return best;
    mx /= m;
    my /= m;
    double sxx = 0, syy = 0, sxy = 0;
    for (int i = 0; i < n; ++i) {
      if (!inlierMask[static_cast<std::size_t>(i)]) continue;
      const double dx = a_[static_cast<std::size_t>(i)].x - mx;
      const double dy = a_[static_cast<std::size_t>(i)].y - my;
      sxx += dx * dx;
      syy += dy * dy;
      sxy += dx * dy;
    }
    sxx /= m;
    syy /= m;
    sxy /= m;
    const double smaller =
        0.5 * (sxx + syy) - std::sqrt(0.25 * (sxx - syy) * (sxx - syy) + sxy * sxy);
    constexpr double kMinSpread = 1e-3;  // a standard deviation of 3 % of the spread
    if (!(smaller >= kMinSpread)) return best;
  }
  cv::Matx33d h = tdInv * bestHn * ts;
  if (std::fabs(h(2, 2)) < 1e-12) return best;
  h *= 1.0 / h(2, 2);
  best.ok = true;
  best.h = h;
  best.inliers = bestCount;
  return best;
}

}  // namespace keyframed
