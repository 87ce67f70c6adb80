#pragma once

#include <array>

#include <opencv2/core/types.hpp>

namespace keyframed {

// A calibrated lens as the overlap analysis needs it: where a pixel's ray would meet
// the image plane of an ideal pinhole camera with the same fx, fy, cx, cy ("ideal"
// pixels), and back. Homographies hold between ideal pixels (a plane, or a pure
// rotation), not between the pixels a wide-angle or fisheye lens draws.
struct LensModel {
  enum class Kind {
    None,     // no calibration: pixels are taken as ideal
    Pinhole,  // Brown-Conrady k1, k2, p1, p2, k3 (cv::calibrateCamera)
    Fisheye,  // OpenCV's fisheye model k1..k4 (cv::fisheye::calibrate)
  };
  Kind kind = Kind::None;
  int width = 0;  // the image size the intrinsics are for
  int height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;  // OpenCV's pixel-centre convention
  std::array<double, 5> k{};              // pinhole: k1 k2 p1 p2 k3; fisheye: k1 k2 k3 k4

  bool operator==(const LensModel&) const = default;
  [[nodiscard]] bool active() const { return kind != Kind::None; }
  // The same lens for images of w x h (same field of view).
  [[nodiscard]] LensModel scaledTo(int w, int h) const;
  // Ideal pixel of a pixel; false where the lens maps no ideal point (a fisheye ray
  // more than 80 degrees off the axis, or a pinhole's distortion folding over).
  [[nodiscard]] bool undistort(cv::Point2d pixel, cv::Point2d& ideal) const;
  // Pixel of an ideal pixel (always defined in front of the camera).
  [[nodiscard]] cv::Point2d distort(cv::Point2d ideal) const;
  // How far from the axis, in focal lengths on the ideal image plane, the lens maps
  // rays monotonically: beyond it the distortion polynomial folds back (or a fisheye
  // passes 80 degrees) and distort() is no longer the image of a ray. Radial terms.
  [[nodiscard]] double monotonicRadius() const;
  // "" or what is wrong (sizes, focal lengths, non-finite terms).
  [[nodiscard]] const char* invalidReason() const;
};

// OpenCV's fisheye polynomial: the distorted angle theta_d = theta (1 + k1 theta^2 +
// k2 theta^4 + k3 theta^6 + k4 theta^8) of a ray theta off the axis (k = k1..k4), and
// its derivative in *slope when asked.
double fisheyeDistortedAngle(double theta, const std::array<double, 5>& k, double* slope = nullptr);

}  // namespace keyframed
