#include "core/geometric_overlap.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/polygon.h"

namespace keyframed {
namespace {
constexpr int kGridCols = 16;
constexpr int kGridRows = 9;

// Largest displacement of the image corners and centre under a step homography.
double stepMotion(const cv::Matx33d& h, cv::Size size) {
  const double w = size.width, hh = size.height;
  const cv::Point2d pts[5] = {{0, 0}, {w, 0}, {w, hh}, {0, hh}, {w / 2, hh / 2}};
  double worst = 0.0;
  for (const cv::Point2d& p : pts) {
    const cv::Vec3d v = h * cv::Vec3d(p.x, p.y, 1.0);
    if (!(v[2] > 1e-9)) return std::numeric_limits<double>::infinity();
    worst = std::max(worst, std::hypot(v[0] / v[2] - p.x, v[1] / v[2] - p.y));
  }
  return worst;
}
}  // namespace

GeometricOverlap::GeometricOverlap(const OverlapConfig& config)
    : config_(config),
      lk_(LkConfig{config.lkWindow, config.lkLevels}),
      perCell_(
          std::max(1, (config.maxTracks + kGridCols * kGridRows - 1) / (kGridCols * kGridRows))),
      cellCount_(kGridCols * kGridRows, 0),
      cellBestCount_(kGridCols * kGridRows, 0),
      cellBest_(static_cast<std::size_t>(kGridCols * kGridRows * perCell_)),
      fast_(config.fastThreshold, true) {
  const auto n = static_cast<std::size_t>(config.maxTracks);
  prevPts_.reserve(n);
  curPts_.reserve(n);
  goodPrev_.reserve(n);
  goodCur_.reserve(n);
  status_.reserve(n);
  inlierMask_.reserve(n);
  keypoints_.reserve(8192);
}

OverlapResult GeometricOverlap::observe(GrayView gray) {
  if (cv::Size(gray.width, gray.height) != size_) {
    // A new stream or a resolution change: start over.
    size_ = cv::Size(gray.width, gray.height);
    havePrev_ = false;
    haveReference_ = false;
    haveCandidate_ = false;
    prevPts_.clear();
  }
  curPyr_.build(gray, config_.lkLevels, config_.lkWindow);

  bool tracked = false;
  lastMotion_ = std::numeric_limits<double>::quiet_NaN();
  lastTracked_ = 0;
  lastInliers_ = 0;
  curPts_.clear();
  if (havePrev_ && static_cast<int>(prevPts_.size()) >= config_.minInliers) {
    lk_.track(prevPyr_, curPyr_, prevPts_, curPts_, status_);
    goodPrev_.clear();
    goodCur_.clear();
    const float w = static_cast<float>(size_.width);
    const float h = static_cast<float>(size_.height);
    for (std::size_t i = 0; i < prevPts_.size(); ++i) {
      const cv::Point2f p = curPts_[i];
      if (status_[i] && p.x >= 0 && p.y >= 0 && p.x < w && p.y < h) {
        goodPrev_.push_back(prevPts_[i]);
        goodCur_.push_back(p);
      }
    }
    lastTracked_ = static_cast<int>(goodCur_.size());
    if (lastTracked_ >= config_.minInliers) {
      const HomographyFit fit = ransac_.fit(goodPrev_, goodCur_, config_.ransacPixels, inlierMask_);
      if (fit.ok) {
        curPts_.clear();
        for (std::size_t i = 0; i < goodCur_.size(); ++i)
          if (inlierMask_[i]) curPts_.push_back(goodCur_[i]);
        lastInliers_ = static_cast<int>(curPts_.size());
        if (lastInliers_ >= config_.minInliers) {
          lastMotion_ = stepMotion(fit.h, size_);
          refToCur_ = fit.h * refToCur_;
          refToCur_ *= 1.0 / refToCur_(2, 2);
          tracked = true;
        }
      }
    }
    if (!tracked) curPts_.clear();
  }

  if (!tracked) {
    // The chain from the reference is broken: overlap is unknown from here on.
    haveReference_ = false;
    haveCandidate_ = false;
  }
  if (static_cast<int>(curPts_.size()) < config_.minTracks) replenish(gray);

  std::swap(prevPyr_, curPyr_);
  std::swap(prevPts_, curPts_);
  havePrev_ = true;

  OverlapResult r = overlapNow();
  r.features = static_cast<int>(prevPts_.size());
  r.matches = lastTracked_;
  r.inliers = lastInliers_;
  r.motionPx = lastMotion_;
  return r;
}

OverlapResult GeometricOverlap::overlapNow() const {
  OverlapResult r;
  if (!haveReference_) return r;
  cv::Matx33d curToRef = refToCur_.inv();
  const double f = visibleFraction(curToRef, size_.width, size_.height);
  if (f < 0.0) return r;  // degenerate mapping: treat as lost
  r.valid = true;
  r.overlap = std::clamp(f, 0.0, 1.0);
  return r;
}

void GeometricOverlap::replenish(GrayView gray) {
  std::fill(cellCount_.begin(), cellCount_.end(), 0);
  const double cw = static_cast<double>(size_.width) / kGridCols;
  const double ch = static_cast<double>(size_.height) / kGridRows;
  auto cellOf = [&](cv::Point2f p) {
    const int cx = std::clamp(static_cast<int>(p.x / cw), 0, kGridCols - 1);
    const int cy = std::clamp(static_cast<int>(p.y / ch), 0, kGridRows - 1);
    return cy * kGridCols + cx;
  };
  for (const cv::Point2f& p : curPts_) ++cellCount_[static_cast<std::size_t>(cellOf(p))];
  const int perCell = perCell_;
  keypoints_.clear();
  fast_.detect(gray, keypoints_);
  // The strongest few corners of each cell that needs points: one linear pass
  // over the detections, no sort.
  const auto slots = static_cast<std::size_t>(perCell);
  std::fill(cellBestCount_.begin(), cellBestCount_.end(), 0);
  const float margin = static_cast<float>(config_.lkWindow) / 2.0f;
  for (const cv::KeyPoint& k : keypoints_) {
    const cv::Point2f p = k.pt;
    if (p.x < margin || p.y < margin || p.x > static_cast<float>(size_.width) - margin ||
        p.y > static_cast<float>(size_.height) - margin)
      continue;
    const auto cell = static_cast<std::size_t>(cellOf(p));
    const int room = perCell - cellCount_[cell];
    if (room <= 0) continue;
    cv::KeyPoint* best = &cellBest_[cell * slots];
    int& n = cellBestCount_[cell];
    if (n < room) {
      best[n++] = k;
      continue;
    }
    int weakest = 0;
    for (int i = 1; i < n; ++i)
      if (best[i].response < best[weakest].response) weakest = i;
    if (k.response > best[weakest].response) best[weakest] = k;
  }
  for (std::size_t cell = 0; cell < cellBestCount_.size(); ++cell) {
    for (int i = 0; i < cellBestCount_[cell]; ++i) {
      if (static_cast<int>(curPts_.size()) >= config_.maxTracks) return;
      curPts_.push_back(cellBest_[cell * slots + static_cast<std::size_t>(i)].pt);
    }
  }
}

void GeometricOverlap::setReferenceToCurrent() {
  refToCur_ = cv::Matx33d::eye();
  haveReference_ = havePrev_;
  haveCandidate_ = false;
}

void GeometricOverlap::markCandidate() {
  if (!haveReference_) return;
  refToCandidate_ = refToCur_;
  haveCandidate_ = true;
}

OverlapResult GeometricOverlap::setReferenceToCandidate() {
  if (!haveReference_ || !haveCandidate_) return {};
  refToCur_ = refToCur_ * refToCandidate_.inv();  // candidate -> current
  refToCur_ *= 1.0 / refToCur_(2, 2);
  haveCandidate_ = false;
  OverlapResult r = overlapNow();
  r.features = static_cast<int>(prevPts_.size());
  r.matches = lastTracked_;
  r.inliers = lastInliers_;
  return r;
}

void GeometricOverlap::reset() {
  haveReference_ = false;
  haveCandidate_ = false;
}

}  // namespace keyframed
