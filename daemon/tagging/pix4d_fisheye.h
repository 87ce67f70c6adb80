#pragma once

#include <array>
#include <optional>
#include <string>

#include "tagging/camera_model.h"

namespace keyframed {

// A fisheye lens in Pix4D's model, as its XMP tags carry it (Camera:FisheyeAffineMatrix,
// Camera:FisheyePolynomial). For a ray at angle theta from the optical axis, in the
// direction (X, Y) across it:
//   t = 2 / pi * theta,  rho = p0 + p1 t + p2 t^2 + p3 t^3  (p0 = 0, p1 = 1),
//   pixel = [C D; E F] * rho * (X, Y) / |(X, Y)| + principal point.
// OpenCV's fisheye model (cv::fisheye: fx * theta * (1 + k1 theta^2 + ... + k4 theta^8))
// has odd powers up to theta^9, which the cubic cannot follow exactly: the cubic is
// fitted (least squares, in pixels) over the angles the image reaches (up to 90
// degrees, where OpenCV's model ends), and the fit's largest error is kept, to be said
// when it matters.
struct Pix4dFisheye {
  std::array<double, 4> affine{};      // C, D, E, F in pixels (D = E = 0: no skew)
  std::array<double, 4> polynomial{};  // p0, p1, p2, p3
  double maxAngleDeg = 0.0;            // theta at the image's farthest corner (<= 90)
  double maxErrorPx = 0.0;             // of the fit, over 0..maxAngleDeg
};

// nullopt unless cam is a calibrated fisheye whose polynomial rises to the image's
// corners (CameraModel::lensWarning says when it does not).
std::optional<Pix4dFisheye> pix4dFisheye(const CameraModel& cam);

// "" unless the fit is more than a pixel out somewhere in the image: then a one-line
// warning that Pix4D reads an approximation (keyframed's own tags are exact).
std::string pix4dFisheyeWarning(const CameraModel& cam);

}  // namespace keyframed
