#include "tagging/camera_mount.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>

namespace keyframed {
namespace {

using Mat3 = std::array<std::array<double, 3>, 3>;

constexpr double kDeg = std::numbers::pi / 180.0;

Mat3 mul(const Mat3& a, const Mat3& b) {
  Mat3 r{};
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      for (int k = 0; k < 3; ++k) r[i][j] += a[i][k] * b[k][j];
  return r;
}

Mat3 transpose(const Mat3& a) {
  Mat3 r{};
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r[i][j] = a[j][i];
  return r;
}

// Rz(yaw) * Ry(pitch) * Rx(roll), angles in degrees (aeronautical Z-Y-X).
Mat3 zyx(double yawDeg, double pitchDeg, double rollDeg) {
  const double cy = std::cos(yawDeg * kDeg), sy = std::sin(yawDeg * kDeg);
  const double cp = std::cos(pitchDeg * kDeg), sp = std::sin(pitchDeg * kDeg);
  const double cr = std::cos(rollDeg * kDeg), sr = std::sin(rollDeg * kDeg);
  return Mat3{{{cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr},
               {sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr},
               {-sp, cp * sr, cp * cr}}};
}

Mat3 toMatrix(const Quaternion& q0) {
  const double n = std::sqrt(q0.w * q0.w + q0.x * q0.x + q0.y * q0.y + q0.z * q0.z);
  const double w = q0.w / n, x = q0.x / n, y = q0.y / n, z = q0.z / n;
  return Mat3{{{1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)},
               {2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)},
               {2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)}}};
}

// Largest-pivot conversion, w >= 0.
Quaternion toQuaternion(const Mat3& m) {
  Quaternion q;
  const double tr = m[0][0] + m[1][1] + m[2][2];
  if (tr >= m[0][0] && tr >= m[1][1] && tr >= m[2][2]) {
    const double s = 2.0 * std::sqrt(std::max(tr + 1.0, 0.0));
    q = {0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s};
  } else if (m[0][0] >= m[1][1] && m[0][0] >= m[2][2]) {
    const double s = 2.0 * std::sqrt(std::max(1.0 + m[0][0] - m[1][1] - m[2][2], 0.0));
    q = {(m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s};
  } else if (m[1][1] >= m[2][2]) {
    const double s = 2.0 * std::sqrt(std::max(1.0 + m[1][1] - m[0][0] - m[2][2], 0.0));
    q = {(m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s};
  } else {
    const double s = 2.0 * std::sqrt(std::max(1.0 + m[2][2] - m[0][0] - m[1][1], 0.0));
    q = {(m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s};
  }
  if (q.w < 0.0) q = {-q.w, -q.x, -q.y, -q.z};
  return q;
}

// OpenCV camera axes -> body FRD for a forward-looking camera (synth.py _R_BODY_CAM0).
constexpr Mat3 kBodyCam0{{{0, 0, 1}, {1, 0, 0}, {0, 1, 0}}};
// OpenCV camera axes -> Pix4D's virtual body (nadir camera, image top to the nose).
constexpr Mat3 kPix4dBodyCam{{{0, -1, 0}, {1, 0, 0}, {0, 0, 1}}};

}  // namespace

Quaternion cameraToNed(const Quaternion& bodyToNed, const CameraMount& mount) {
  const Mat3 bodyCam = mul(zyx(mount.yawDeg, mount.pitchDeg, mount.rollDeg), kBodyCam0);
  return toQuaternion(mul(toMatrix(bodyToNed), bodyCam));
}

Pix4dAngles pix4dAngles(const Quaternion& cameraToNedQ) {
  const Mat3 m = mul(toMatrix(cameraToNedQ), transpose(kPix4dBodyCam));
  Pix4dAngles a;
  const double sp = std::clamp(-m[2][0], -1.0, 1.0);
  a.pitchDeg = std::asin(sp) / kDeg;
  if (std::abs(sp) < 1.0 - 1e-12) {
    a.yawDeg = std::atan2(m[1][0], m[0][0]) / kDeg;
    a.rollDeg = std::atan2(m[2][1], m[2][2]) / kDeg;
  } else {
    // Gimbal lock: only yaw -+ roll is defined; put it all in yaw.
    a.yawDeg = std::atan2(-m[0][1], m[1][1]) / kDeg;
    a.rollDeg = 0.0;
  }
  a.yawDeg = std::fmod(a.yawDeg + 360.0, 360.0);
  if (a.yawDeg >= 360.0) a.yawDeg = 0.0;  // fmod(-1e-17 + 360) rounding
  if (a.rollDeg <= -180.0) a.rollDeg += 360.0;
  return a;
}

Quaternion fromPix4dAngles(const Pix4dAngles& a) {
  return toQuaternion(mul(zyx(a.yawDeg, a.pitchDeg, a.rollDeg), kPix4dBodyCam));
}

}  // namespace keyframed
