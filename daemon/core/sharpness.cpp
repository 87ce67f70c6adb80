#include "core/sharpness.h"

#include <algorithm>
#include <cmath>
#include <string>

#include <opencv2/imgproc.hpp>

namespace keyframed {

LaplacianStats sampledLaplacianVariance(GrayView gray, int rowStep, int colStep) {
  LaplacianStats total;
  if (gray.width < 3 || gray.height < 3 || rowStep < 1 || colStep < 1) return total;
  double m2 = 0.0;
  for (int y = 1; y < gray.height - 1; y += rowStep) {
    const std::uint8_t* up = gray.row(y - 1);
    const std::uint8_t* mid = gray.row(y);
    const std::uint8_t* down = gray.row(y + 1);
    // Exact integer sums for one row (|L| <= 1020, so no overflow), then one
    // Welford/Chan update per row: the same on-line variance, but the inner loop
    // has no division and vectorises.
    std::int64_t sum = 0;
    std::int64_t sumSq = 0;
    std::int64_t n = 0;
    for (int x = 1; x < gray.width - 1; x += colStep) {
      const int l = up[x] + down[x] + mid[x - 1] + mid[x + 1] - 4 * mid[x];
      sum += l;
      sumSq += static_cast<std::int64_t>(l) * l;
      ++n;
    }
    if (n == 0) continue;
    const double rowMean = static_cast<double>(sum) / static_cast<double>(n);
    const double rowM2 = static_cast<double>(sumSq) - static_cast<double>(sum) * rowMean;
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
      history_(static_cast<std::size_t>(std::max(1, config.window)), 0.0),
      scratch_(history_.size(), 0.0) {}

void SharpnessScorer::reset() {
  next_ = 0;
  filled_ = 0;
}

double SharpnessScorer::score(GrayView gray) {
  if (config_.analysisWidth > 0 && gray.width > config_.analysisWidth) {
    const int h = std::max(3, static_cast<int>(std::lround(static_cast<double>(gray.height) *
                                                           config_.analysisWidth / gray.width)));
    cv::resize(gray.mat(), resized_, cv::Size(config_.analysisWidth, h), 0, 0, cv::INTER_AREA);
    gray = GrayView::of(resized_);
  }
  return sampledLaplacianVariance(gray, config_.rowStep, config_.colStep).variance;
}

double SharpnessScorer::threshold() const {
  if (config_.mode == BlurMode::Absolute) return config_.absoluteThreshold;
  if (filled_ < static_cast<std::size_t>(std::max(1, config_.warmup))) return config_.floor;
  std::copy_n(history_.begin(), filled_, scratch_.begin());
  const auto k =
      static_cast<std::size_t>(std::lround(config_.quantile * static_cast<double>(filled_ - 1)));
  std::nth_element(scratch_.begin(), scratch_.begin() + static_cast<std::ptrdiff_t>(k),
                   scratch_.begin() + static_cast<std::ptrdiff_t>(filled_));
  return std::max(config_.floor, config_.ratio * scratch_[k]);
}

void SharpnessScorer::observe(double s) {
  history_[next_] = s;
  next_ = (next_ + 1) % history_.size();
  filled_ = std::min(filled_ + 1, history_.size());
}

SharpnessScorer::Result SharpnessScorer::evaluate(GrayView gray) {
  Result r;
  r.score = score(gray);
  r.threshold = threshold();
  r.sharp = r.score >= r.threshold;
  observe(r.score);
  return r;
}

}  // namespace keyframed
