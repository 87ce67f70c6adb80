#include "core/lens.h"

#include <cmath>
#include <limits>
#include <numbers>

namespace keyframed {
namespace {

// Largest field angle a fisheye pixel may have and still be an ideal pixel: tan()
// grows without bound towards 90 degrees, and so would the homography's leverage.
constexpr double kMaxFisheyeTheta = 80.0 * std::numbers::pi / 180.0;

// Brown-Conrady on normalised coordinates.
cv::Point2d brown(cv::Point2d p, const std::array<double, 5>& k) {
  const double r2 = p.x * p.x + p.y * p.y;
  const double radial = 1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]));
  return {p.x * radial + 2 * k[2] * p.x * p.y + k[3] * (r2 + 2 * p.x * p.x),
          p.y * radial + k[2] * (r2 + 2 * p.y * p.y) + 2 * k[3] * p.x * p.y};
}

// The normalised point n that brown() takes to d, polished by Newton's method (on a
// numeric Jacobian, each step halved until it gets closer) where the fixed point
// crept (strong distortion near its limit, `miss` under 0.05 px) or overshot further
// each step (a strong pincushion, k1 of tens): then from d itself, outside the answer,
// where the radial curve rises ever faster. Only an answer on the lens's one-to-one
// part counts: a pixel past a barrel lens's fold has none, yet Newton can land on a
// point across the centre or past the fold that the polynomial maps there too. Kept
// out of undistort() (noinline) so that its common path stays small.
[[gnu::noinline]] bool polishUndistorted(cv::Point2d d, const std::array<double, 5>& k, double fx,
                                         double fy, double miss, cv::Point2d& n) {
  const auto missPx = [&](cv::Point2d p) {
    const cv::Point2d b = brown(p, k);
    return std::hypot((b.x - d.x) * fx, (b.y - d.y) * fy);
  };
  if (!(miss < 0.05)) {
    n = d;
    miss = missPx(n);
  }
  for (int i = 0; i < 30 && miss >= 1e-7; ++i) {
    const cv::Point2d b = brown(n, k);
    const double h = 1e-7;
    const cv::Point2d bx = brown({n.x + h, n.y}, k), by = brown({n.x, n.y + h}, k);
    const double a11 = (bx.x - b.x) / h, a12 = (by.x - b.x) / h;
    const double a21 = (bx.y - b.y) / h, a22 = (by.y - b.y) / h;
    const double det = a11 * a22 - a12 * a21;
    if (!(std::fabs(det) > 1e-12)) return false;
    const double ex = b.x - d.x, ey = b.y - d.y;
    cv::Point2d step((a22 * ex - a12 * ey) / det, (a11 * ey - a21 * ex) / det);
    double after = missPx(n - step);
    for (int halve = 0; halve < 30 && !(after < miss); ++halve) {
      step *= 0.5;
      after = missPx(n - step);
    }
    if (!(after < miss)) break;  // no step gets closer: as close as it gets
    n -= step;
    miss = after;
  }
  if (!(miss < 0.05)) return false;
  if (n.x * d.x + n.y * d.y <= 0.0 && std::hypot(d.x, d.y) > 1e-9) return false;
  const double r2 = n.x * n.x + n.y * n.y;
  for (int j = 1; j <= 16; ++j) {
    const double s2 = r2 * j * j / 256.0;  // (r * j / 16)^2: the radial curve rises to n
    if (!(1 + s2 * (3 * k[0] + s2 * (5 * k[1] + s2 * 7 * k[4])) > 0.0)) return false;
  }
  return true;
}

}  // namespace

double fisheyeDistortedAngle(double theta, const std::array<double, 5>& k, double* slope) {
  const double t2 = theta * theta;
  const double poly = 1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])));
  if (slope != nullptr) {
    *slope = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])));
  }
  return theta * poly;
}

LensModel LensModel::scaledTo(int w, int h) const {
  LensModel out = *this;
  if (width <= 0 || height <= 0 || (w == width && h == height)) return out;
  const double sx = static_cast<double>(w) / width;
  const double sy = static_cast<double>(h) / height;
  out.width = w;
  out.height = h;
  out.fx = fx * sx;
  out.fy = fy * sy;
  out.cx = (cx + 0.5) * sx - 0.5;
  out.cy = (cy + 0.5) * sy - 0.5;
  return out;
}

bool LensModel::undistort(cv::Point2d pixel, cv::Point2d& ideal) const {
  if (kind == Kind::None) {
    ideal = pixel;
    return true;
  }
  const cv::Point2d d((pixel.x - cx) / fx, (pixel.y - cy) / fy);
  cv::Point2d n = d;
  if (kind == Kind::Fisheye) {
    const double thetaD = std::hypot(d.x, d.y);
    if (thetaD > 1e-12) {
      double theta = thetaD;
      double err = 1.0;
      for (int i = 0; i < 20 && std::fabs(err) > 1e-12; ++i) {
        double slope = 0;
        err = fisheyeDistortedAngle(theta, k, &slope) - thetaD;
        if (!(slope > 1e-6)) return false;  // the polynomial turns back: no inverse
        theta -= err / slope;
      }
      // Not converged (a far-off start on a strong polynomial), or out of reach.
      if (!(std::fabs(fisheyeDistortedAngle(theta, k, nullptr) - thetaD) < 1e-9)) return false;
      if (!(theta >= 0.0 && theta < kMaxFisheyeTheta)) return false;
      const double s = std::tan(theta) / thetaD;
      n = {d.x * s, d.y * s};
    }
  } else {
    // Fixed-point iteration (as cv::undistortPoints), then a check that it converged.
    for (int i = 0; i < 20; ++i) {
      const cv::Point2d b = brown(n, k);
      n = {n.x + (d.x - b.x), n.y + (d.y - b.y)};
    }
    const cv::Point2d b = brown(n, k);
    const double miss = std::hypot((b.x - d.x) * fx, (b.y - d.y) * fy);
    if (!(miss < 1e-4) && !polishUndistorted(d, k, fx, fy, miss, n)) return false;
  }
  ideal = {n.x * fx + cx, n.y * fy + cy};
  return std::isfinite(ideal.x) && std::isfinite(ideal.y);
}

cv::Point2d LensModel::distort(cv::Point2d ideal) const {
  if (kind == Kind::None) return ideal;
  const cv::Point2d n((ideal.x - cx) / fx, (ideal.y - cy) / fy);
  cv::Point2d d = n;
  if (kind == Kind::Fisheye) {
    const double r = std::hypot(n.x, n.y);
    if (r > 1e-12) {
      const double s = fisheyeDistortedAngle(std::atan(r), k, nullptr) / r;
      d = {n.x * s, n.y * s};
    }
  } else {
    d = brown(n, k);
  }
  return {d.x * fx + cx, d.y * fy + cy};
}

double LensModel::monotonicRadius() const {
  if (kind == Kind::None) return std::numeric_limits<double>::infinity();
  if (kind == Kind::Fisheye) {
    // The first angle where theta_d stops growing, at most 80 degrees.
    double limit = kMaxFisheyeTheta;
    for (double theta = 0.0; theta < kMaxFisheyeTheta; theta += 0.001) {
      double slope = 0;
      fisheyeDistortedAngle(theta, k, &slope);
      if (!(slope > 0.0)) {
        limit = theta;
        break;
      }
    }
    return std::tan(limit);
  }
  // d/dr of r (1 + k1 r^2 + k2 r^4 + k3 r^6) = 1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6.
  for (double r = 0.0; r < 10.0; r += 0.001) {
    const double r2 = r * r;
    if (!(1 + r2 * (3 * k[0] + r2 * (5 * k[1] + r2 * 7 * k[4])) > 0.0)) return r;
  }
  return 10.0;  // about 84 degrees off the axis: further than any pinhole lens sees
}

const char* LensModel::invalidReason() const {
  if (kind == Kind::None) return "";
  if (width <= 0 || height <= 0) return "lens: image size missing";
  if (!(fx > 0 && fy > 0 && std::isfinite(fx) && std::isfinite(fy))) {
    return "lens: focal lengths must be > 0";
  }
  if (!(std::isfinite(cx) && std::isfinite(cy))) return "lens: principal point must be finite";
  for (double v : k) {
    if (!std::isfinite(v)) return "lens: distortion terms must be finite";
  }
  return "";
}

}  // namespace keyframed
