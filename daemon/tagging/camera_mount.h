#pragma once

#include "telemetry/pose.h"

namespace keyframed {

// How the camera sits on the vehicle, relative to the body FRD frame (x forward,
// y right, z down), as the synthetic flights define it (synth.py _mount_rotation):
//   R_body_cam = Rz(yaw) * Ry(pitch) * Rx(roll) * R0,
//   R0 = [[0,0,1],[1,0,0],[0,1,0]] maps OpenCV camera axes (x right, y down, z optical
//   axis) onto body axes. All angles 0: looking forward, image top up. pitch -90
//   (default): looking straight down, image top toward the nose.
// With gimbal set, the angles are not used: the camera sits on a gimbal whose reported
// attitude (GIMBAL_DEVICE_ATTITUDE_STATUS: gimbal FRD, x along the optical axis, image
// top up at zero roll) gives the camera's, as a body with a 0,0,0 mount would:
// cameraToNed(gimbalToNed, CameraMount{0, 0, 0}).
struct CameraMount {
  double rollDeg = 0.0;
  double pitchDeg = -90.0;
  double yawDeg = 0.0;
  bool gimbal = false;
};

// Camera (OpenCV axes) -> local NED attitude from the body FRD -> NED attitude.
[[nodiscard]] Quaternion cameraToNed(const Quaternion& bodyToNed, const CameraMount& mount);

// Pix4D's camera Yaw/Pitch/Roll (XMP Camera:Yaw/Pitch/Roll), degrees. Definition: Pix4D
// support article "Yaw, Pitch, Roll and Omega, Phi, Kappa angles" (support.pix4d.com;
// see docs/formats.md), referenced by the XMP Camera tag specification
// https://support.pix4d.com/hc/en-us/articles/360016450032. They are the angles of a virtual body
// that carries a nadir camera with the image top toward its nose, in the aeronautical Z-Y-X order
// relative to NED:
//   R_ned_cam = Rz(yaw) * Ry(pitch) * Rx(roll) * B,  B = [[0,-1,0],[1,0,0],[0,0,1]]
// (B: camera x right -> body y, image up (-y) -> body x, optical axis -> body z down).
// So yaw 0 / pitch 0 / roll 0 is nadir with the image top north, yaw 90 nadir with the
// image top east, pitch 90 looking forward (horizon). Ranges: yaw [0, 360), pitch
// [-90, 90], roll (-180, 180]. At pitch +-90 (a horizontal camera) yaw and roll are
// not separable: roll is reported as 0.
struct Pix4dAngles {
  double yawDeg = 0.0;
  double pitchDeg = 0.0;
  double rollDeg = 0.0;
};

[[nodiscard]] Pix4dAngles pix4dAngles(const Quaternion& cameraToNed);
[[nodiscard]] Quaternion fromPix4dAngles(const Pix4dAngles& angles);

}  // namespace keyframed
