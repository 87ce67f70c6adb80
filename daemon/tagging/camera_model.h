#pragma once

#include <cmath>
#include <string>
#include <string_view>
#include <vector>

#include "core/lens.h"

namespace keyframed {

// What is known about the camera: identity, pinhole intrinsics in pixels (OpenCV
// convention: the centre of pixel (0,0) is at (0,0)), distortion and physical size.
// Unknown numbers are NaN; nothing is guessed.
struct CameraModel {
  // The lens's projection: a pinhole with Brown-Conrady distortion (cv::calibrateCamera)
  // or OpenCV's fisheye model (cv::fisheye::calibrate: equidistant projection with the
  // Kannala-Brandt polynomial theta * (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 +
  // k4 theta^8)). The same fx, fy, cx, cy in both.
  enum class Lens { Pinhole, Fisheye };

  // EXIF Make and Model: "" when the calibration does not name the camera (then
  // neither is tagged: nothing is made up).
  std::string make;
  std::string model;
  int width = 0;  // pixels the intrinsics refer to
  int height = 0;
  double fx = NAN;
  double fy = NAN;
  double cx = NAN;
  double cy = NAN;
  Lens lens = Lens::Pinhole;
  // OpenCV order: pinhole k1, k2, p1, p2[, k3]; fisheye k1, k2, k3, k4.
  std::vector<double> distortion;
  double sensorWidthMm = NAN;
  double sensorHeightMm = NAN;
  double focalLengthMm = NAN;

  // True when the pinhole intrinsics (fx, fy, cx, cy) and the image size are known.
  [[nodiscard]] bool calibrated() const;
  // 35 mm equivalent focal length, NaN when unknown. Convention: the image's longer
  // side is matched to the 36 mm side of a 36x24 mm frame (fx * 36 / max(w, h), or
  // focalLengthMm * 36 / sensor long side). This is how OpenSfM/ODM read EXIF
  // FocalLengthIn35mmFilm back into a focal length (focal / 36 * max(w, h)), so a
  // reconstruction starts from the right field of view; the diagonal ("crop factor")
  // convention would differ by a few percent on 4:3 sensors.
  [[nodiscard]] double focalLength35mm() const;
  // The same camera at another resolution (same field of view): intrinsics scale per
  // axis; the OpenCV pixel-centre convention is kept ((c + 0.5) * s - 0.5).
  [[nodiscard]] CameraModel scaledTo(int w, int h) const;
  // "" when frames of w x h are this calibration scaled (same aspect ratio within
  // 0.5 %, or no calibrated size), else a one-line warning: another aspect ratio is
  // a crop of the sensor (a 16:9 mode of a 4:3 sensor), which scaling gets wrong.
  [[nodiscard]] std::string aspectMismatch(int w, int h) const;
  // The camera's identity and its lens's focal length in mm, nothing measured in
  // pixels or on the sensor: what is still true of a calibration made in another
  // sensor mode (aspectMismatch), so that no wrong intrinsics are tagged.
  [[nodiscard]] CameraModel withoutIntrinsics() const;
  // "" unless the calibration is in pixels only (no sensor size, no focal length in
  // mm): then the tags cannot carry the principal point and the focal length in mm.
  [[nodiscard]] std::string physicalSizeWarning() const;
  // "" unless the distortion folds back (or a fisheye passes 80 degrees) before the
  // image's corners: the image beyond cannot be undistorted, and the overlap analysis
  // loses it (a k3 fitted without points near the edge does this).
  [[nodiscard]] std::string lensWarning() const;
  // The lens as the overlap analysis takes it: none unless calibrated with a fisheye
  // or a non-zero distortion (a distortion-free pinhole changes no homography).
  [[nodiscard]] LensModel lensModel() const;
};

// An EXIF ASCII value set by the user (Make, Model): at most 63 printable ASCII
// characters. Empty on success, else why not (without the value).
std::string exifTextError(std::string_view text);

// Reads a camera model from:
//  - OpenCV FileStorage YAML/XML as OpenCV's calibration sample writes it
//    (camera_matrix, distortion_coefficients, image_width, image_height, fisheye_model
//    (1: cv::fisheye); optional sensor_width_mm, sensor_height_mm, focal_length_mm,
//    make, model);
//  - TOML (*.toml): a [camera] table with make, model, lens ("pinhole" or "fisheye"),
//    width, height, fx, fy, cx, cy, distortion, sensor_width_mm, sensor_height_mm,
//    focal_length_mm (unknown keys are errors);
//  - JSON intrinsics.json from keyframed.synth (width, height, fx, fy, cx, cy,
//    distortion, model ("pinhole" or "fisheye"), sensor_width_mm, sensor_height_mm,
//    focal_length_mm).
// Derives focalLengthMm = fx * sensorWidthMm / width when it is not given.
// Returns false with a one-line error; never throws.
[[nodiscard]] bool loadCameraModel(const std::string& path, CameraModel& out, std::string& error);

// The checks every calibration file passes (sizes, focal lengths, the lens's number of
// distortion terms, finite numbers), and the values derived from it, for a camera
// model from elsewhere (a flight record); errors start with `origin`.
[[nodiscard]] bool checkCameraModel(const std::string& origin, CameraModel& m, std::string& error);

// A settings file's text (a configuration or a calibration), read whole: "" when
// it is fine, else why not (unreadable, over 1 MiB, nested over 64 deep: its parser
// would recurse past the stack; core/nesting.h).
[[nodiscard]] std::string readSmallText(const std::string& path, std::string& text);

}  // namespace keyframed
