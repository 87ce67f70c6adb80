#include "tagging/pix4d_fisheye.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <numbers>

#include <opencv2/core.hpp>

#include "core/lens.h"

namespace keyframed {

std::optional<Pix4dFisheye> pix4dFisheye(const CameraModel& cam) {
  if (cam.lens != CameraModel::Lens::Fisheye || !cam.calibrated() || !(cam.fx > 0.0) ||
      !(cam.fy > 0.0))
    return std::nullopt;
  std::array<double, 5> k{};  // k1..k4
  std::copy_n(cam.distortion.begin(), std::min(cam.distortion.size(), std::size_t{4}), k.begin());
  const auto distortedAngle = [&](double theta) { return fisheyeDistortedAngle(theta, k); };
  // The farthest corner, as OpenCV's distorted angle (the normalised image radius).
  double reach = 0.0;
  for (const double u : {-0.5, cam.width - 0.5}) {
    for (const double v : {-0.5, cam.height - 0.5})
      reach = std::max(reach, std::hypot((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy));
  }
  // The angle that reaches it: walking out while the polynomial still rises, then
  // halving the last step. OpenCV's model ends at 90 degrees (a ray is x / z, y / z):
  // corners beyond it (an image circle inside the frame) have no ray to fit.
  constexpr double kStep = 1e-3;
  constexpr double kRightAngle = std::numbers::pi / 2;
  double lo = 0.0, drawn = 0.0;
  while (lo < kRightAngle) {
    const double next = distortedAngle(std::min(lo + kStep, kRightAngle));
    if (!(next > drawn)) return std::nullopt;  // folds back: lensWarning() says so
    if (next >= reach) break;
    lo = std::min(lo + kStep, kRightAngle);
    drawn = next;
  }
  double hi = std::min(lo + kStep, kRightAngle);
  for (int i = 0; i < 40 && lo < kRightAngle; ++i) {
    const double mid = 0.5 * (lo + hi);
    (distortedAngle(mid) < reach ? lo : hi) = mid;
  }
  const double theta = std::min(hi, kRightAngle);
  if (!(theta > 0.0)) return std::nullopt;
  // fx * theta_d(theta) ~ a1 t + a2 t^2 + a3 t^3, t = 2 theta / pi: then C = a1 and
  // p2, p3 = a2 / a1, a3 / a1.
  constexpr int kSamples = 256;
  cv::Mat a(kSamples, 3, CV_64F), b(kSamples, 1, CV_64F);
  for (int i = 0; i < kSamples; ++i) {
    const double th = theta * (i + 1) / kSamples;
    const double t = 2.0 * th / std::numbers::pi;
    a.at<double>(i, 0) = t;
    a.at<double>(i, 1) = t * t;
    a.at<double>(i, 2) = t * t * t;
    b.at<double>(i, 0) = cam.fx * distortedAngle(th);
  }
  cv::Mat x;
  if (!cv::solve(a, b, x, cv::DECOMP_QR) || !(x.at<double>(0) > 0.0)) return std::nullopt;
  const cv::Mat residual = a * x - b;
  double worst = 0.0;
  cv::minMaxLoc(cv::abs(residual), nullptr, &worst);
  Pix4dFisheye out;
  const double c = x.at<double>(0);
  out.affine = {c, 0.0, 0.0, c * cam.fy / cam.fx};
  out.polynomial = {0.0, 1.0, x.at<double>(1) / c, x.at<double>(2) / c};
  out.maxAngleDeg = theta * 180.0 / std::numbers::pi;
  out.maxErrorPx = worst * std::max(1.0, cam.fy / cam.fx);  // the y axis scales by F / C
  return out;
}

std::string pix4dFisheyeWarning(const CameraModel& cam) {
  const auto p = pix4dFisheye(cam);
  if (!p || p->maxErrorPx <= 1.0) return {};
  char buf[320];
  std::snprintf(buf, sizeof buf,
                "Pix4D's fisheye model (a cubic in the angle) follows this lens to within "
                "%.1f px only, out to %.0f degrees: Pix4D starts from that; keyframed's own "
                "XMP tags and the COLMAP/OpenDroneMap camera files carry the lens exactly",
                p->maxErrorPx, p->maxAngleDeg);
  return buf;
}

}  // namespace keyframed
