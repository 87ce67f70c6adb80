#include "core/polygon.h"

#include <algorithm>
#include <cmath>

#include <opencv2/core.hpp>

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
  if (mapRectangle(curToRef, w, h, quad)) {
    const Polygon clipped = clipToRectangle(quad, w, h);
    if (clipped.n < 3) return 0.0;
    return std::fabs(clipped.area()) / (w * h);
  }
  // A corner of the current image maps to or past the reference's horizon (a camera
  // tilted up from a nadir keyframe): the part of the reference in front of the
  // current camera, mapped into the current image and clipped to it, then back.
  const cv::Matx33d refToCur = curToRef.inv();
  const cv::Matx33d& m = refToCur;
  const double det = m(0, 0) * (m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1)) -
                     m(0, 1) * (m(1, 0) * m(2, 2) - m(1, 2) * m(2, 0)) +
                     m(0, 2) * (m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0));
  if (!std::isfinite(det) || !(det > 0.0)) return -1.0;  // singular, or a fold
  Polygon ref;
  ref.n = 4;
  ref.pts[0] = {0, 0};
  ref.pts[1] = {w, 0};
  ref.pts[2] = {w, h};
  ref.pts[3] = {0, h};
  const double a = refToCur(2, 0), b = refToCur(2, 1), c = refToCur(2, 2);
  const double margin = 1e-9 * (std::fabs(a) * w + std::fabs(b) * h + std::fabs(c));
  ref = clipHalfPlane(ref, a, b, c - margin);  // w > 0: in front
  if (ref.n < 3) return 0.0;
  Polygon cur;
  for (int i = 0; i < ref.n; ++i) {
    const cv::Point2d p = ref.pts[static_cast<std::size_t>(i)];
    const cv::Vec3d v = refToCur * cv::Vec3d(p.x, p.y, 1.0);
    if (!(v[2] > 0.0)) return -1.0;
    cur.pts[static_cast<std::size_t>(cur.n++)] = {v[0] / v[2], v[1] / v[2]};
  }
  cur = clipToRectangle(cur, w, h);
  if (cur.n < 3) return 0.0;
  Polygon back;
  for (int i = 0; i < cur.n; ++i) {
    const cv::Point2d p = cur.pts[static_cast<std::size_t>(i)];
    const cv::Vec3d v = curToRef * cv::Vec3d(p.x, p.y, 1.0);
    if (!(std::fabs(v[2]) > 0.0)) return -1.0;
    back.pts[static_cast<std::size_t>(back.n++)] = {v[0] / v[2], v[1] / v[2]};
  }
  return std::min(1.0, std::fabs(back.area()) / (w * h));
}

}  // namespace keyframed
