#pragma once

#include <array>

#include <opencv2/core/matx.hpp>
#include <opencv2/core/types.hpp>

namespace keyframed {

// A small convex polygon on the stack (clipping a quad by a rectangle gives at
// most 8 vertices).
struct Polygon {
  std::array<cv::Point2d, 12> pts{};
  int n = 0;
  [[nodiscard]] double area() const;  // signed; positive when counter-clockwise in y-up terms
};

// Maps the rectangle [0,w]x[0,h] through a homography. Returns false when any
// corner lands at or behind infinity, or the image is not a convex quad with
// the rectangle's orientation (a degenerate or folded mapping).
[[nodiscard]] bool mapRectangle(const cv::Matx33d& h, double w, double hgt, Polygon& out);

// Sutherland-Hodgman clip of a convex polygon by the rectangle [0,w]x[0,h].
[[nodiscard]] Polygon clipToRectangle(const Polygon& poly, double w, double h);

// Fraction of the reference image area (w x h) that is visible in the current
// image, given the homography mapping current-image points to reference points
// (also when part of the current image lies past the reference's horizon).
// Returns a negative value for a degenerate mapping (singular, or a fold).
[[nodiscard]] double visibleFraction(const cv::Matx33d& curToRef, double w, double h);

}  // namespace keyframed
