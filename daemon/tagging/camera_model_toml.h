#pragma once

#include <string>
#include <string_view>

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

// The keys of such a table for `m` (what is known of it), one `key = value` per line,
// that cameraFromTomlTable reads back as the same model: make, model, lens, width and
// height when known, the finite numbers, the distortion when there is one.
std::string cameraTomlKeys(const CameraModel& m);

// A [camera] table's text (cameraTomlKeys under "[camera]"), as a flight record keeps
// it, read back; errors start with `origin`.
[[nodiscard]] bool cameraFromTomlText(const std::string& text, const std::string& origin,
                                      CameraModel& out, std::string& error);

// A TOML basic string of `s` (quoted, escaped).
std::string tomlString(std::string_view s);
// The shortest text that reads back as the same double, always a TOML float.
std::string tomlReal(double v);

}  // namespace keyframed
