#include "core/polygon.h"

#include <cmath>

namespace keyframed {

double Polygon::area() const {
  double a = 0.0;
  for (int i = 0; i < n; ++i) {
    const cv::Point2d& p = pts[static_cast<std::size_t>(i)];
    const cv::Point2d& q = pts[static_cast<std::size_t>((i + 1) % n)];
    a += p.x * q.y - q.x * p.y;
  }
  return 0.5 * a;
}

bool mapRectangle(const cv::Matx33d& h, double w, double hgt, Polygon& out) {
  const cv::Point2d corners[4] = {{0, 0}, {w, 0}, {w, hgt}, {0, hgt}};
  out.n = 4;
  for (int i = 0; i < 4; ++i) {
    const cv::Vec3d v = h * cv::Vec3d(corners[i].x, corners[i].y, 1.0);
    if (!(v[2] > 1e-9) || !std::isfinite(v[0]) || !std::isfinite(v[1])) return false;
    out.pts[static_cast<std::size_t>(i)] = {v[0] / v[2], v[1] / v[2]};
  }
  // Convex with the same winding as the source rectangle: all cross products of
  // consecutive edges positive (image coordinates, y down, clockwise on screen).
  for (int i = 0; i < 4; ++i) {
    const cv::Point2d a = out.pts[static_cast<std::size_t>(i)];
    const cv::Point2d b = out.pts[static_cast<std::size_t>((i + 1) % 4)];
    const cv::Point2d c = out.pts[static_cast<std::size_t>((i + 2) % 4)];
    const double cross = (b.x - a.x) * (c.y - b.y) - (b.y - a.y) * (c.x - b.x);
    if (!(cross > 0.0)) return false;
  }
  return true;
}

namespace {

// Clip against one half-plane a*x + b*y + c >= 0.
Polygon clipHalfPlane(const Polygon& in, double a, double b, double c) {
  Polygon out;
  for (int i = 0; i < in.n; ++i) {
    const cv::Point2d p = in.pts[static_cast<std::size_t>(i)];
    const cv::Point2d q = in.pts[static_cast<std::size_t>((i + 1) % in.n)];
    const double dp = a * p.x + b * p.y + c;
    const double dq = a * q.x + b * q.y + c;
    if (dp >= 0) out.pts[static_cast<std::size_t>(out.n++)] = p;
    if ((dp >= 0) != (dq >= 0)) {
      const double t = dp / (dp - dq);
      out.pts[static_cast<std::size_t>(out.n++)] = p + t * (q - p);
    }
    if (out.n >= static_cast<int>(out.pts.size()) - 1) break;
  }
  return out;
}

}  // namespace

Polygon clipToRectangle(const Polygon& poly, double w, double h) {
  Polygon p = clipHalfPlane(poly, 1, 0, 0);  // x >= 0
  p = clipHalfPlane(p, -1, 0, w);            // x <= w
  p = clipHalfPlane(p, 0, 1, 0);             // y >= 0
  return clipHalfPlane(p, 0, -1, h);         // y <= h
}

double visibleFraction(const cv::Matx33d& curToRef, double w, double h) {
  Polygon quad;
  if (!mapRectangle(curToRef, w, h, quad)) return -1.0;
  const Polygon clipped = clipToRectangle(quad, w, h);
  if (clipped.n < 3) return 0.0;
  return std::fabs(clipped.area()) / (w * h);
}

}  // namespace keyframed
