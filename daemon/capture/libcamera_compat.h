#pragma once

// Version guards for the libcamera API. keyframed builds against Debian 12's
// libcamera 0.0.3; Raspberry Pi OS ships newer releases whose API moved:
//   0.1: Camera::generateConfiguration() takes Span<const StreamRole>
//   0.2: CameraConfiguration::orientation replaces ::transform
//   0.7: Request::metadata() is const
// Code that differs goes through the helpers below, not #ifs at call sites.

#include <memory>
#include <vector>

#include <libcamera/camera.h>
#include <libcamera/request.h>
#include <libcamera/stream.h>
#include <libcamera/version.h>

#define KEYFRAMED_LIBCAMERA_VERSION(major, minor, patch) ((major)*1000000 + (minor)*1000 + (patch))
#define KEYFRAMED_LIBCAMERA_CURRENT                                             \
  KEYFRAMED_LIBCAMERA_VERSION(LIBCAMERA_VERSION_MAJOR, LIBCAMERA_VERSION_MINOR, \
                              LIBCAMERA_VERSION_PATCH)
#define KEYFRAMED_LIBCAMERA_AT_LEAST(major, minor) \
  (KEYFRAMED_LIBCAMERA_CURRENT >= KEYFRAMED_LIBCAMERA_VERSION(major, minor, 0))

#if KEYFRAMED_LIBCAMERA_AT_LEAST(0, 2)
#include <libcamera/orientation.h>
#endif

namespace keyframed::libcamera_compat {

inline constexpr int kVersion = KEYFRAMED_LIBCAMERA_CURRENT;
inline constexpr bool kStreamRoleSpan = KEYFRAMED_LIBCAMERA_AT_LEAST(0, 1);
inline constexpr bool kOrientation = KEYFRAMED_LIBCAMERA_AT_LEAST(0, 2);
inline constexpr bool kConstMetadata = KEYFRAMED_LIBCAMERA_AT_LEAST(0, 7);

// One role, as every release accepts it (a vector before 0.1, a span after).
inline std::unique_ptr<libcamera::CameraConfiguration> generateConfiguration(
    libcamera::Camera& camera, libcamera::StreamRole role) {
  const std::vector<libcamera::StreamRole> roles{role};
#if KEYFRAMED_LIBCAMERA_AT_LEAST(0, 1)
  return camera.generateConfiguration(libcamera::Span<const libcamera::StreamRole>(roles));
#else
  return camera.generateConfiguration(roles);
#endif
}

// Frames as the sensor is mounted: no flip, no rotation (the camera mount in
// tagging/ describes how the camera sits on the aircraft).
inline void setUprightOrientation(libcamera::CameraConfiguration& config) {
#if KEYFRAMED_LIBCAMERA_AT_LEAST(0, 2)
  config.orientation = libcamera::Orientation::Rotate0;
#else
  config.transform = libcamera::Transform::Identity;
#endif
}

// Request metadata, read-only in every release (the accessor is const from 0.7
// on, non-const before: hence the non-const Request here).
inline const libcamera::ControlList& metadata(libcamera::Request& request) {
  return request.metadata();
}

}  // namespace keyframed::libcamera_compat
