#pragma once

#include <string>

#include <toml++/toml.h>

#include "tagging/camera_model.h"

namespace keyframed {

// A camera model from a TOML table with the keys of a TOML calibration file's
// [camera] table (camera_model.h), wherever that table sits: a calibration file's
// [camera], or keyframed.toml's [tagging.camera]. Errors name path, the line and
// prefix.key ("tagging.camera.fx"); unknown keys are errors. Derives what
// loadCameraModel derives.
[[nodiscard]] bool cameraFromTomlTable(const toml::table& table, const std::string& path,
                                       const std::string& prefix, CameraModel& out,
                                       std::string& error);

}  // namespace keyframed
