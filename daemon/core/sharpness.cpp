#include "core/sharpness.h"

#include <algorithm>
#include <cmath>
#include <string>

#include <opencv2/core/hal/intrin.hpp>
#include <opencv2/imgproc.hpp>

namespace keyframed {

namespace {

struct RowSums {
  std::int64_t sum = 0;
  std::int64_t sumSq = 0;
  std::int64_t n = 0;
};

// Laplacian at x = 1, 1 + step, ... of one row, exact integer sums.
RowSums rowScalar(const std::uint8_t* up, const std::uint8_t* mid, const std::uint8_t* down, int x0,
                  int width, int step) {
  RowSums r;
  for (int x = x0; x < width - 1; x += step) {
    const int l = up[x] + down[x] + mid[x - 1] + mid[x + 1] - 4 * mid[x];
    r.sum += l;
    r.sumSq += static_cast<std::int64_t>(l) * l;
    ++r.n;
  }
  return r;
}

#if CV_SIMD128
// The same for step 3 (the paper's S9 columns), 16 samples at a time: a row
// read as three interleaved channels puts x-1, x and x+1 of every sample in
// channels 0, 1 and 2. OpenCV's universal intrinsics: SSE2 here, NEON on a Pi.
RowSums rowStep3(const std::uint8_t* up, const std::uint8_t* mid, const std::uint8_t* down,
                 int width) {
  using namespace cv;
  RowSums r;
  const int blocks = (width - 1) / 48;
  v_int32x4 vsum = v_setzero_s32();
  v_int32x4 vsq = v_setzero_s32();
  for (int b = 0; b < blocks; ++b) {
    const int o = 48 * b;
    v_uint8x16 m0, m1, m2, u0, u1, u2, d0, d1, d2;
    v_load_deinterleave(mid + o, m0, m1, m2);
    v_load_deinterleave(up + o, u0, u1, u2);
    v_load_deinterleave(down + o, d0, d1, d2);
    v_uint16x8 m0l, m0h, m1l, m1h, m2l, m2h, u1l, u1h, d1l, d1h;
    v_expand(m0, m0l, m0h);
    v_expand(m1, m1l, m1h);
    v_expand(m2, m2l, m2h);
    v_expand(u1, u1l, u1h);
    v_expand(d1, d1l, d1h);
    const v_int16x8 ll =
        v_reinterpret_as_s16(u1l + d1l + m0l + m2l) - v_reinterpret_as_s16(v_shl<2>(m1l));
    const v_int16x8 lh =
        v_reinterpret_as_s16(u1h + d1h + m0h + m2h) - v_reinterpret_as_s16(v_shl<2>(m1h));
    const v_int16x8 one = v_setall_s16(1);
    vsum += v_dotprod(ll, one) + v_dotprod(lh, one);
    vsq += v_dotprod(ll, ll) + v_dotprod(lh, lh);
  }
  r.sum = v_reduce_sum(vsum);
  // Each lane holds at most 4 * 170 * 1020^2 < 2^31 for widths up to 8192;
  // their total may not fit in 32 bits, so add them in 64.
  int lanes[4];
  v_store(lanes, vsq);
  r.sumSq = std::int64_t{lanes[0]} + lanes[1] + lanes[2] + lanes[3];
  r.n = 16 * static_cast<std::int64_t>(blocks);
  const RowSums tail = rowScalar(up, mid, down, 1 + 48 * blocks, width, 3);
  r.sum += tail.sum;
  r.sumSq += tail.sumSq;
  r.n += tail.n;
  return r;
}
#endif

}  // namespace

LaplacianStats sampledLaplacianVariance(GrayView gray, int rowStep, int colStep) {
  LaplacianStats total;
  if (gray.width < 3 || gray.height < 3 || rowStep < 1 || colStep < 1) return total;
  double m2 = 0.0;
  for (int y = 1; y < gray.height - 1; y += rowStep) {
    const std::uint8_t* up = gray.row(y - 1);
    const std::uint8_t* mid = gray.row(y);
    const std::uint8_t* down = gray.row(y + 1);
    // Exact integer sums for one row (|L| <= 1020), then one Welford/Chan
    // update per row: the same on-line variance as a per-sample update, but the
    // inner loop has no division and vectorises.
#if CV_SIMD128
    const RowSums row = colStep == 3 && gray.width <= 8192
                            ? rowStep3(up, mid, down, gray.width)
                            : rowScalar(up, mid, down, 1, gray.width, colStep);
#else
    const RowSums row = rowScalar(up, mid, down, 1, gray.width, colStep);
#endif
    if (row.n == 0) continue;
    const auto n = row.n;
    const double rowMean = static_cast<double>(row.sum) / static_cast<double>(n);
    const double rowM2 = static_cast<double>(row.sumSq) - static_cast<double>(row.sum) * rowMean;
    const std::int64_t merged = total.count + n;
    const double delta = rowMean - total.mean;
    total.mean += delta * static_cast<double>(n) / static_cast<double>(merged);
    m2 += rowM2 + delta * delta * static_cast<double>(total.count) * static_cast<double>(n) /
                      static_cast<double>(merged);
    total.count = merged;
  }
  total.variance = total.count > 0 ? m2 / static_cast<double>(total.count) : 0.0;
  return total;
}

LaplacianStats referenceLaplacianVariance(GrayView gray) {
  LaplacianStats stats;
  if (gray.width < 3 || gray.height < 3) return stats;
  cv::Mat lap;
  cv::Laplacian(gray.mat(), lap, CV_16S, 1);  // ksize 1: the 4-neighbour kernel; |L| <= 1020
  const cv::Mat interior = lap(cv::Rect(1, 1, gray.width - 2, gray.height - 2));
  double sum = 0.0;
  for (int y = 0; y < interior.rows; ++y) {
    const auto* row = interior.ptr<std::int16_t>(y);
    for (int x = 0; x < interior.cols; ++x) sum += row[x];
  }
  stats.count = static_cast<std::int64_t>(interior.rows) * interior.cols;
  stats.mean = sum / static_cast<double>(stats.count);
  double sq = 0.0;
  for (int y = 0; y < interior.rows; ++y) {
    const auto* row = interior.ptr<std::int16_t>(y);
    for (int x = 0; x < interior.cols; ++x) {
      const double d = row[x] - stats.mean;
      sq += d * d;
    }
  }
  stats.variance = sq / static_cast<double>(stats.count);
  return stats;
}

std::string SharpnessConfig::validate() const {
  if (rowStep < 1 || rowStep > 16) return "blur row step must be 1..16";
  if (colStep < 1 || colStep > 16) return "blur column step must be 1..16";
  if (!(absoluteThreshold >= 0.0)) return "blur threshold must be >= 0";
  if (!(floor >= 0.0)) return "blur floor must be >= 0";
  if (!(ratio > 0.0 && ratio <= 2.0)) return "blur ratio must be in (0, 2]";
  if (!(quantile >= 0.0 && quantile <= 1.0)) return "blur quantile must be in [0, 1]";
  if (window < 1 || window > 10000) return "blur window must be 1..10000 frames";
  if (warmup < 0 || warmup > window) return "blur warm-up must be 0..window";
  if (analysisWidth < 0 || (analysisWidth > 0 && analysisWidth < 32))
    return "blur analysis width must be 0 (full) or >= 32";
  return {};
}

SharpnessScorer::SharpnessScorer(const SharpnessConfig& config)
    : config_(config),
      history_(static_cast<std::size_t>(std::max(1, config.window))),
      fallPerFrame_(std::pow(0.5, 2.0 / std::max(1, config.window))) {}

void SharpnessScorer::reset() {
  history_.clear();
  applied_ = 0.0;
}

double SharpnessScorer::score(GrayView gray) {
  if (config_.analysisWidth > 0 && gray.width > config_.analysisWidth) {
    const int h = std::max(3, static_cast<int>(std::lround(static_cast<double>(gray.height) *
                                                           config_.analysisWidth / gray.width)));
    gray = scaler_.scale(gray, config_.analysisWidth, h);
  }
  return sampledLaplacianVariance(gray, config_.rowStep, config_.colStep).variance;
}

double SharpnessScorer::threshold() const {
  if (config_.mode == BlurMode::Absolute) return config_.absoluteThreshold;
  if (history_.size() < static_cast<std::size_t>(std::max(1, config_.warmup))) return config_.floor;
  const double recent =
      std::max(config_.floor, config_.ratio * history_.quantile(config_.quantile));
  return std::max(recent, applied_ * fallPerFrame_);
}

bool SharpnessScorer::warmingUp() const {
  return config_.mode == BlurMode::Adaptive &&
         history_.size() < static_cast<std::size_t>(std::max(1, config_.warmup));
}

void SharpnessScorer::observe(double s) {
  // A frame under the floor can never pass: it says nothing about what sharp looks
  // like here, and a dark start-up would otherwise end the warm-up.
  if (s >= config_.floor && s > 0.0) history_.push(s);
}

SharpnessScorer::Result SharpnessScorer::evaluate(GrayView gray) {
  Result r;
  r.score = score(gray);
  r.threshold = threshold();
  // A score of 0 is a uniform frame (a lens cap, a black frame): never sharp, also
  // with a floor or an absolute threshold of 0.
  r.sharp = r.score >= r.threshold && r.score > 0.0;
  if (config_.mode == BlurMode::Adaptive && !warmingUp()) applied_ = r.threshold;
  observe(r.score);
  return r;
}

}  // namespace keyframed
