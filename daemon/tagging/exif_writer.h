#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "tagging/camera_model.h"
#include "telemetry/pose.h"

namespace keyframed {

// What is known about one keyframe. Absent parts produce no tags: nothing is guessed.
struct TagSet {
  const CameraModel* camera = nullptr;    // borrowed; nullptr = nothing known
  std::optional<Quaternion> cameraToNed;  // camera (OpenCV axes) -> local NED
  std::optional<GeoPosition> position;    // WGS84, altitude AMSL
  GpsQuality gps;
  std::optional<std::int64_t> utcUs;  // capture time, unix microseconds (UTC)
  std::string software = "keyframed";
  std::int64_t frameIndex = -1;  // not written yet (no standard tag fits)
};

// Writes EXIF (IFD0, Exif, GPS) and XMP (Pix4D Camera namespace) tags into the JPEG in
// memory, replacing it. The tag list and their units are in docs/formats.md.
// Thread-safe. Returns false with a one-line error (e.g. not a JPEG); `jpeg` is then
// left unchanged.
[[nodiscard]] bool writeTags(std::vector<std::uint8_t>& jpeg, const TagSet& tags,
                             std::string& error);

}  // namespace keyframed
