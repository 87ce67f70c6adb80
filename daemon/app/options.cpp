#include "app/options.h"

#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <functional>
#include <map>
#include <set>

#include "app/config.h"
#include "output/mcap_replay.h"
#include "tagging/camera_model.h"
#include "telemetry/link.h"

namespace keyframed {
namespace {

bool parseInt(const std::string& s, std::int64_t& out) {
  if (s.empty()) return false;
  char* end = nullptr;
  errno = 0;
  out = std::strtoll(s.c_str(), &end, 10);
  return errno == 0 && end == s.c_str() + s.size();
}

bool parsePair(const std::string& s, std::string& a, std::string& b) {
  const auto comma = s.find(',');
  if (comma == std::string::npos) return false;
  a = s.substr(0, comma);
  b = s.substr(comma + 1);
  return true;
}

}  // namespace

std::string selectUsage() {
  return R"(usage: keyframed select VIDEO --out DIR [options]

Reads VIDEO, keeps sharp frames that overlap the previous keyframe by the
target amount, writes them to DIR as NNNNNN.jpg (zero-based frame index),
DIR/keyframes.csv (one row per keyframe: its pose and tags), DIR/decisions.csv
(one row per frame) and DIR/summary.json. VIDEO may also be
a flight record (MCAP from `keyframed run`): its preview stream is replayed, with
its recorded MAVLink as telemetry.

selection:
  --mode geometric|paper     overlap test (default geometric)
  --target F                 overlap to keep a frame at, 0.01..0.99 (default 0.70)
  --band LO,HI               overlap band for fallbacks (default 0.60,0.85)
  --min-overlap F            hard floor: a blurry fallback is kept rather than
                             let overlap fall under F (default 0.50)
  --motion-ratio R           geometric mode: a frame moving more than R times the
                             recent lower quartile is motion-blurred, 0 = off (default 4)
  --motion-min-fraction F    ... and more than F of the image width (default 0.01)
  --motion-window N          recent frames for that quartile (default 150)
  --capture-wait-ms MS       a capture asked for over MAVLink waits this long for a
                             sharp frame, then takes one at the floor (default 1000)
  --analysis-width PX        overlap analysis width, 0 = full (default 640)
  --orb-features N           paper mode: ORB features (default 2500)
  --paper-threshold T        paper mode: mean Hamming distance to keep (default 50)
  --paper-min-matches N      paper mode: fewer mutual matches = lost (default 20)
  --max-tracks N             geometric mode: tracked points (default 200)
  --min-tracks N             geometric mode: replenish below N (default 80, or
                             2/5 of --max-tracks when that is smaller)
  --min-inliers N            geometric mode: fewer RANSAC inliers = lost (default 15)
  --ransac-px PX             geometric mode: RANSAC threshold, analysis pixels (default 1.5)
  --fast-threshold N         geometric mode: FAST corner threshold (default 20)
  --lk-window N              geometric mode: optical-flow window (default 13)
  --lk-levels N              geometric mode: optical-flow pyramid levels (default 3)
blur:
  --blur-mode adaptive|absolute   (default adaptive)
  --blur-threshold V         absolute mode threshold on Laplacian variance (default 100)
  --blur-floor V             adaptive mode: absolute floor (default 10)
  --blur-ratio R             adaptive mode: fraction of the recent quantile (default 0.7)
  --blur-quantile Q          adaptive mode: quantile of recent scores (default 0.75)
  --blur-window N            adaptive mode: recent frames considered (default 150)
  --blur-warmup N            adaptive mode: frames before the statistic is trusted
                             (default 5, or the window when that is smaller)
  --blur-step R,C            sample every R-th row, C-th column (default 2,3)
  --blur-width PX            score at reduced width, 0 = full (default 0)
telemetry and tags:
  --telemetry SRC            MAVLink source: FILE.tlog, udpin:HOST:PORT, udpout:HOST:PORT
                             or serial:DEVICE[:BAUD]; keyframes are geotagged with the
                             pose at their time (a live link implies --realtime)
  --video-start TIME|auto    with a tlog: UTC time of the video's first frame (ISO 8601
                             or unix seconds), or auto (the default): found by lining
                             up the camera's turns in the video with the tlog's attitude
  --time-offset MS           the camera's latency: each keyframe's pose and UTC time are
                             taken MS after its frame time (negative: before; -2000..2000,
                             default 0)
  --calibration FILE         camera intrinsics (OpenCV YAML/XML, TOML or JSON)
  --make TEXT, --model TEXT  EXIF Make and Model (default: the calibration file's;
                             without one, only these are tagged)
  --mount R,P,Y|gimbal       camera mount on the body, degrees (default 0,-90,0: nadir),
                             or 'gimbal': the attitude of GIMBAL_DEVICE_ATTITUDE_STATUS
  --autopilot SYS[:COMP]     follow this autopilot (default: the first one heard)
  --mavlink-sysid N          our system id on a live link (default: the autopilot's)
  --telemetry-wait MS        wait this long for telemetry newer than a keyframe and a settled
                             clock (default 1000)
  --telemetry-start-wait MS  live link: wait this long for a first pose before
                             reading video (default 10000; 0 = do not wait)
  --set telemetry.KEY=VALUE  any [telemetry] setting of the daemon (docs/configuration.md),
                             e.g. telemetry.stale_ms=300 (not the keys the options
                             above set)
  --realtime                 deliver frames at the video's own rate, stamped with the
                             monotonic clock, as a camera would
output:
  --out DIR                  where the keyframes go (created; an earlier run's
                             output there is refused, see --overwrite)
  --decisions csv|jsonl      decisions file format (default csv)
  --jpeg-quality Q           1..100 (default 92)
  --max-frames N             stop after N frames
  --progress | --no-progress progress line on stderr (default: when a terminal)
  --quiet                    no summary on stdout
  --overwrite                replace an earlier run's keyframes, decisions and summary
                             in DIR (without it, such a DIR is refused: a keyframe of
                             the old run would pass for one of the new)
recording and streaming:
  --mcap FILE                record decisions, keyframes, calibration and poses to an
                             MCAP file (Foxglove schemas; see docs/formats.md)
  --zenoh-config FILE        publish keyframes on Zenoh (JSON5 zenoh config) under
                             keyframed/<vehicle>/ and serve them by sequence number
  --vehicle NAME             vehicle name in Zenoh keys (default uav)
  -h, --help                 this text
)";
}

// Settings that must agree with each other, named by their options (the defaults
// count too: --target 0.5 alone is under the default band).
std::string checkSelectSettings(const SelectorConfig& c) {
  const auto num = [](double v) {
    char buf[32];
    const auto [end, ec] = std::to_chars(buf, buf + sizeof buf, v);
    return std::string(buf, ec == std::errc() ? end : buf);
  };
  if (c.bandLow > c.target)
    return "--band LO (" + num(c.bandLow) + ") must not exceed --target (" + num(c.target) + ")";
  if (c.target > c.bandHigh)
    return "--target (" + num(c.target) + ") must not exceed --band HI (" + num(c.bandHigh) + ")";
  if (c.minOverlap > c.bandLow)
    return "--min-overlap (" + num(c.minOverlap) + ") must not exceed --band LO (" +
           num(c.bandLow) + ")";
  if (c.overlap.minTracks > c.overlap.maxTracks)
    return "--min-tracks (" + std::to_string(c.overlap.minTracks) +
           ") must not exceed --max-tracks (" + std::to_string(c.overlap.maxTracks) + ")";
  if (c.overlap.minInliers > c.overlap.minTracks)
    return "--min-inliers (" + std::to_string(c.overlap.minInliers) +
           ") must not exceed --min-tracks (" + std::to_string(c.overlap.minTracks) +
           "): tracks are replenished only below it";
  if (c.overlap.paperMinMatches > c.overlap.orbFeatures)
    return "--paper-min-matches (" + std::to_string(c.overlap.paperMinMatches) +
           ") must not exceed --orb-features (" + std::to_string(c.overlap.orbFeatures) + ")";
  if (c.blur.warmup > c.blur.window)
    return "--blur-warmup (" + std::to_string(c.blur.warmup) + ") must not exceed --blur-window (" +
           std::to_string(c.blur.window) + ")";
  if (c.motionRatio > 0.0 && c.motionRatio < 1.0)
    return "--motion-ratio (" + num(c.motionRatio) + ") must be 0 (off) or at least 1";
  // The core's own rules as a last line of defence.
  if (std::string e = c.validate(); !e.empty()) return "selection settings: " + e;
  return {};
}

namespace {

// The options given that the others make pointless, one line each. A flight record's
// mode and blur settings are its own unless given, so only the link's are judged there.
void noEffectWarnings(const SelectOptions& o, const std::set<std::string>& given,
                      std::vector<std::string>& out) {
  const auto warn = [&](std::initializer_list<const char*> options, const std::string& why) {
    for (const char* opt : options) {
      if (given.contains(opt)) out.push_back(std::string(opt) + " has no effect " + why);
    }
  };
  const bool record = isMcapFile(o.video);
  const bool live = !o.telemetry.empty() && !isTlogUrl(o.telemetry);
  if (o.telemetry.empty() && !record) {
    warn({"--mount"}, "without --telemetry (no attitude to turn)");
    warn({"--autopilot"}, "without --telemetry (no link to choose an autopilot on)");
  }
  if (!live) {
    warn({"--telemetry-wait", "--telemetry-start-wait", "--mavlink-sysid"},
         "without a live --telemetry link");
  }
  // Commanded captures come over a live link (or a record's, replayed).
  if (!live && !record) warn({"--capture-wait-ms"}, "without a live --telemetry link");
  if (record) return;
  const SelectorConfig& c = o.selector;
  if (c.overlap.mode == OverlapMode::Geometric) {
    warn({"--orb-features", "--paper-threshold", "--paper-min-matches"},
         "in the geometric mode (--mode paper)");
  } else {
    warn({"--max-tracks", "--min-tracks", "--min-inliers", "--ransac-px", "--fast-threshold",
          "--lk-window", "--lk-levels"},
         "in the paper mode (--mode geometric)");
  }
  if (c.blur.mode == BlurMode::Adaptive) {
    warn({"--blur-threshold"}, "in the adaptive blur mode (--blur-mode absolute)");
  } else {
    warn({"--blur-ratio", "--blur-quantile", "--blur-window", "--blur-warmup"},
         "in the absolute blur mode (--blur-mode adaptive)");
  }
}

}  // namespace

ParseResult parseSelectOptions(const std::vector<std::string>& args, SelectOptions& o) {
  ParseResult r;
  o.args = args;
  auto fail = [&r](std::string msg) {
    r.error = std::move(msg);
    return r;
  };
  SelectorConfig& c = o.selector;
  using Handler = std::function<std::string(const std::string&)>;
  // Ranges come from app/settings.h, shared with the daemon's config file.
  auto number = [](double& dst, SettingRange<double> range) -> Handler {
    return [&dst, range](const std::string& v) -> std::string {
      double d = 0;
      if (!parseDouble(v, d)) return "not a number: '" + v + "'";
      if (!range.contains(d)) return rangeError(range, d);
      dst = d;
      return {};
    };
  };
  auto integer = [](auto& dst, SettingRange<std::int64_t> range) -> Handler {
    return [&dst, range](const std::string& v) -> std::string {
      std::int64_t n = 0;
      if (!parseInt(v, n)) {
        if (errno == ERANGE) return "out of range: '" + v + "'";
        return "not an integer: '" + v + "'";
      }
      if (!range.contains(n)) return rangeError(range, n);
      dst = static_cast<std::remove_reference_t<decltype(dst)>>(n);
      return {};
    };
  };
  auto exifText = [](std::string& dst) -> Handler {
    return [&dst](const std::string& v) -> std::string {
      if (std::string e = exifTextError(v); !e.empty()) return e + " (got '" + v + "')";
      dst = v;
      return {};
    };
  };
  // --set telemetry.KEY=VALUE; the keys this command has options for are set one way.
  auto telemetrySet = [&o](const std::string& v) -> std::string {
    static const std::map<std::string, std::string> kOwnOption = {
        {"telemetry.url", "--telemetry"},
        {"telemetry.autopilot", "--autopilot"},
        {"telemetry.mavlink_sysid", "--mavlink-sysid"},
        {"telemetry.wait_ms", "--telemetry-wait"},
        {"telemetry.start_wait_ms", "--telemetry-start-wait"}};
    if (v.rfind("telemetry.", 0) != 0) {
      return "only [telemetry] keys (telemetry.KEY=VALUE); the other settings have options of "
             "their own (got '" +
             v + "')";
    }
    if (const auto it = kOwnOption.find(v.substr(0, v.find('='))); it != kOwnOption.end()) {
      return it->first + " is set with " + it->second + " here";
    }
    o.telemetrySets.push_back(v);
    return {};
  };
  auto vehicleName = [&o](const std::string& v) -> std::string {
    if (std::string e = vehicleNameError(v); !e.empty())
      return "vehicle name " + e + " (got '" + v + "')";
    o.vehicle = v;
    return {};
  };
  // Settings whose defaults give way to a smaller explicit setting they depend on.
  bool minTracksSet = false;
  bool warmupSet = false;
  auto explicitly = [](bool& set, Handler h) -> Handler {
    return [&set, h = std::move(h)](const std::string& v) {
      set = true;
      return h(v);
    };
  };
  std::set<std::string> given;  // the options with a value that were given
  std::map<std::string, Handler> withValue = {
      {"--out",
       [&](const std::string& v) -> std::string {
         if (v.empty()) return "empty directory";
         o.outDir = v;
         return {};
       }},
      {"--mode",
       [&](const std::string& v) -> std::string {
         if (!parseOverlapMode(v, c.overlap.mode))
           return "unknown mode '" + v + "' (geometric or paper)";
         return {};
       }},
      {"--target", number(c.target, limits::kOverlapTarget)},
      {"--band",
       [&](const std::string& v) -> std::string {
         std::string a, b;
         if (!parsePair(v, a, b)) return "expected LO,HI";
         double lo = 0, hi = 0;
         if (!parseDouble(a, lo) || !parseDouble(b, hi)) return "expected two numbers LO,HI";
         // As the TOML keys: a band of one value (LO = HI = the target) is allowed.
         if (!limits::kOverlapBand.contains(lo) || !limits::kOverlapBand.contains(hi) || lo > hi)
           return "band must satisfy 0.01 <= LO <= HI <= 0.99 (got " + v + ")";
         c.bandLow = lo;
         c.bandHigh = hi;
         return {};
       }},
      {"--analysis-width",
       [&](const std::string& v) -> std::string {
         if (std::string e = integer(c.analysisWidth, limits::kAnalysisWidth)(v); !e.empty())
           return e;
         if (c.analysisWidth > 0 && c.analysisWidth < 64) return "must be 0 (full) or >= 64";
         return {};
       }},
      {"--min-overlap", number(c.minOverlap, limits::kMinOverlap)},
      {"--motion-ratio", number(c.motionRatio, limits::kMotionRatio)},
      {"--motion-min-fraction", number(c.motionMinFraction, limits::kMotionMinFraction)},
      {"--motion-window", integer(c.motionWindow, limits::kMotionWindow)},
      {"--capture-wait-ms", integer(c.captureWaitMs, limits::kCaptureWaitMs)},
      {"--orb-features", integer(c.overlap.orbFeatures, limits::kOrbFeatures)},
      {"--paper-threshold", number(c.overlap.paperThreshold, limits::kPaperThreshold)},
      {"--paper-min-matches", integer(c.overlap.paperMinMatches, limits::kPaperMinMatches)},
      {"--max-tracks", integer(c.overlap.maxTracks, limits::kMaxTracks)},
      {"--min-tracks", explicitly(minTracksSet, integer(c.overlap.minTracks, limits::kMinTracks))},
      {"--min-inliers", integer(c.overlap.minInliers, limits::kMinInliers)},
      {"--ransac-px", number(c.overlap.ransacPixels, limits::kRansacPixels)},
      {"--fast-threshold", integer(c.overlap.fastThreshold, limits::kFastThreshold)},
      {"--lk-window", integer(c.overlap.lkWindow, limits::kLkWindow)},
      {"--lk-levels", integer(c.overlap.lkLevels, limits::kLkLevels)},
      {"--blur-mode",
       [&](const std::string& v) -> std::string {
         if (!parseBlurMode(v, c.blur.mode))
           return "unknown blur mode '" + v + "' (adaptive or absolute)";
         return {};
       }},
      {"--blur-threshold", number(c.blur.absoluteThreshold, limits::kBlurThreshold)},
      {"--blur-floor", number(c.blur.floor, limits::kBlurFloor)},
      {"--blur-ratio", number(c.blur.ratio, limits::kBlurRatio)},
      {"--blur-quantile", number(c.blur.quantile, limits::kBlurQuantile)},
      {"--blur-window", integer(c.blur.window, limits::kBlurWindow)},
      {"--blur-warmup", explicitly(warmupSet, integer(c.blur.warmup, limits::kBlurWarmup))},
      {"--blur-step",
       [&](const std::string& v) -> std::string {
         std::string a, b;
         std::int64_t rs = 0, cs = 0;
         if (!parsePair(v, a, b) || !parseInt(a, rs) || !parseInt(b, cs)) return "expected R,C";
         if (!limits::kBlurStep.contains(rs) || !limits::kBlurStep.contains(cs))
           return "steps must be 1..16";
         c.blur.rowStep = static_cast<int>(rs);
         c.blur.colStep = static_cast<int>(cs);
         return {};
       }},
      {"--blur-width",
       [&](const std::string& v) -> std::string {
         if (std::string e = integer(c.blur.analysisWidth, limits::kBlurWidth)(v); !e.empty())
           return e;
         if (c.blur.analysisWidth > 0 && c.blur.analysisWidth < 32)
           return "must be 0 (full) or >= 32";
         return {};
       }},
      {"--decisions",
       [&](const std::string& v) -> std::string {
         if (v == "csv")
           o.decisions = DecisionFormat::Csv;
         else if (v == "jsonl")
           o.decisions = DecisionFormat::JsonLines;
         else
           return "unknown decisions format '" + v + "' (csv or jsonl)";
         return {};
       }},
      {"--jpeg-quality", integer(o.jpegQuality, limits::kJpegQuality)},
      {"--max-frames", integer(o.maxFrames, SettingRange<std::int64_t>{1, std::int64_t{1} << 40})},
      {"--telemetry",
       [&](const std::string& v) -> std::string {
         if (v.empty()) return "empty telemetry source";
         o.telemetry = v;
         return {};
       }},
      {"--calibration",
       [&](const std::string& v) -> std::string {
         if (v.empty()) return "empty calibration path";
         o.calibration = v;
         return {};
       }},
      {"--set", telemetrySet},
      {"--make", exifText(o.make)},
      {"--model", exifText(o.model)},
      {"--video-start",
       [&](const std::string& v) -> std::string {
         std::int64_t ns = 0;
         if (v == "auto") {
           o.videoStartAuto = true;
           o.videoStartUnixNs.reset();
           return {};
         }
         if (!parseUtcTime(v, ns))
           return "expected a UTC time like 2026-06-01T10:00:00Z, unix seconds or auto, got '" + v +
                  "'";
         o.videoStartUnixNs = ns;
         o.videoStartAuto = false;
         return {};
       }},
      {"--mount",
       [&](const std::string& v) -> std::
                                     string {
                                       if (v == "gimbal") {
                                         o.mountGimbal = true;
                                         return {};
                                       }
                                       o.mountGimbal = false;
                                       double a[3];
                                       std::size_t start = 0;
                                       for (int k = 0; k < 3; ++k) {
                                         const auto comma = v.find(',', start);
                                         if ((k < 2) != (comma != std::string::npos))
                                           return "expected ROLL,PITCH,YAW in degrees or 'gimbal'";
                                         const std::string part = v.substr(
                                             start, comma == std::string::npos ? std::string::npos
                                                                               : comma - start);
                                         if (!parseDouble(part, a[k]) ||
                                             !limits::kMountAngleDeg.contains(a[k]))
                                           return "bad angle '" + part + "'";
                                         start = comma + 1;
                                       }
                                       o.mountRollDeg = a[0];
                                       o.mountPitchDeg = a[1];
                                       o.mountYawDeg = a[2];
                                       return {};
                                     }},
      {"--telemetry-wait", integer(o.telemetryWaitMs, limits::kTelemetryWaitMs)},
      {"--time-offset", number(o.timeOffsetMs, limits::kTimeOffsetMs)},
      {"--telemetry-start-wait", integer(o.telemetryStartWaitMs, limits::kTelemetryStartWaitMs)},
      {"--autopilot",
       [&](const std::string& v)
           -> std::string { return parseAutopilot(v, o.autopilotSystem, o.autopilotComponent); }},
      {"--mavlink-sysid", integer(o.mavlinkSystemId, limits::kOwnSystemId)},
      {"--mcap",
       [&](const std::string& v) -> std::
                                     string {
                                       if (v.empty()) return "empty MCAP path";
                                       o.mcap = v;
                                       return {};
                                     }},
      {"--zenoh-config",
       [&](const std::string& v) -> std::
                                     string {
                                       if (v.empty()) return "empty zenoh config path";
                                       o.zenohConfig = v;
                                       return {};
                                     }},
      {"--vehicle", vehicleName},
  };

  for (std::size_t i = 0; i < args.size(); ++i) {
    std::string a = args[i];
    if (a == "-h" || a == "--help") {
      r.help = true;
      r.ok = true;
      return r;
    }
    if (a == "--progress") {
      o.progress = true;
      continue;
    }
    if (a == "--no-progress") {
      o.progress = false;
      continue;
    }
    if (a == "--quiet") {
      o.quiet = true;
      continue;
    }
    if (a == "--overwrite") {
      o.overwrite = true;
      continue;
    }
    if (a == "--realtime") {
      o.realtime = true;
      continue;
    }
    if (a.rfind("--", 0) == 0) {
      std::string value;
      bool inlineValue = false;
      if (const auto eq = a.find('='); eq != std::string::npos) {
        value = a.substr(eq + 1);
        a = a.substr(0, eq);
        inlineValue = true;
      }
      const auto it = withValue.find(a);
      if (it == withValue.end())
        return fail("unknown option " + a + " (see keyframed select --help)");
      if (!inlineValue) {
        if (i + 1 >= args.size()) return fail("option " + a + " needs a value");
        value = args[++i];
      }
      if (std::string e = it->second(value); !e.empty()) return fail(a + ": " + e);
      given.insert(a);
      continue;
    }
    if (a.size() > 1 && a[0] == '-')
      return fail("unknown option " + a + " (see keyframed select --help)");
    if (!o.video.empty())
      return fail("more than one video given: '" + o.video + "' and '" + a + "'");
    o.video = a;
  }
  if (o.video.empty()) return fail("no video given (usage: keyframed select VIDEO --out DIR)");
  if (o.outDir.empty()) return fail("--out DIR is required");
  relaxDependentDefaults(c, minTracksSet, warmupSet);
  // A flight record's own settings are the base its options go on top of: the replay
  // checks them once it has read the record (checkSelectSettings).
  if (!isMcapFile(o.video)) {
    if (std::string e = checkSelectSettings(c); !e.empty()) return fail(e);
  }
  if (!o.telemetrySets.empty()) {
    const ConfigLoadResult loaded = loadOverrides(o.telemetrySets);
    if (!loaded.ok()) return fail(loaded.errors.front());
  }
  if (!o.telemetry.empty()) {
    std::string e;
    if (!parseMavlinkUrl(o.telemetry, e)) return fail("--telemetry: " + e);
    const bool replay = isTlogUrl(o.telemetry);
    // A flight record replays its own telemetry, on its own clock.
    if (isMcapFile(o.video))
      return fail(
          "a flight record replays the telemetry it recorded (/mavlink/raw), on its own "
          "clock: no --telemetry with it");
    // Without --video-start the video is placed in the tlog by its motion, as `auto`.
    if (replay && !o.videoStartUnixNs && !o.videoStartAuto) o.videoStartAuto = true;
    if (!replay && (o.videoStartUnixNs || o.videoStartAuto))
      return fail(
          "--video-start aligns a video with a tlog; a live link's frames are "
          "stamped as they arrive");
    if (!replay) o.realtime = true;  // a live link runs on the real clock
  } else if (o.videoStartAuto) {
    return fail("--video-start auto lines the video up with a tlog: give --telemetry FILE.tlog");
  }
  noEffectWarnings(o, given, r.warnings);
  r.ok = true;
  return r;
}

}  // namespace keyframed
