#include "app/config.h"

#include <algorithm>
#include <array>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <functional>
#include <map>
#include <span>
#include <sstream>
#include <system_error>

#include <toml++/toml.h>

#include "app/settings.h"
#include "app/text_io.h"
#include "output/flight_outputs.h"
#include "output/h264.h"
#include "tagging/camera_model.h"
#include "tagging/camera_model_toml.h"
#include "telemetry/link.h"

#ifndef KEYFRAMED_DEFAULT_CONFIG_DIR
#define KEYFRAMED_DEFAULT_CONFIG_DIR "/etc/keyframed"
#endif

namespace keyframed {

const char* toString(DaemonConfig::Source source) {
  switch (source) {
    case DaemonConfig::Source::V4l2: return "v4l2";
    case DaemonConfig::Source::Libcamera: return "libcamera";
    case DaemonConfig::Source::File: return "file";
  }
  return "v4l2";
}

namespace {

// SECTION.KEY=VALUE in form: an '=', and a '.' after a section name before it.
bool isSetAssignment(std::string_view a) {
  const auto eq = a.find('=');
  const auto dot = a.find('.');
  return eq != std::string_view::npos && dot != std::string_view::npos && dot != 0 && dot < eq;
}

namespace fs = std::filesystem;

constexpr std::int64_t kNsPerMs = 1'000'000;
constexpr std::int64_t kNsPerS = 1'000'000'000;

// ---------------------------------------------------------------- value text

const char* typeName(const toml::node& n) {
  switch (n.type()) {
    case toml::node_type::string: return "a string";
    case toml::node_type::integer: return "an integer";
    case toml::node_type::floating_point: return "a float";
    case toml::node_type::boolean: return "a boolean";
    case toml::node_type::date:
    case toml::node_type::time:
    case toml::node_type::date_time: return "a date/time";
    case toml::node_type::array: return "an array";
    case toml::node_type::table: return "a table";
    case toml::node_type::none: break;
  }
  return "nothing";
}

std::string typeError(const char* expected, const toml::node& n) {
  return std::string("expected ") + expected + ", got " + typeName(n);
}

// ---------------------------------------------------------------- the schema

enum class Kind { Integer, Real, Boolean, String };

// One configuration key: how to read it from TOML into DaemonConfig (empty: ok,
// else what is wrong) and how to write its current value back as TOML.
struct Field {
  std::string_view section;
  std::string_view key;
  Kind kind;
  std::function<std::string(const toml::node&, DaemonConfig&)> read;
  std::function<std::string(const DaemonConfig&)> write;

  [[nodiscard]] std::string name() const { return std::string(section) + "." + std::string(key); }
};

using Check = std::function<std::string(const std::string&)>;

// `get` is a generic lambda giving a reference to the member, const or not.
// A setting where 0 switches something off (or means "full"), and any other value must
// be at least `min`: "must be 0 (what) or >= min (got v)"; empty when `v` is fine.
struct ZeroOr {
  double min = 0.0;
  const char* what = "";

  [[nodiscard]] std::string check(double v) const {
    if (min <= 0.0 || v == 0.0 || v >= min) return {};
    const auto number = [](double x) {
      return x == std::trunc(x) && std::fabs(x) < 1e15
                 ? std::to_string(static_cast<std::int64_t>(x))
                 : tomlReal(x);
    };
    return "must be 0 (" + std::string(what) + ") or >= " + number(min) + " (got " + number(v) +
           ")";
  }
};

template <typename Get>
Field integer(std::string_view section, std::string_view key, Get get,
              SettingRange<std::int64_t> range, ZeroOr zeroOr = {}) {
  return {section, key, Kind::Integer,
          [get, range, zeroOr](const toml::node& n, DaemonConfig& c) -> std::string {
            const auto* v = n.as_integer();
            if (v == nullptr) return typeError("an integer", n);
            if (!range.contains(v->get())) return rangeError(range, v->get());
            if (std::string e = zeroOr.check(static_cast<double>(v->get())); !e.empty()) return e;
            auto& dst = get(c);
            dst = static_cast<std::remove_reference_t<decltype(dst)>>(v->get());
            return {};
          },
          [get](const DaemonConfig& c) { return std::to_string(get(c)); }};
}

// An integer key in `unit` (ms, s) over a member in nanoseconds.
template <typename Get>
Field duration(std::string_view section, std::string_view key, Get get,
               SettingRange<std::int64_t> range, std::int64_t nsPerUnit) {
  return {section, key, Kind::Integer,
          [get, range, nsPerUnit](const toml::node& n, DaemonConfig& c) -> std::string {
            const auto* v = n.as_integer();
            if (v == nullptr) return typeError("an integer", n);
            if (!range.contains(v->get())) return rangeError(range, v->get());
            get(c) = v->get() * nsPerUnit;
            return {};
          },
          [get, nsPerUnit](const DaemonConfig& c) { return std::to_string(get(c) / nsPerUnit); }};
}

template <typename Get>
Field real(std::string_view section, std::string_view key, Get get, SettingRange<double> range,
           ZeroOr zeroOr = {}) {
  return {section, key, Kind::Real,
          [get, range, zeroOr](const toml::node& n, DaemonConfig& c) -> std::string {
            double d = 0;
            if (const auto* f = n.as_floating_point())
              d = f->get();
            else if (const auto* i = n.as_integer())
              d = static_cast<double>(i->get());
            else
              return typeError("a number", n);
            if (!range.contains(d)) return rangeError(range, d);
            if (std::string e = zeroOr.check(d); !e.empty()) return e;
            get(c) = d;
            return {};
          },
          [get](const DaemonConfig& c) { return tomlReal(get(c)); }};
}

template <typename Get>
Field boolean(std::string_view section, std::string_view key, Get get) {
  return {section, key, Kind::Boolean,
          [get](const toml::node& n, DaemonConfig& c) -> std::string {
            const auto* v = n.as_boolean();
            if (v == nullptr) return typeError("true or false", n);
            get(c) = v->get();
            return {};
          },
          [get](const DaemonConfig& c) { return std::string(get(c) ? "true" : "false"); }};
}

template <typename Get>
Field text(std::string_view section, std::string_view key, Get get, Check check = {}) {
  return {section, key, Kind::String,
          [get, check](const toml::node& n, DaemonConfig& c) -> std::string {
            const auto* v = n.as_string();
            if (v == nullptr) return typeError("a string", n);
            // TOML strings may hold "\u0000" and other control characters: a path (or
            // a name) the C library would cut at the NUL, or a log line broken in two.
            // First: a check's message may quote the value.
            for (const char ch : v->get()) {
              if (static_cast<unsigned char>(ch) < 0x20 || ch == 0x7f)
                return "must not contain control characters (a NUL, a newline, a tab, ...)";
            }
            if (check) {
              if (std::string e = check(v->get()); !e.empty()) return e;
            }
            get(c) = v->get();
            return {};
          },
          [get](const DaemonConfig& c) { return tomlString(get(c)); }};
}

// A string naming an enum value.
template <typename Get, typename Parse, typename Name>
Field choice(std::string_view section, std::string_view key, Get get, Parse parse, Name name,
             std::string_view allowed) {
  return {section, key, Kind::String,
          [get, parse, allowed](const toml::node& n, DaemonConfig& c) -> std::string {
            const auto* v = n.as_string();
            if (v == nullptr) return typeError("a string", n);
            if (!parse(v->get(), get(c)))
              return "must be one of " + std::string(allowed) + " (got " + tomlString(v->get()) +
                     ")";
            return {};
          },
          [get, name](const DaemonConfig& c) { return tomlString(name(get(c))); }};
}

using Source = DaemonConfig::Source;

bool parseCameraSource(std::string_view s, Source& out) {
  for (Source v : {Source::V4l2, Source::Libcamera, Source::File}) {
    if (s == toString(v)) {
      out = v;
      return true;
    }
  }
  return false;
}

std::string upper(const std::string& s) {
  std::string up;
  for (char ch : s) up += static_cast<char>(std::toupper(static_cast<unsigned char>(ch)));
  return up;
}

std::string checkPixelFormat(const std::string& s) {
  if (s == "auto") return {};
  // The names the capture backends take (V4L2: all of them; libcamera: the YUV ones,
  // which it checks again at open with the camera's own list).
  static constexpr std::array<std::string_view, 11> kNames = {
      "NV12", "YUV420", "YU12", "I420", "YUYV", "YUY2", "MJPEG", "MJPG", "GREY", "GRAY", "GRAY8"};
  if (std::find(kNames.begin(), kNames.end(), upper(s)) != kNames.end()) return {};
  return "must be \"auto\" or one of NV12, YUV420 (YU12, I420), YUYV (YUY2), MJPEG (MJPG), "
         "GREY (GRAY, GRAY8) (got " +
         tomlString(s) + ")";
}

std::string checkStartTime(const std::string& s) {
  std::int64_t ns = 0;
  if (s.empty() || s == "auto" || parseUtcTime(s, ns)) return {};
  return "expected a UTC time like \"2026-06-01T10:00:00Z\", unix seconds or \"auto\" (got " +
         tomlString(s) + ")";
}

std::string checkMavlinkUrl(const std::string& s) {
  std::string e;
  if (s.empty() || parseMavlinkUrl(s, e)) return {};
  return e;
}

std::string checkExifText(const std::string& s) {
  const std::string e = exifTextError(s);
  return e.empty() ? e : e + " (got " + tomlString(s) + ")";
}

std::string checkAbsolutePath(const std::string& s) {
  if (!s.empty() && s[0] == '/') return {};
  return "must be an absolute path (got " + tomlString(s) + ")";
}

// Files named in a configuration file: absolute, as the service starts in / (a
// relative name would pass check-config run elsewhere); --set makes them absolute.
std::string checkCalibration(const std::string& s) {
  if (s.empty()) return {};
  if (std::string e = checkAbsolutePath(s); !e.empty()) return e;
  CameraModel model;
  std::string e;
  if (!loadCameraModel(s, model, e)) return e;  // names the file
  return {};
}

// A file the daemon reads at start (the Zenoh configuration): there and readable, so
// that check-config says so rather than the start.
std::string checkReadableFile(const std::string& s) {
  if (s.empty()) return {};
  std::error_code ec;
  if (!fs::exists(s, ec)) return "no such file: " + s;
  if (!fs::is_regular_file(s, ec)) return "not a regular file: " + s;
  if (std::FILE* f = std::fopen(s.c_str(), "rb")) {
    std::fclose(f);
    return {};
  }
  return "cannot be read: " + s + ": " + std::strerror(errno);
}

// The Zenoh configuration: readable, and a configuration zenoh takes (a typo found
// by check-config and at the start, exit 78, not by the session after the camera
// opened: a restart loop under systemd).
std::string checkZenohConfig(const std::string& s) {
  if (s.empty()) return {};
  if (std::string e = checkAbsolutePath(s); !e.empty()) return e;
  if (std::string e = checkReadableFile(s); !e.empty()) return e;
  return zenohConfigError(s);
}

// Keys that name a file or directory.
bool isFileKey(std::string_view name) {
  return name == "tagging.calibration" || name == "zenoh.config" || name == "output.state_dir";
}

// A chunk of the key expression keyframed/<vehicle>/... ("": the host's name).
std::string checkVehicle(const std::string& s) {
  if (s.empty()) return {};
  const std::string e = vehicleNameError(s);
  return e.empty() ? e : e + " (got " + tomlString(s) + ")";
}

Field autopilot() {
  return {"telemetry", "autopilot", Kind::String,
          [](const toml::node& n, DaemonConfig& c) -> std::string {
            TelemetryConfig& t = c.telemetry.link.decoder;
            if (const auto* i = n.as_integer()) {  // autopilot = 1
              if (!limits::kMavlinkId.contains(i->get()))
                return rangeError(limits::kMavlinkId, i->get());
              t.autopilotSystem = static_cast<int>(i->get());
              t.autopilotComponent = 0;
              return {};
            }
            const auto* v = n.as_string();
            if (v == nullptr) return typeError("a string \"SYS[:COMP]\"", n);
            if (v->get().empty()) {
              t.autopilotSystem = 0;
              t.autopilotComponent = 0;
              return {};
            }
            std::string e = parseAutopilot(v->get(), t.autopilotSystem, t.autopilotComponent);
            return e.empty() ? e : e + " (got " + tomlString(v->get()) + ")";
          },
          [](const DaemonConfig& c) {
            const TelemetryConfig& t = c.telemetry.link.decoder;
            if (t.autopilotSystem == 0) return tomlString("");
            std::string s = std::to_string(t.autopilotSystem);
            if (t.autopilotComponent != 0) s += ":" + std::to_string(t.autopilotComponent);
            return tomlString(s);
          }};
}

Field categoryLevel(LogCategory category) {
  const auto i = static_cast<std::size_t>(category);
  return {"log", toString(category), Kind::String,
          [i](const toml::node& n, DaemonConfig& c) -> std::string {
            const auto* v = n.as_string();
            if (v == nullptr) return typeError("a string", n);
            LogLevel level{};
            if (v->get().empty()) {
              c.log.categories[i].reset();
            } else if (parseLogLevel(v->get(), level)) {
              c.log.categories[i] = level;
            } else {
              return "must be \"\" (follow log.level) or one of debug, info, notice, warning, "
                     "error (got " +
                     tomlString(v->get()) + ")";
            }
            return {};
          },
          [i](const DaemonConfig& c) {
            const auto& l = c.log.categories[i];
            return tomlString(l ? toString(*l) : "");
          }};
}

std::vector<Field> makeSchema() {
  namespace L = limits;
  using R = SettingRange<std::int64_t>;
  std::vector<Field> f;
  // [camera]
  f.push_back(choice(
      "camera", "source", [](auto& c) -> auto& { return c.camera.source; }, parseCameraSource,
      [](Source s) { return toString(s); }, "v4l2, libcamera, file"));
  f.push_back(text(
      "camera", "device", [](auto& c) -> auto& { return c.camera.device; }));
  f.push_back(text(
      "camera", "path", [](auto& c) -> auto& { return c.camera.path; }));
  f.push_back(integer(
      "camera", "width", [](auto& c) -> auto& { return c.camera.width; }, R{16, 16384}));
  f.push_back(integer(
      "camera", "height", [](auto& c) -> auto& { return c.camera.height; }, R{16, 16384}));
  f.push_back(real(
      "camera", "fps", [](auto& c) -> auto& { return c.camera.fps; },
      SettingRange<double>{1.0, 240.0}));
  f.push_back(text(
      "camera", "pixel_format", [](auto& c) -> auto& { return c.camera.pixelFormat; },
      checkPixelFormat));
  f.push_back(boolean(
      "camera", "realtime", [](auto& c) -> auto& { return c.camera.realtime; }));
  f.push_back(text(
      "camera", "start_time", [](auto& c) -> auto& { return c.camera.startTime; }, checkStartTime));
  f.push_back(integer(
      "camera", "queue_ms", [](auto& c) -> auto& { return c.camera.queueMs; }, R{0, 5000}));
  f.push_back(real(
      "camera", "time_offset_ms", [](auto& c) -> auto& { return c.camera.timeOffsetMs; },
      limits::kTimeOffsetMs));

  // [selection]: the same settings as `keyframed select`'s options.
  const auto sel = "selection";
  f.push_back(choice(
      sel, "mode", [](auto& c) -> auto& { return c.selection.overlap.mode; },
      [](std::string_view s, OverlapMode& m) { return parseOverlapMode(s, m); },
      [](OverlapMode m) { return toString(m); }, "geometric, paper"));
  f.push_back(real(
      sel, "target", [](auto& c) -> auto& { return c.selection.target; }, L::kOverlapTarget));
  f.push_back(real(
      sel, "band_low", [](auto& c) -> auto& { return c.selection.bandLow; }, L::kOverlapBand));
  f.push_back(real(
      sel, "band_high", [](auto& c) -> auto& { return c.selection.bandHigh; }, L::kOverlapBand));
  f.push_back(real(
      sel, "min_overlap", [](auto& c) -> auto& { return c.selection.minOverlap; }, L::kMinOverlap));
  f.push_back(real(
      sel, "motion_ratio", [](auto& c) -> auto& { return c.selection.motionRatio; },
      L::kMotionRatio, ZeroOr{1.0, "off"}));
  f.push_back(real(
      sel, "motion_min_fraction", [](auto& c) -> auto& { return c.selection.motionMinFraction; },
      L::kMotionMinFraction));
  f.push_back(integer(
      sel, "motion_window", [](auto& c) -> auto& { return c.selection.motionWindow; },
      L::kMotionWindow));
  f.push_back(integer(
      sel, "capture_wait_ms", [](auto& c) -> auto& { return c.selection.captureWaitMs; },
      L::kCaptureWaitMs));
  f.push_back(integer(
      sel, "analysis_width", [](auto& c) -> auto& { return c.selection.analysisWidth; },
      L::kAnalysisWidth, ZeroOr{64, "full"}));
  f.push_back(integer(
      sel, "max_tracks", [](auto& c) -> auto& { return c.selection.overlap.maxTracks; },
      L::kMaxTracks));
  f.push_back(integer(
      sel, "min_tracks", [](auto& c) -> auto& { return c.selection.overlap.minTracks; },
      L::kMinTracks));
  f.push_back(integer(
      sel, "min_inliers", [](auto& c) -> auto& { return c.selection.overlap.minInliers; },
      L::kMinInliers));
  f.push_back(real(
      sel, "ransac_px", [](auto& c) -> auto& { return c.selection.overlap.ransacPixels; },
      L::kRansacPixels));
  f.push_back(integer(
      sel, "fast_threshold", [](auto& c) -> auto& { return c.selection.overlap.fastThreshold; },
      L::kFastThreshold));
  f.push_back(integer(
      sel, "lk_window", [](auto& c) -> auto& { return c.selection.overlap.lkWindow; },
      L::kLkWindow));
  f.push_back(integer(
      sel, "lk_levels", [](auto& c) -> auto& { return c.selection.overlap.lkLevels; },
      L::kLkLevels));
  f.push_back(integer(
      sel, "orb_features", [](auto& c) -> auto& { return c.selection.overlap.orbFeatures; },
      L::kOrbFeatures));
  f.push_back(real(
      sel, "paper_threshold", [](auto& c) -> auto& { return c.selection.overlap.paperThreshold; },
      L::kPaperThreshold));
  f.push_back(integer(
      sel, "paper_min_matches",
      [](auto& c) -> auto& { return c.selection.overlap.paperMinMatches; }, L::kPaperMinMatches));
  f.push_back(choice(
      sel, "blur_mode", [](auto& c) -> auto& { return c.selection.blur.mode; },
      [](std::string_view s, BlurMode& m) { return parseBlurMode(s, m); },
      [](BlurMode m) { return blurModeName(m); }, "adaptive, absolute"));
  f.push_back(real(
      sel, "blur_threshold", [](auto& c) -> auto& { return c.selection.blur.absoluteThreshold; },
      L::kBlurThreshold));
  f.push_back(real(
      sel, "blur_floor", [](auto& c) -> auto& { return c.selection.blur.floor; }, L::kBlurFloor));
  f.push_back(real(
      sel, "blur_ratio", [](auto& c) -> auto& { return c.selection.blur.ratio; }, L::kBlurRatio));
  f.push_back(real(
      sel, "blur_quantile", [](auto& c) -> auto& { return c.selection.blur.quantile; },
      L::kBlurQuantile));
  f.push_back(integer(
      sel, "blur_window", [](auto& c) -> auto& { return c.selection.blur.window; },
      L::kBlurWindow));
  f.push_back(integer(
      sel, "blur_warmup", [](auto& c) -> auto& { return c.selection.blur.warmup; },
      L::kBlurWarmup));
  f.push_back(integer(
      sel, "blur_row_step", [](auto& c) -> auto& { return c.selection.blur.rowStep; },
      L::kBlurStep));
  f.push_back(integer(
      sel, "blur_col_step", [](auto& c) -> auto& { return c.selection.blur.colStep; },
      L::kBlurStep));
  f.push_back(integer(
      sel, "blur_width", [](auto& c) -> auto& { return c.selection.blur.analysisWidth; },
      L::kBlurWidth, ZeroOr{32, "full"}));

  // [telemetry]
  f.push_back(text(
      "telemetry", "url", [](auto& c) -> auto& { return c.telemetry.link.url; }, checkMavlinkUrl));
  f.push_back(autopilot());
  f.push_back(integer(
      "telemetry", "mavlink_sysid", [](auto& c) -> auto& { return c.telemetry.link.systemId; },
      L::kOwnSystemId));
  f.push_back(integer(
      "telemetry", "component_id", [](auto& c) -> auto& { return c.telemetry.link.componentId; },
      L::kMavlinkId));
  f.push_back(boolean(
      "telemetry", "timesync", [](auto& c) -> auto& { return c.telemetry.link.timesync; }));
  f.push_back(real(
      "telemetry", "message_rate_hz",
      [](auto& c) -> auto& { return c.telemetry.link.messageRateHz; },
      SettingRange<double>{0.0, 200.0}, ZeroOr{1.0, "off"}));
  f.push_back(boolean(
      "telemetry", "camera_component", [](auto& c) -> auto& { return c.telemetry.link.camera; }));
  f.push_back(boolean(
      "telemetry", "mavlink1", [](auto& c) -> auto& { return c.telemetry.link.mavlink1; }));
  f.push_back(integer(
      "telemetry", "wait_ms", [](auto& c) -> auto& { return c.telemetry.waitMs; },
      L::kTelemetryWaitMs));
  f.push_back(integer(
      "telemetry", "start_wait_ms", [](auto& c) -> auto& { return c.telemetry.startWaitMs; },
      L::kTelemetryStartWaitMs));
  f.push_back(duration(
      "telemetry", "stale_ms",
      [](auto& c) -> auto& { return c.telemetry.link.decoder.store.maxHoldNs; }, R{0, 10000},
      kNsPerMs));
  f.push_back(duration(
      "telemetry", "attitude_gap_ms",
      [](auto& c) -> auto& { return c.telemetry.link.decoder.store.maxAttitudeGapNs; }, R{1, 10000},
      kNsPerMs));
  f.push_back(duration(
      "telemetry", "position_gap_ms",
      [](auto& c) -> auto& { return c.telemetry.link.decoder.store.maxPositionGapNs; }, R{1, 60000},
      kNsPerMs));
  f.push_back(duration(
      "telemetry", "history_s",
      [](auto& c) -> auto& { return c.telemetry.link.decoder.store.historyNs; }, R{1, 3600},
      kNsPerS));
  f.push_back(integer(
      "telemetry", "min_fix_type",
      [](auto& c) -> auto& { return c.telemetry.link.decoder.store.minFixType; }, R{0, 6}));
  f.push_back(duration(
      "telemetry", "gps_stale_ms",
      [](auto& c) -> auto& { return c.telemetry.link.decoder.store.maxGpsAgeNs; }, R{100, 600000},
      kNsPerMs));
  f.push_back(integer(
      "telemetry", "pending_captures",
      [](auto& c) -> auto& { return c.telemetry.link.maxPendingCaptures; }, R{1, 100000}));
  f.push_back(integer(
      "telemetry", "capture_history",
      [](auto& c) -> auto& { return c.telemetry.link.captureHistory; }, R{0, 100000}));
  f.push_back(duration(
      "telemetry", "clock_window_s",
      [](auto& c) -> auto& { return c.telemetry.link.decoder.clock.arrivalWindowNs; }, R{1, 600},
      kNsPerS));
  f.push_back(duration(
      "telemetry", "timesync_timeout_s",
      [](auto& c) -> auto& { return c.telemetry.link.decoder.clock.timesyncTimeoutNs; }, R{1, 600},
      kNsPerS));

  // [tagging]
  f.push_back(text(
      "tagging", "calibration", [](auto& c) -> auto& { return c.tagging.calibration; },
      checkCalibration));
  f.push_back(text(
      "tagging", "make", [](auto& c) -> auto& { return c.tagging.make; }, checkExifText));
  f.push_back(text(
      "tagging", "model", [](auto& c) -> auto& { return c.tagging.model; }, checkExifText));
  f.push_back(boolean(
      "tagging", "system_clock_utc", [](auto& c) -> auto& { return c.tagging.systemClockUtc; }));
  f.push_back(choice(
      "tagging", "mount", [](auto& c) -> auto& { return c.tagging.mountGimbal; },
      [](std::string_view s, bool& g) {
        if (s != "fixed" && s != "gimbal") return false;
        g = s == "gimbal";
        return true;
      },
      [](bool g) { return std::string(g ? "gimbal" : "fixed"); }, "fixed, gimbal"));
  f.push_back(real(
      "tagging", "mount_roll", [](auto& c) -> auto& { return c.tagging.mountRollDeg; },
      L::kMountAngleDeg));
  f.push_back(real(
      "tagging", "mount_pitch", [](auto& c) -> auto& { return c.tagging.mountPitchDeg; },
      L::kMountAngleDeg));
  f.push_back(real(
      "tagging", "mount_yaw", [](auto& c) -> auto& { return c.tagging.mountYawDeg; },
      L::kMountAngleDeg));
  f.push_back(integer(
      "tagging", "jpeg_quality", [](auto& c) -> auto& { return c.tagging.jpegQuality; },
      L::kJpegQuality));

  // [output]
  f.push_back(text(
      "output", "state_dir", [](auto& c) -> auto& { return c.output.stateDir; },
      checkAbsolutePath));
  f.push_back(boolean(
      "output", "mcap", [](auto& c) -> auto& { return c.output.mcap; }));
  f.push_back(integer(
      "output", "mcap_rotate_mb", [](auto& c) -> auto& { return c.output.mcapRotateMb; },
      R{0, 1 << 20}));
  f.push_back(integer(
      "output", "mcap_rotate_s", [](auto& c) -> auto& { return c.output.mcapRotateS; },
      R{0, 86400}));
  f.push_back(boolean(
      "output", "mcap_fsync", [](auto& c) -> auto& { return c.output.mcapFsync; }));
  f.push_back(text(
      "output", "mcap_compression", [](auto& c) -> auto& { return c.output.mcapCompression; },
      [](const std::string& s) -> std::string {
        return s == "auto" || s == "zstd" || s == "lz4" || s == "none"
                   ? ""
                   : "must be auto, zstd, lz4 or none (got " + tomlString(s) + ")";
      }));
  f.push_back(integer(
      "output", "preview_width", [](auto& c) -> auto& { return c.output.previewWidth; },
      R{0, 16384}, ZeroOr{16, "no preview"}));
  f.push_back(text(
      "output", "preview_format", [](auto& c) -> auto& { return c.output.previewFormat; },
      [](const std::string& s) -> std::string {
        if (s == "h264" && !h264EncoderAvailable())
          return "h264 needs libavcodec with its libx264 encoder, which this one lacks (use "
                 "\"jpeg\")";
        return s == "jpeg" || s == "h264" ? "" : "must be jpeg or h264 (got " + tomlString(s) + ")";
      }));

  // [zenoh]
  f.push_back(boolean(
      "zenoh", "enabled", [](auto& c) -> auto& { return c.zenoh.enabled; }));
  f.push_back(text(
      "zenoh", "config", [](auto& c) -> auto& { return c.zenoh.config; }, checkZenohConfig));
  f.push_back(text(
      "zenoh", "vehicle", [](auto& c) -> auto& { return c.zenoh.vehicle; }, checkVehicle));
  f.push_back(integer(
      "zenoh", "open_retry_s", [](auto& c) -> auto& { return c.zenoh.openRetryS; }, R{0, 3600}));

  // [log]
  f.push_back(choice(
      "log", "level", [](auto& c) -> auto& { return c.log.level; },
      [](std::string_view s, LogLevel& l) { return parseLogLevel(s, l); },
      [](LogLevel l) { return toString(l); }, "debug, info, notice, warning, error"));
  f.push_back(choice(
      "log", "target", [](auto& c) -> auto& { return c.log.target; },
      [](std::string_view s, LogTarget& t) { return parseLogTarget(s, t); },
      [](LogTarget t) { return toString(t); }, "auto, journal, stderr"));
  for (int i = 0; i < kLogCategories; ++i) f.push_back(categoryLevel(static_cast<LogCategory>(i)));
  return f;
}

const std::vector<Field>& schema() {
  static const std::vector<Field> s = makeSchema();
  return s;
}

const Field* findField(std::string_view section, std::string_view key) {
  for (const Field& f : schema()) {
    if (f.section == section && f.key == key) return &f;
  }
  return nullptr;
}

bool isSection(std::string_view name) {
  return std::any_of(schema().begin(), schema().end(),
                     [name](const Field& f) { return f.section == name; });
}

std::size_t editDistance(std::string_view a, std::string_view b) {
  std::vector<std::size_t> row(b.size() + 1);
  for (std::size_t j = 0; j <= b.size(); ++j) row[j] = j;
  for (std::size_t i = 1; i <= a.size(); ++i) {
    std::size_t diag = row[0];
    row[0] = i;
    for (std::size_t j = 1; j <= b.size(); ++j) {
      const std::size_t up = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, diag + (a[i - 1] == b[j - 1] ? 0 : 1)});
      diag = up;
    }
  }
  return row[b.size()];
}

// " (did you mean 'x'?)" for a near miss among the candidates.
std::string suggestion(std::string_view name, const std::vector<std::string>& candidates) {
  std::string best;
  std::size_t bestDistance = 3;
  for (const std::string& c : candidates) {
    const std::size_t d = editDistance(name, c);
    if (d < bestDistance) {
      bestDistance = d;
      best = c;
    }
  }
  return best.empty() ? "" : " (did you mean '" + best + "'?)";
}

std::vector<std::string> keysOf(std::string_view section) {
  std::vector<std::string> keys;
  for (const Field& f : schema()) {
    if (f.section == section) keys.emplace_back(f.key);
  }
  return keys;
}

// ---------------------------------------------------------------- loading

// Where a key got its value.
struct Origin {
  int layer = 0;  // 0: built-in default
  std::string where;
  std::int64_t line = 0;
};

struct Error {
  int layer;
  std::int64_t line;
  std::string text;
};

class Loader {
 public:
  explicit Loader(ConfigLoadResult& out) : out_(out) {
    out_.layers.emplace_back("built-in defaults");
  }

  void file(const std::string& path) {
    ++layer_;
    out_.layers.push_back(path);
    std::error_code ec;
    if (!fs::is_regular_file(path, ec)) {
      fail(0, path + ": " + (fs::exists(path, ec) ? "not a regular file" : "no such file"));
      return;
    }
    std::string text;
    if (std::string why = readSmallText(path, text); !why.empty()) {
      fail(0, path + ": " + why);
      return;
    }
    toml::table doc;
    try {
      doc = toml::parse(text, path);
    } catch (const toml::parse_error& e) {
      fail(e.source().begin.line, path + ":" + std::to_string(e.source().begin.line) + ": " +
                                      std::string(e.description()));
      return;
    }
    for (auto&& [name, node] : doc) {
      const std::int64_t line = name.source().begin.line;
      const std::string prefix = path + ":" + std::to_string(line) + ": ";
      const std::string sectionName(name.str());
      if (!isSection(sectionName)) {
        if (!node.is_table()) {
          std::string hint;
          for (const Field& f : schema()) {
            if (f.key == sectionName) hint = " (did you mean [" + std::string(f.section) + "]?)";
          }
          fail(line, prefix + sectionName + ": key outside any section" + hint);
          continue;
        }
        fail(line, prefix + sectionName + ": unknown section" +
                       suggestion(sectionName, configSections()));
        continue;
      }
      const toml::table* section = node.as_table();
      if (section == nullptr) {
        fail(line, prefix + sectionName + ": expected a [" + sectionName + "] table, got " +
                       typeName(node));
        continue;
      }
      for (auto&& [key, value] : *section) {
        const std::int64_t keyLine = key.source().begin.line;
        const std::string keyName(key.str());
        const std::string where = path + ":" + std::to_string(keyLine);
        if (sectionName == "tagging" && keyName == "camera") {
          inlineCamera(value, path, where, keyLine);
          continue;
        }
        const Field* field = findField(sectionName, keyName);
        if (field == nullptr) {
          fail(keyLine, where + ": " + sectionName + "." + keyName + ": unknown key" +
                            suggestion(keyName, keysOf(sectionName)));
          continue;
        }
        apply(*field, value, where, keyLine);
      }
    }
  }

  void overrideKey(const std::string& assignment) {
    ++layer_;
    const std::string where = "--set " + assignment;
    out_.layers.push_back(where);
    if (assignment.find_first_of("\r\n") != std::string::npos) {
      fail(0, "--set " + tomlString(assignment) + ": one line, SECTION.KEY=VALUE");
      return;
    }
    if (!isSetAssignment(assignment)) {
      fail(0, where + ": expected --set SECTION.KEY=VALUE");
      return;
    }
    const auto eq = assignment.find('=');
    const std::string name = assignment.substr(0, eq);
    const auto dot = name.find('.');
    const std::string section = name.substr(0, dot);
    const std::string key = name.substr(dot + 1);
    if (!isSection(section)) {
      fail(0, where + ": " + section + ": unknown section" + suggestion(section, configSections()));
      return;
    }
    const Field* field = findField(section, key);
    if (field == nullptr) {
      fail(0, where + ": " + name + ": unknown key" + suggestion(key, keysOf(section)));
      return;
    }
    const std::string value = assignment.substr(eq + 1);
    // Strings need no quotes on a command line: --set camera.source=file. A file
    // named relative to the working directory, as a command line's names are.
    if (field->kind == Kind::String && (value.empty() || (value[0] != '"' && value[0] != '\''))) {
      std::string text = value;
      if (isFileKey(name) && !text.empty() && text[0] != '/') {
        std::error_code ec;
        const fs::path absolute = fs::absolute(text, ec);
        if (!ec) text = absolute.lexically_normal().string();
      }
      apply(*field, toml::value<std::string>(text), where, 0);
      return;
    }
    toml::table doc;
    try {
      doc = toml::parse("v = " + value);
    } catch (const toml::parse_error&) {
      const char* expected = field->kind == Kind::Integer   ? "an integer"
                             : field->kind == Kind::Real    ? "a number"
                             : field->kind == Kind::Boolean ? "true or false"
                                                            : "a string";
      fail(0, where + ": " + name + ": expected " + expected + " (got " + tomlString(value) + ")");
      return;
    }
    apply(*field, *doc.get("v"), where, 0);
  }

  // Checks that involve more than one key, reported where the last of them was set.
  void crossChecks() {
    const DaemonConfig& c = out_.config;
    if (c.tagging.camera && !c.tagging.calibration.empty()) {
      const Origin& a = origins_["tagging.camera"];
      const Origin& b = origins_["tagging.calibration"];
      const Origin& latest = (b.layer > a.layer || (b.layer == a.layer && b.line > a.line)) ? b : a;
      fail(latest.line,
           (latest.where.empty() ? std::string("built-in defaults") : latest.where) +
               ": tagging.calibration and [tagging.camera] are both set: give the intrinsics "
               "one way",
           latest.layer);
    }
    const SelectorConfig& s = c.selection;
    auto num = [](double v) { return tomlReal(v); };
    auto require = [this](bool ok, std::vector<std::string> keys, const std::string& message) {
      if (ok) return;
      std::string latestKey = keys.front();
      Origin latest = origins_[latestKey];
      for (const std::string& k : keys) {
        const Origin& o = origins_[k];
        if (o.layer > latest.layer || (o.layer == latest.layer && o.line > latest.line)) {
          latest = o;
          latestKey = k;
        }
      }
      std::string text = latest.where.empty() ? std::string("built-in defaults") : latest.where;
      text.append(": ").append(latestKey).append(": ").append(message);
      fail(latest.line, std::move(text), latest.layer);
    };
    require(s.bandLow <= s.target, {"selection.band_low", "selection.target"},
            "selection.band_low (" + num(s.bandLow) + ") must not exceed selection.target (" +
                num(s.target) + ")");
    require(s.target <= s.bandHigh, {"selection.band_high", "selection.target"},
            "selection.target (" + num(s.target) + ") must not exceed selection.band_high (" +
                num(s.bandHigh) + ")");
    require(s.minOverlap <= s.bandLow, {"selection.min_overlap", "selection.band_low"},
            "selection.min_overlap (" + num(s.minOverlap) +
                ") must not exceed selection.band_low (" + num(s.bandLow) + ")");
    require(s.overlap.minTracks <= s.overlap.maxTracks,
            {"selection.min_tracks", "selection.max_tracks"},
            "selection.min_tracks must not exceed selection.max_tracks");
    require(s.overlap.minInliers <= s.overlap.minTracks,
            {"selection.min_inliers", "selection.min_tracks"},
            "selection.min_inliers must not exceed selection.min_tracks (tracks are "
            "replenished only below it)");
    require(s.overlap.paperMinMatches <= s.overlap.orbFeatures,
            {"selection.paper_min_matches", "selection.orb_features"},
            "selection.paper_min_matches must not exceed selection.orb_features");
    require(s.blur.warmup <= s.blur.window, {"selection.blur_warmup", "selection.blur_window"},
            "selection.blur_warmup must not exceed selection.blur_window");
    require(c.camera.source != Source::File || !c.camera.path.empty(),
            {"camera.source", "camera.path"}, "source \"file\" needs camera.path");
    // (An unknown name is reported by the key's own check.)
    require(c.camera.source != Source::File || filePixelFormat(c.camera.pixelFormat) ||
                !checkPixelFormat(c.camera.pixelFormat).empty(),
            {"camera.source", "camera.pixel_format"},
            "source \"file\" delivers \"auto\" (BGR, as decoded), YUV420 or NV12 (got " +
                tomlString(c.camera.pixelFormat) + ")");
    {
      const std::string pf = upper(c.camera.pixelFormat);
      const bool libcameraFormat = pf == "AUTO" || pf == "NV12" || pf == "YUV420" || pf == "YU12" ||
                                   pf == "I420" || pf == "YUYV" || pf == "YUY2";
      require(c.camera.source != Source::Libcamera || libcameraFormat ||
                  !checkPixelFormat(c.camera.pixelFormat).empty(),
              {"camera.source", "camera.pixel_format"},
              "source \"libcamera\" delivers \"auto\", NV12, YUV420 or YUYV (got " +
                  tomlString(c.camera.pixelFormat) + ")");
    }
    std::string e;
    const std::string& url = c.telemetry.link.url;
    require(!isTlogUrl(url) || (c.camera.source == Source::File && !c.camera.startTime.empty()),
            {"telemetry.url", "camera.source", "camera.start_time"},
            "a tlog replays a recorded flight: it needs camera.source = \"file\" and "
            "camera.start_time");
    require(c.camera.startTime != "auto" || (c.camera.source == Source::File && isTlogUrl(url)),
            {"camera.start_time", "camera.source", "telemetry.url"},
            "camera.start_time = \"auto\" places a video in its tlog by their motion: it needs "
            "camera.source = \"file\" and a tlog as telemetry.url");
    // Frames read as fast as they decode carry the video's time, which a live link's
    // poses have nothing to do with: every keyframe would be tagged wrong or not at all.
    require(c.camera.source != Source::File || c.camera.realtime || url.empty() || isTlogUrl(url),
            {"camera.realtime", "telemetry.url"},
            "a live telemetry link needs camera.realtime = true (a file read as fast as it "
            "decodes is on the video's clock; replay its tlog instead, or set telemetry.url "
            "= \"\")");
    // The core's own rules (e.g. "0 or >= 64") as a last line of defence.
    if (errors_.empty()) {
      std::vector<std::string> keys;
      for (const std::string& k : keysOf("selection")) keys.push_back("selection." + k);
      const std::string core = s.validate();
      require(core.empty(), keys, core);
    }
  }

  void finish() {
    // A dependent key set in an earlier file than the key it depends on follows it as
    // its default would (the shipped keyframed.toml spells out min_tracks = 80; a
    // conf.d file's max_tracks = 50 alone lowers it).
    const auto setSince = [this](const char* dependent, const char* controlling) {
      const auto d = origins_.find(dependent);
      if (d == origins_.end()) return false;
      const auto c = origins_.find(controlling);
      return c == origins_.end() || d->second.layer >= c->second.layer;
    };
    relaxDependentDefaults(out_.config.selection,
                           setSince("selection.min_tracks", "selection.max_tracks"),
                           setSince("selection.blur_warmup", "selection.blur_window"));
    crossChecks();
    std::stable_sort(errors_.begin(), errors_.end(), [](const Error& a, const Error& b) {
      return a.layer != b.layer ? a.layer < b.layer : a.line < b.line;
    });
    for (Error& e : errors_) out_.errors.push_back(std::move(e.text));
  }

 private:
  void apply(const Field& field, const toml::node& value, const std::string& where,
             std::int64_t line) {
    if (std::string e = field.read(value, out_.config); !e.empty()) {
      fail(line, where + ": " + field.name() + ": " + e);
      return;
    }
    origins_[field.name()] = {layer_, where, line};
  }

  // [tagging.camera]: replaces an earlier layer's table as a whole.
  void inlineCamera(const toml::node& value, const std::string& path, const std::string& where,
                    std::int64_t line) {
    const toml::table* table = value.as_table();
    if (table == nullptr) {
      fail(line,
           where + ": tagging.camera: expected a [tagging.camera] table, got " + typeName(value));
      return;
    }
    CameraModel m;
    std::string e;
    if (!cameraFromTomlTable(*table, path, "tagging.camera", m, e)) {
      fail(line, e);
      return;
    }
    out_.config.tagging.camera = std::move(m);
    origins_["tagging.camera"] = {layer_, where, line};
  }

  void fail(std::int64_t line, std::string text, int layer = -1) {
    errors_.push_back({layer < 0 ? layer_ : layer, line, std::move(text)});
  }

  ConfigLoadResult& out_;
  int layer_ = 0;
  std::map<std::string, Origin> origins_;
  std::vector<Error> errors_;
};

// A drop-in by its name: one that is then no regular file (a directory, a dangling
// symlink) is an error, not skipped, as its settings would be lost without a word.
bool isTomlFile(const fs::directory_entry& e) {
  const std::string name = e.path().filename().string();
  return !name.starts_with(".") && name.ends_with(".toml");
}

}  // namespace

std::string defaultConfigDir() {
  const char* env = std::getenv("KEYFRAMED_CONFIG_DIR");
  return env != nullptr && *env != '\0' ? env : KEYFRAMED_DEFAULT_CONFIG_DIR;
}

ConfigLoadResult loadConfig(const ConfigSources& sources) {
  ConfigLoadResult result;
  Loader loader(result);
  if (!sources.files.empty()) {
    for (const std::string& f : sources.files) loader.file(f);
  } else {
    const bool explicitDir = !sources.configDir.empty();
    const fs::path dir = explicitDir ? sources.configDir : defaultConfigDir();
    std::error_code ec;
    if (explicitDir && !fs::is_directory(dir, ec)) {
      result.errors.push_back(dir.string() + ": no such directory");
      return result;
    }
    // A missing main file or conf.d means: defaults.
    // (A dangling symlink in its place is an error: someone meant a file there.)
    if (fs::exists(dir / "keyframed.toml", ec) || fs::is_symlink(dir / "keyframed.toml", ec))
      loader.file((dir / "keyframed.toml").string());
    std::vector<std::string> dropIns;
    // increment(ec), not a range-for: a read error mid-directory (a failing SD card,
    // on a SIGHUP reload too) is reported, not thrown.
    for (fs::directory_iterator it(dir / "conf.d", ec), end; !ec && it != end; it.increment(ec)) {
      if (isTomlFile(*it)) dropIns.push_back(it->path().string());
    }
    // Missing is fine; there but unreadable would silently drop its settings.
    if (ec && ec != std::errc::no_such_file_or_directory) {
      result.errors.push_back((dir / "conf.d").string() + ": cannot read: " + ec.message());
    }
    std::sort(dropIns.begin(), dropIns.end());
    for (const std::string& f : dropIns) loader.file(f);
  }
  for (const std::string& o : sources.overrides) loader.overrideKey(o);
  loader.finish();
  return result;
}

ConfigLoadResult loadOverrides(const std::vector<std::string>& overrides) {
  ConfigLoadResult result;
  Loader loader(result);
  for (const std::string& o : overrides) loader.overrideKey(o);
  loader.finish();
  return result;
}

std::string takeConfigArgs(std::vector<std::string>& args, ConfigSources& sources) {
  std::vector<std::string> rest;
  for (std::size_t i = 0; i < args.size(); ++i) {
    std::string a = args[i];
    std::string value;
    bool inlineValue = false;
    if (a.starts_with("--")) {
      if (const auto eq = a.find('='); eq != std::string::npos) {
        value = a.substr(eq + 1);
        a = a.substr(0, eq);
        inlineValue = true;
      }
    }
    if (a != "--config-dir" && a != "--set") {
      rest.push_back(args[i]);
      continue;
    }
    if (!inlineValue) {
      if (i + 1 >= args.size()) return "option " + a + " needs a value";
      value = args[++i];
    }
    if (a == "--config-dir") {
      if (value.empty()) return "--config-dir: empty directory";
      sources.configDir = value;
    } else {
      // The form is a command-line matter (exit 2); the key and value are checked with
      // the files' (exit 1 from check-config, 78 from run).
      if (!isSetAssignment(value)) return "--set " + value + ": expected --set SECTION.KEY=VALUE";
      sources.overrides.push_back(value);
    }
  }
  args = std::move(rest);
  return {};
}

std::string toToml(const DaemonConfig& config) {
  std::string out;
  std::string_view section;
  for (const Field& f : schema()) {
    if (f.section != section) {
      if (!section.empty()) out += "\n";
      section = f.section;
      out.append("[").append(section).append("]\n");
    }
    out.append(f.key).append(" = ").append(f.write(config)).append("\n");
  }
  if (const auto& cam = config.tagging.camera) {
    out += "\n[tagging.camera]\n" + cameraTomlKeys(*cam);
  }
  return out;
}

namespace {

// What a flight record keeps of the configuration: every key of `section`, or the
// keys named in `names` ("section.key"), as `section.KEY=VALUE` lines.
std::string recordedLines(const DaemonConfig& c, std::string_view section,
                          std::span<const std::string_view> names) {
  std::string out;
  for (const Field& f : schema()) {
    const std::string name = f.name();
    if (names.empty() ? f.section != section
                      : std::find(names.begin(), names.end(), name) == names.end())
      continue;
    out.append(name).append("=").append(f.write(c)).append("\n");
  }
  return out;
}

// Those lines back, through --set's validation: any other line is an error.
ConfigLoadResult loadRecordedLines(const std::string& lines, std::string_view section,
                                   std::span<const std::string_view> names) {
  std::vector<std::string> overrides;
  std::size_t start = 0;
  while (start < lines.size()) {
    std::size_t end = lines.find('\n', start);
    if (end == std::string::npos) end = lines.size();
    std::string line = lines.substr(start, end - start);
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (!line.empty()) {
      const std::size_t eq = line.find('=');
      const std::string name = eq == std::string::npos ? std::string() : line.substr(0, eq);
      const bool known = names.empty() ? name.starts_with(std::string(section) + ".") &&
                                             name.size() > section.size() + 1
                                       : std::find(names.begin(), names.end(), name) != names.end();
      if (!known) {
        ConfigLoadResult r;
        r.errors.push_back("not a " + std::string(section) + " setting: '" + line + "'");
        return r;
      }
      overrides.push_back(std::move(line));
    }
    start = end + 1;
  }
  return loadOverrides(overrides);
}

// What shapes a keyframe's tags beside the camera model (which comes whole): EXIF make
// and model, the camera mount, the frame time's offset to the exposure.
constexpr std::string_view kRecordedTagging[] = {
    "tagging.make",        "tagging.model",     "tagging.mount",        "tagging.mount_roll",
    "tagging.mount_pitch", "tagging.mount_yaw", "camera.time_offset_ms"};

}  // namespace

std::string selectionOverrides(const SelectorConfig& selection) {
  DaemonConfig c;
  c.selection = selection;
  return recordedLines(c, "selection", {});
}

ConfigLoadResult loadSelectionOverrides(const std::string& lines) {
  return loadRecordedLines(lines, "selection", {});
}

std::string taggingOverrides(const DaemonConfig::Tagging& tagging, double timeOffsetMs) {
  DaemonConfig c;
  c.tagging = tagging;
  c.camera.timeOffsetMs = timeOffsetMs;
  return recordedLines(c, "tagging", kRecordedTagging);
}

ConfigLoadResult loadTaggingOverrides(const std::string& lines) {
  return loadRecordedLines(lines, "tagging", kRecordedTagging);
}

std::optional<PixelFormat> filePixelFormat(const std::string& name) {
  const std::string up = upper(name);
  if (up == "AUTO") return PixelFormat::BGR24;
  if (up == "YUV420" || up == "YU12" || up == "I420") return PixelFormat::YUV420;
  if (up == "NV12") return PixelFormat::NV12;
  return std::nullopt;
}

std::vector<std::string> configKeys() {
  std::vector<std::string> keys;
  for (const Field& f : schema()) keys.push_back(f.name());
  return keys;
}

std::vector<std::string> configSections() {
  std::vector<std::string> sections;
  for (const Field& f : schema()) {
    if (sections.empty() || sections.back() != f.section) sections.emplace_back(f.section);
  }
  return sections;
}

namespace {

constexpr const char* kCheckUsage =
    R"(usage: keyframed check-config [FILE...] [--config-dir DIR] [--set SECTION.KEY=VALUE]... [--quiet]

Loads the configuration the daemon would use, checks every key and prints the
result as TOML (every key, defaults included). Exit status 0 when valid, 1 with
one line per problem (FILE:LINE: SECTION.KEY: what is wrong) otherwise.

  FILE...             check these files (over the defaults) instead of the directory
  --config-dir DIR    DIR/keyframed.toml, then DIR/conf.d/*.toml in name order
                      (default: $KEYFRAMED_CONFIG_DIR, else )" KEYFRAMED_DEFAULT_CONFIG_DIR R"()
  --set S.KEY=VALUE   override one key (repeatable), e.g. --set camera.fps=25
  -q, --quiet         print nothing when valid
)";

}  // namespace

int checkConfigMain(const std::vector<std::string>& argsIn) {
  std::vector<std::string> args = argsIn;
  ConfigSources sources;
  if (std::string e = takeConfigArgs(args, sources); !e.empty()) {
    std::fprintf(stderr, "keyframed: check-config: %s\n", oneLine(e).c_str());
    return 2;
  }
  bool quiet = false;
  for (const std::string& a : args) {
    if (a == "-h" || a == "--help") {
      std::fputs(kCheckUsage, stdout);
      return 0;
    }
    if (a == "-q" || a == "--quiet") {
      quiet = true;
    } else if (a.starts_with("-")) {
      std::fprintf(stderr, "keyframed: check-config: unknown option %s (see --help)\n",
                   oneLine(a).c_str());
      return 2;
    } else {
      sources.files.push_back(a);
    }
  }
  if (!sources.files.empty() && !sources.configDir.empty()) {
    std::fputs("keyframed: check-config: give FILE or --config-dir, not both\n", stderr);
    return 2;
  }
  const ConfigLoadResult r = loadConfig(sources);
  if (!r.ok()) {
    for (const std::string& e : r.errors)
      std::fprintf(stderr, "keyframed: %s\n", oneLine(e).c_str());
    return 1;
  }
  if (!quiet) {
    std::string header = "# keyframed configuration from:";
    for (const std::string& l : r.layers) header += (&l == &r.layers.front() ? " " : " < ") + l;
    std::printf("%s\n%s", header.c_str(), toToml(r.config).c_str());
  }
  return 0;
}

}  // namespace keyframed
