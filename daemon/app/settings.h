#pragma once

#include <cstdint>
#include <string>
#include <string_view>

#include "core/overlap.h"
#include "core/selector.h"
#include "core/sharpness.h"

// The vocabulary shared by the `select` command line and the daemon's TOML
// configuration: value ranges and names. Both front ends check against these, so
// a setting accepted in one place is accepted in the other.
namespace keyframed {

template <typename T>
struct SettingRange {
  T lo;
  T hi;
  [[nodiscard]] constexpr bool contains(T v) const { return v >= lo && v <= hi; }
};

// The whole of `text` as a finite number (strtod); false otherwise.
bool parseDouble(const std::string& text, double& out);

// "must be between LO and HI (got V)"
std::string rangeError(SettingRange<double> range, double value);
std::string rangeError(SettingRange<std::int64_t> range, std::int64_t value);

namespace limits {
// Selection.
inline constexpr SettingRange<double> kOverlapTarget{0.01, 0.99};
inline constexpr SettingRange<double> kOverlapBand{0.01, 0.99};
inline constexpr SettingRange<double> kMinOverlap{0.01, 0.99};
inline constexpr SettingRange<double> kMotionRatio{0.0, 100.0};
inline constexpr SettingRange<double> kMotionMinFraction{0.001, 0.99};
inline constexpr SettingRange<std::int64_t> kMotionWindow{5, 10000};
inline constexpr SettingRange<std::int64_t> kCaptureWaitMs{0, 60000};
inline constexpr SettingRange<std::int64_t> kAnalysisWidth{0, 16384};
inline constexpr SettingRange<std::int64_t> kOrbFeatures{50, 50000};
inline constexpr SettingRange<double> kPaperThreshold{1.0, 256.0};
inline constexpr SettingRange<std::int64_t> kPaperMinMatches{4, 50000};
inline constexpr SettingRange<std::int64_t> kMaxTracks{20, 5000};
inline constexpr SettingRange<std::int64_t> kMinTracks{8, 5000};
inline constexpr SettingRange<std::int64_t> kMinInliers{4, 5000};
inline constexpr SettingRange<double> kRansacPixels{0.1, 49.0};
inline constexpr SettingRange<std::int64_t> kFastThreshold{1, 200};
inline constexpr SettingRange<std::int64_t> kLkWindow{5, 61};
inline constexpr SettingRange<std::int64_t> kLkLevels{0, 6};
// Blur.
inline constexpr SettingRange<double> kBlurThreshold{0.0, 1e9};
inline constexpr SettingRange<double> kBlurFloor{0.0, 1e9};
inline constexpr SettingRange<double> kBlurRatio{0.01, 2.0};
inline constexpr SettingRange<double> kBlurQuantile{0.0, 1.0};
inline constexpr SettingRange<std::int64_t> kBlurWindow{1, 10000};
inline constexpr SettingRange<std::int64_t> kBlurWarmup{0, 10000};
inline constexpr SettingRange<std::int64_t> kBlurStep{1, 16};
inline constexpr SettingRange<std::int64_t> kBlurWidth{0, 16384};
// Telemetry and tags.
inline constexpr SettingRange<std::int64_t> kMavlinkId{1, 255};
// Our system id: 0 takes the autopilot's.
inline constexpr SettingRange<std::int64_t> kOwnSystemId{0, 255};
inline constexpr SettingRange<std::int64_t> kTelemetryWaitMs{0, 60000};
inline constexpr SettingRange<std::int64_t> kTelemetryStartWaitMs{0, 600000};
inline constexpr SettingRange<double> kMountAngleDeg{-360.0, 360.0};
// camera.time_offset_ms / --time-offset: camera latency, either way, up to 2 s.
inline constexpr SettingRange<double> kTimeOffsetMs{-2000.0, 2000.0};
inline constexpr SettingRange<std::int64_t> kJpegQuality{1, 100};
}  // namespace limits

// Defaults that depend on another setting give way when only that one is set: a
// max_tracks under the default min_tracks lowers min_tracks to 2/5 of it (at least
// 8), a blur_window under the default warm-up shortens the warm-up to the window.
// A value the user set explicitly is never changed (validation reports conflicts).
void relaxDependentDefaults(SelectorConfig& config, bool minTracksSet, bool warmupSet);

// Names used on the command line and in the config file.
// (The overlap mode's name is core's toString(OverlapMode).)
bool parseOverlapMode(std::string_view text, OverlapMode& mode);
const char* blurModeName(BlurMode mode);  // "adaptive" | "absolute"
bool parseBlurMode(std::string_view text, BlurMode& mode);

// "SYS[:COMP]" with ids 1..255 (COMP 0 when absent). Empty on success, else why not.
std::string parseAutopilot(std::string_view text, int& system, int& component);

// Parses an ISO 8601 UTC time (2026-06-01T10:00:00Z, fractions allowed) or a number
// of unix seconds into unix nanoseconds.
bool parseUtcTime(const std::string& text, std::int64_t& unixNs);

// "" when frames of w x h can be analysed at `analysisWidth` (0: full width), else
// why not: the smallest analysis image is 32 pixels each way (ORB's pyramid and the
// corner tracker need room; a 4000x8 strip scaled to 640 wide is one row).
std::string tooSmallToAnalyse(int w, int h, int analysisWidth);
// ... and too large: at most 16384 pixels a side (as camera.width/height) and 64
// megapixels (8K UHD is 33): a frame is held three times over in BGR.
std::string tooLargeToAnalyse(int w, int h);

// "" when `name` may be a vehicle's name (keyframed/<name>/... keys, a ground
// station's folder): letters, digits, '-', '_' and '.', 1 to 64 of them.
std::string vehicleNameError(const std::string& name);

}  // namespace keyframed
