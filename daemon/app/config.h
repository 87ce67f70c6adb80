#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "app/log.h"
#include "core/selector.h"
#include "tagging/camera_model.h"
#include "telemetry/telemetry_service.h"

// The daemon's configuration (`keyframed run`, `keyframed check-config`). Every
// field names its TOML key; config/keyframed.toml lists them all with their
// defaults and docs/configuration.md explains them. Layers, later wins:
//   built-in defaults < DIR/keyframed.toml < DIR/conf.d/*.toml (by name) < --set
// with DIR = --config-dir, else $KEYFRAMED_CONFIG_DIR, else /etc/keyframed.
namespace keyframed {

namespace config_detail {
inline TelemetryServiceConfig defaultLink() {
  TelemetryServiceConfig link;
  link.url = "udpin:0.0.0.0:14550";  // mavlink-router's usual endpoint for a companion
  return link;
}
}  // namespace config_detail

// Section types are nested: names such as TelemetryConfig exist elsewhere in the
// namespace, and two different definitions of one name would break the ODR.
struct DaemonConfig {
  enum class Source { V4l2, Libcamera, File };

  struct Camera {
    Source source = Source::V4l2;      // camera.source
    std::string device;                // camera.device ("": the first camera)
    std::string path;                  // camera.path (source "file": the video)
    int width = 1920;                  // camera.width
    int height = 1080;                 // camera.height
    double fps = 30.0;                 // camera.fps
    std::string pixelFormat = "auto";  // camera.pixel_format (FourCC or "auto")
    bool realtime = true;              // camera.realtime (file: pace at the video's rate)
    std::string startTime;             // camera.start_time (file: UTC of frame 0)
    int queueMs = 300;                 // camera.queue_ms (frames waiting for analysis)
    double timeOffsetMs = 0.0;         // camera.time_offset_ms (frame time -> exposure time)
  };

  struct Telemetry {
    // telemetry.url, mavlink_sysid, component_id, timesync, camera_component, mavlink1,
    // autopilot, stale_ms, attitude_gap_ms, position_gap_ms, history_s, min_fix_type,
    // clock_window_s, timesync_timeout_s: handed to TelemetryService as they are.
    TelemetryServiceConfig link = config_detail::defaultLink();
    int waitMs = 1000;        // telemetry.wait_ms
    int startWaitMs = 10000;  // telemetry.start_wait_ms
  };

  struct Tagging {
    std::string calibration;  // tagging.calibration ("": no intrinsics)
    // [tagging.camera]: the intrinsics inline, as a calibration file's [camera] table
    // (one or the other, not both).
    std::optional<CameraModel> camera;
    std::string make;             // tagging.make (EXIF Make; "": the calibration's)
    std::string model;            // tagging.model (EXIF Model; "": the calibration's)
    bool systemClockUtc = false;  // tagging.system_clock_utc
    double mountRollDeg = 0.0;    // tagging.mount_roll
    double mountPitchDeg = -90;   // tagging.mount_pitch (-90: nadir)
    double mountYawDeg = 0.0;     // tagging.mount_yaw
    bool mountGimbal = false;     // tagging.mount = "gimbal" (else "fixed")
    int jpegQuality = 92;         // tagging.jpeg_quality
  };

  struct Output {
    std::string stateDir = "/var/lib/keyframed";  // output.state_dir
    bool mcap = true;                             // output.mcap
    std::int64_t mcapRotateMb = 1024;             // output.mcap_rotate_mb (0: never)
    std::int64_t mcapRotateS = 1800;              // output.mcap_rotate_s (0: never)
    bool mcapFsync = true;                        // output.mcap_fsync (timed flush + fsync)
    std::string mcapCompression = "auto";         // output.mcap_compression
    std::int64_t previewWidth = 640;              // output.preview_width (0: no preview)
    std::string previewFormat = "jpeg";           // output.preview_format: jpeg | h264
  };

  struct Zenoh {
    bool enabled = true;          // zenoh.enabled
    std::string config;           // zenoh.config (JSON5 file; "": peer mode, Zenoh's defaults)
    std::string vehicle;          // zenoh.vehicle (keyframed/<vehicle>/...; "": host name)
    std::int64_t openRetryS = 5;  // zenoh.open_retry_s (0: exit when no session opens)
  };

  Camera camera;
  SelectorConfig selection;  // [selection]: the same settings as `keyframed select`
  Telemetry telemetry;
  Tagging tagging;
  Output output;
  Zenoh zenoh;
  LogConfig log;
};

const char* toString(DaemonConfig::Source source);  // "v4l2" | "libcamera" | "file"

// Where the layers come from.
struct ConfigSources {
  std::string configDir;               // "": defaultConfigDir()
  std::vector<std::string> files;      // when set: these files instead of the directory
  std::vector<std::string> overrides;  // "section.key=value" (--set), applied last
};

struct ConfigLoadResult {
  DaemonConfig config;
  std::vector<std::string> layers;  // what was read, in order ("--set ..." included)
  // One line each: "FILE:LINE: section.key: what is wrong".
  std::vector<std::string> errors;
  [[nodiscard]] bool ok() const { return errors.empty(); }
};

// $KEYFRAMED_CONFIG_DIR, else the built-in directory (/etc/keyframed).
std::string defaultConfigDir();

// Loads and validates every layer; all problems are reported, not just the first.
ConfigLoadResult loadConfig(const ConfigSources& sources);
// The built-in defaults with "section.key=value" overrides applied, no files read
// (`keyframed select --set telemetry.KEY=VALUE`).
ConfigLoadResult loadOverrides(const std::vector<std::string>& overrides);

// Takes --config-dir DIR and --set KEY=VALUE (also --opt=value forms) out of args,
// leaving the rest. Empty, or a one-line error.
std::string takeConfigArgs(std::vector<std::string>& args, ConfigSources& sources);

// The configuration as TOML, every key, in the documented order. Loading it back
// gives the same configuration.
std::string toToml(const DaemonConfig& config);

// The [selection] settings as `selection.KEY=VALUE` lines (TOML values), what a
// flight record keeps so that a replay selects as the flight did; and back, through
// the same validation as --set (errors name the key).
std::string selectionOverrides(const SelectorConfig& selection);
ConfigLoadResult loadSelectionOverrides(const std::string& lines);
// The same for what shapes a keyframe's tags: tagging.make, model, mount, mount_roll,
// mount_pitch, mount_yaw and camera.time_offset_ms (any other line is an error).
std::string taggingOverrides(const DaemonConfig::Tagging& tagging, double timeOffsetMs);
ConfigLoadResult loadTaggingOverrides(const std::string& lines);

// What a video file is delivered as for camera.pixel_format (any case): "auto" BGR24,
// as decoded; YUV420 (YU12, I420) or NV12, converted as a camera would deliver them.
// nullopt for the formats only a camera has.
std::optional<PixelFormat> filePixelFormat(const std::string& name);

// Every key as "section.key", in order, and the sections.
std::vector<std::string> configKeys();
std::vector<std::string> configSections();

// `keyframed check-config [FILE...] [--config-dir DIR] [--set KEY=VALUE]...`
int checkConfigMain(const std::vector<std::string>& args);

}  // namespace keyframed
