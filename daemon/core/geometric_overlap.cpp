#include "core/geometric_overlap.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/polygon.h"

namespace keyframed {
namespace {
constexpr int kGridCols = 16;
constexpr int kGridRows = 9;
// The sample grid that measures overlap through a lens: one point per cell of a
// 48 x 27 grid (0.08 % of the image each).
constexpr int kSampleCols = 48;
constexpr int kSampleRows = 27;

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
  idealPrev_.reserve(n);
  idealCur_.reserve(n);
  sampleIdeal_.reserve(kSampleCols * kSampleRows);
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
    prepareLens();
  }
  curPyr_.build(gray, config_.lkLevels, config_.lkWindow);

  bool tracked = false;
  lastMotion_ = std::numeric_limits<double>::quiet_NaN();
  lastRotation_ = std::numeric_limits<double>::quiet_NaN();
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
    if (lens_.active()) {
      // Homographies hold between ideal pixels: undistort both ends, and drop the
      // pairs the lens maps no ideal point for.
      idealPrev_.clear();
      idealCur_.clear();
      std::size_t kept = 0;
      for (std::size_t i = 0; i < goodCur_.size(); ++i) {
        cv::Point2d a, b;
        if (!lens_.undistort(goodPrev_[i], a) || !lens_.undistort(goodCur_[i], b)) continue;
        goodPrev_[kept] = goodPrev_[i];
        goodCur_[kept] = goodCur_[i];
        ++kept;
        idealPrev_.emplace_back(static_cast<float>(a.x), static_cast<float>(a.y));
        idealCur_.emplace_back(static_cast<float>(b.x), static_cast<float>(b.y));
      }
      goodPrev_.resize(kept);
      goodCur_.resize(kept);
    }
    lastTracked_ = static_cast<int>(goodCur_.size());
    if (lastTracked_ >= config_.minInliers) {
      const HomographyFit fit =
          lens_.active() ? ransac_.fit(idealPrev_, idealCur_, config_.ransacPixels, inlierMask_)
                         : ransac_.fit(goodPrev_, goodCur_, config_.ransacPixels, inlierMask_);
      if (fit.ok) {
        curPts_.clear();
        for (std::size_t i = 0; i < goodCur_.size(); ++i)
          if (inlierMask_[i]) curPts_.push_back(goodCur_[i]);
        lastInliers_ = static_cast<int>(curPts_.size());
        if (lastInliers_ >= config_.minInliers) {
          lastMotion_ = stepMotion(fit.h);
          lastRotation_ = rotationAtCentre(fit.h);
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
  r.stepRotationRad = lastRotation_;
  return r;
}

double GeometricOverlap::rotationAtCentre(const cv::Matx33d& h) const {
  // The homography's Jacobian at the optical axis (the principal point, which is its
  // own ideal pixel; the image centre without a lens), and the rotation of its nearest
  // similarity.
  const cv::Point2d c = lens_.active() ? cv::Point2d(lens_.cx, lens_.cy)
                                       : cv::Point2d(0.5 * size_.width, 0.5 * size_.height);
  const double w = h(2, 0) * c.x + h(2, 1) * c.y + h(2, 2);
  if (!(std::abs(w) > 1e-12)) return std::numeric_limits<double>::quiet_NaN();
  const double u = (h(0, 0) * c.x + h(0, 1) * c.y + h(0, 2)) / w;
  const double v = (h(1, 0) * c.x + h(1, 1) * c.y + h(1, 2)) / w;
  const double j00 = (h(0, 0) - u * h(2, 0)) / w;
  const double j01 = (h(0, 1) - u * h(2, 1)) / w;
  const double j10 = (h(1, 0) - v * h(2, 0)) / w;
  const double j11 = (h(1, 1) - v * h(2, 1)) / w;
  return std::atan2(j10 - j01, j00 + j11);
}

OverlapResult GeometricOverlap::overlapNow() const {
  OverlapResult r;
  if (!haveReference_) return r;
  const double f = lens_.active() ? lensVisibleFraction(refToCur_)
                                  : visibleFraction(refToCur_.inv(), size_.width, size_.height);
  if (f < 0.0) return r;  // degenerate mapping: treat as lost
  r.valid = true;
  r.overlap = std::clamp(f, 0.0, 1.0);
  return r;
}

void GeometricOverlap::prepareLens() {
  lens_ = config_.lens.active() ? config_.lens.scaledTo(size_.width, size_.height) : LensModel{};
  sampleIdeal_.clear();
  if (!lens_.active()) return;
  const double reach = lens_.monotonicRadius();
  lensReach2_ = reach * reach;
  const double cw = static_cast<double>(size_.width) / kSampleCols;
  const double ch = static_cast<double>(size_.height) / kSampleRows;
  for (int row = 0; row < kSampleRows; ++row) {
    for (int col = 0; col < kSampleCols; ++col) {
      // Cell centres, in OpenCV's pixel-centre coordinates.
      const cv::Point2d p((col + 0.5) * cw - 0.5, (row + 0.5) * ch - 0.5);
      cv::Point2d ideal;
      if (lens_.undistort(p, ideal)) sampleIdeal_.push_back(ideal);
    }
  }
}

// The largest displacement, in image pixels, of the image's corners and centre under
// a step homography (between ideal pixels when there is a lens: each point goes
// through it and back; a point the lens maps no ideal point for is left out).
double GeometricOverlap::stepMotion(const cv::Matx33d& h) const {
  const double w = size_.width, hh = size_.height;
  const cv::Point2d pts[5] = {{0, 0}, {w, 0}, {w, hh}, {0, hh}, {w / 2, hh / 2}};
  double worst = 0.0;
  for (const cv::Point2d& p : pts) {
    cv::Point2d ideal;
    if (!lens_.undistort(p, ideal)) continue;
    const cv::Vec3d v = h * cv::Vec3d(ideal.x, ideal.y, 1.0);
    if (!(v[2] > 1e-9)) return std::numeric_limits<double>::infinity();
    const cv::Point2d q = lens_.distort({v[0] / v[2], v[1] / v[2]});
    worst = std::max(worst, std::hypot(q.x - p.x, q.y - p.y));
  }
  return worst;
}

// The share of the reference's sample points that the current image shows: each
// one's ideal pixel carried by the homography, drawn back through the lens, inside
// the image. Negative (lost) when the mapping folds the image over.
double GeometricOverlap::lensVisibleFraction(const cv::Matx33d& refToCur) const {
  if (sampleIdeal_.empty() || !(cv::determinant(refToCur) > 0.0)) return -1.0;
  const double w = size_.width, h = size_.height;
  int visible = 0;
  for (const cv::Point2d& p : sampleIdeal_) {
    const cv::Vec3d v = refToCur * cv::Vec3d(p.x, p.y, 1.0);
    if (!(v[2] > 1e-9)) continue;  // behind the camera
    const cv::Point2d ideal(v[0] / v[2], v[1] / v[2]);
    // A distortion polynomial folds back far outside the calibrated field: a point
    // that would land inside the image only that way is not seen.
    const double nx = (ideal.x - lens_.cx) / lens_.fx;
    const double ny = (ideal.y - lens_.cy) / lens_.fy;
    if (!(nx * nx + ny * ny < lensReach2_)) continue;
    const cv::Point2d q = lens_.distort(ideal);
    if (q.x >= -0.5 && q.y >= -0.5 && q.x < w - 0.5 && q.y < h - 0.5) ++visible;
  }
  return static_cast<double>(visible) / static_cast<double>(sampleIdeal_.size());
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
  // In rounds, each cell's strongest corner first: taken cell by cell, maxTracks would
  // run out part-way down the grid (200 tracks, 2 slots in each of 144 cells: the
  // bottom third of the image without any) and the homography would be fitted on the
  // top of the image alone.
  for (std::size_t cell = 0; cell < cellBestCount_.size(); ++cell) {
    cv::KeyPoint* best = &cellBest_[cell * slots];
    std::sort(best, best + cellBestCount_[cell],
              [](const cv::KeyPoint& a, const cv::KeyPoint& b) { return a.response > b.response; });
  }
  for (int round = 0; round < perCell; ++round) {
    for (std::size_t cell = 0; cell < cellBestCount_.size(); ++cell) {
      if (round >= cellBestCount_[cell]) continue;
      if (static_cast<int>(curPts_.size()) >= config_.maxTracks) return;
      curPts_.push_back(cellBest_[cell * slots + static_cast<std::size_t>(round)].pt);
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
