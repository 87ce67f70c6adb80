#pragma once

#include <opencv2/core.hpp>

namespace keyframed::test {

// A point through a homography, done by hand: the reference the core's geometry is
// held against.
inline cv::Point2f applyHomography(const cv::Matx33d& h, cv::Point2f p) {
  const cv::Vec3d v = h * cv::Vec3d(p.x, p.y, 1.0);
  return {static_cast<float>(v[0] / v[2]), static_cast<float>(v[1] / v[2])};
}

}  // namespace keyframed::test
