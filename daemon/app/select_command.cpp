#include "app/select_command.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <thread>
#include <vector>

#include <opencv2/core/utils/logger.hpp>

#include "app/config.h"
#include "app/decision_log.h"
#include "app/keyframe_output.h"
#include "app/keyframe_stage.h"
#include "app/keyframe_writer.h"
#include "app/log.h"
#include "app/log_to_record.h"
#include "app/mavlink_record.h"
#include "app/paced_source.h"
#include "app/settings.h"
#include "app/telemetry_log.h"
#include "app/text_io.h"
#include "app/video_sync.h"
#include "capture/file_source.h"
#include "output/flight_outputs.h"
#include "output/mcap_replay.h"
#include "tagging/camera_model.h"
#include "tagging/pix4d_fisheye.h"
#include "telemetry/telemetry_service.h"

namespace keyframed {
namespace {

// A run's record of itself in --out: the decisions, the summary, the keyframe list.
bool isRunRecord(const std::string& name) {
  return name == "summary.json" || name == "keyframes.csv" || name == "decisions.csv" ||
         name == "decisions.jsonl";
}

// A keyframe's name: its frame index in six digits or more, ".jpg".
bool isKeyframeName(const std::string& name) {
  if (name.size() < 6 + 4 || name.compare(name.size() - 4, 4, ".jpg") != 0) return false;
  return std::all_of(name.begin(), name.end() - 4, [](char c) { return c >= '0' && c <= '9'; });
}

// What a run's output directory already holds: an earlier run's record and
// keyframes, or, with no record, numbered pictures that are someone else's.
struct EarlierFiles {
  std::vector<std::filesystem::path> files;  // the record's files and the pictures
  bool record = false;                       // a run's record is among them
};

EarlierFiles earlierFiles(const std::string& dir) {
  std::error_code ec;
  EarlierFiles out;
  for (std::filesystem::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string name = it->path().filename().string();
    std::error_code typeEc;
    if (!it->is_regular_file(typeEc)) continue;
    if (isRunRecord(name)) {
      out.record = true;
      out.files.push_back(it->path());
    } else if (isKeyframeName(name)) {
      out.files.push_back(it->path());
    }
  }
  return out;
}

// Whether two paths name one file: the same inode where both exist (a link, another
// spelling), else the same absolute path.
bool samePath(const std::string& a, const std::string& b) {
  namespace fs = std::filesystem;
  std::error_code ec;
  if (fs::equivalent(a, b, ec) && !ec) return true;
  const fs::path ca = fs::weakly_canonical(a, ec);
  if (ec) return false;
  const fs::path cb = fs::weakly_canonical(b, ec);
  return !ec && ca == cb;
}

// The options that shape the tags as the daemon's [tagging] keys a flight record keeps
// (taggingOverrides), and back.
DaemonConfig::Tagging taggingOf(const SelectOptions& o) {
  DaemonConfig::Tagging t;
  t.make = o.make;
  t.model = o.model;
  t.mountGimbal = o.mountGimbal;
  t.mountRollDeg = o.mountRollDeg;
  t.mountPitchDeg = o.mountPitchDeg;
  t.mountYawDeg = o.mountYawDeg;
  return t;
}

void setTagging(SelectOptions& o, const DaemonConfig::Tagging& t, double timeOffsetMs) {
  o.make = t.make;
  o.model = t.model;
  o.mountGimbal = t.mountGimbal;
  o.mountRollDeg = t.mountRollDeg;
  o.mountPitchDeg = t.mountPitchDeg;
  o.mountYawDeg = t.mountYawDeg;
  o.timeOffsetMs = timeOffsetMs;
}

// --mcap names a file the run reads, or one it writes in --out: the record would
// destroy it (a flight record replayed into itself reads nothing and ends "done").
std::string mcapClashes(const SelectOptions& opts) {
  if (opts.mcap.empty()) return {};
  std::vector<std::pair<std::string, const char*>> taken;
  if (isMcapFile(opts.video)) {
    for (const std::string& part : mcapParts(opts.video)) taken.emplace_back(part, "the record");
  }
  taken.emplace_back(opts.video, "the video");
  if (!opts.telemetry.empty()) {
    const std::string t = opts.telemetry;
    taken.emplace_back(t.starts_with("tlog:") ? t.substr(5) : t, "--telemetry");
  }
  if (!opts.calibration.empty()) taken.emplace_back(opts.calibration, "--calibration");
  if (!opts.zenohConfig.empty()) taken.emplace_back(opts.zenohConfig, "--zenoh-config");
  for (const char* name : {"summary.json", "keyframes.csv", "decisions.csv", "decisions.jsonl"})
    taken.emplace_back(opts.outDir + "/" + name, "the run's own output");
  for (const auto& [path, what] : taken) {
    if (samePath(opts.mcap, path))
      return "--mcap " + opts.mcap + " is " + what + " (" + path +
             "): the record would overwrite it; give another file";
  }
  const std::filesystem::path mcap(opts.mcap);
  if (isKeyframeName(mcap.filename().string()) &&
      samePath(mcap.parent_path().empty() ? "." : mcap.parent_path().string(), opts.outDir))
    return "--mcap " + opts.mcap + " has a keyframe's name in --out: a keyframe would " +
           "overwrite the record; give another file";
  return {};
}

std::string earlierRunRefused(const std::string& dir, std::size_t files) {
  return dir + " holds an earlier run's output (" + std::to_string(files) +
         " files: keyframes, decisions, summary): choose another --out, or --overwrite to "
         "replace it";
}

// With --overwrite, the earlier run's files go (other files in `dir` stay).
bool removeEarlierRun(const std::string& dir, std::string& error) {
  std::error_code ec;
  const EarlierFiles earlier = earlierFiles(dir);
  if (!earlier.record) return true;  // someone else's pictures stay
  for (const auto& p : earlier.files) {
    if (!std::filesystem::remove(p, ec) && ec) {
      error = "cannot remove " + p.string() + ": " + ec.message();
      return false;
    }
  }
  return true;
}

bool writeSummary(const std::string& path, const SelectOptions& o, const SourceInfo& info,
                  const SelectSummary& s, std::string& error) {
  std::string tel = "null";
  if (!s.telemetry.source.empty()) {
    tel = formatText(
        "{\n    \"source\": \"%s\",\n    \"geotagged\": %lld,\n"
        "    \"clock\": \"%s\",\n    \"clock_offset_ms\": %s,\n"
        "    \"clock_uncertainty_ms\": %s,\n"
        "    \"record_clock_ahead_ms\": %s,\n"
        "    \"messages\": %llu,\n    \"rejected_frames\": %llu,\n"
        "    \"unknown_ids\": %llu,\n"
        "    \"skipped_bytes\": %llu,\n    \"other_sources\": %llu,\n"
        "    \"gimbal_messages\": %llu,\n    \"bad_samples\": %llu,\n"
        "    \"autopilot_reboots\": %llu,\n"
        "    \"captures_sent\": %llu,\n    \"captures_pending\": %llu,\n"
        "    \"captures_dropped\": %llu,\n    \"captures_resent\": %llu,\n"
        "    \"captures_requested\": %llu,\n    \"captures_refused\": %llu,\n"
        "    \"captures_unserved\": %llu,\n"
        "    \"link_errors\": %llu,\n    \"reconnects\": %llu,\n"
        "    \"truncated\": %s\n  }",
        jsonEscape(s.telemetry.source).c_str(), static_cast<long long>(s.telemetry.geotagged),
        s.telemetry.clock.c_str(), s.telemetry.clockOffsetMs.c_str(),
        s.telemetry.clockUncertaintyMs.c_str(), s.telemetry.recordClockAheadMs.c_str(),
        static_cast<unsigned long long>(s.telemetry.messages),
        static_cast<unsigned long long>(s.telemetry.rejected),
        static_cast<unsigned long long>(s.telemetry.unknownIds),
        static_cast<unsigned long long>(s.telemetry.skippedBytes),
        static_cast<unsigned long long>(s.telemetry.otherSources),
        static_cast<unsigned long long>(s.telemetry.gimbal),
        static_cast<unsigned long long>(s.telemetry.badSamples),
        static_cast<unsigned long long>(s.telemetry.reboots),
        static_cast<unsigned long long>(s.telemetry.capturesSent),
        static_cast<unsigned long long>(s.telemetry.capturesPending),
        static_cast<unsigned long long>(s.telemetry.capturesDropped),
        static_cast<unsigned long long>(s.telemetry.capturesResent),
        static_cast<unsigned long long>(s.telemetry.capturesRequested),
        static_cast<unsigned long long>(s.telemetry.capturesRefused),
        static_cast<unsigned long long>(s.telemetry.capturesUnserved),
        static_cast<unsigned long long>(s.telemetry.linkErrors),
        static_cast<unsigned long long>(s.telemetry.reconnects),
        s.telemetry.truncated ? "true" : "false");
  }
  std::string start = "null";
  if (!s.videoStart.method.empty()) {
    const std::int64_t ns = s.videoStart.unixNs;
    const long long sec = ns >= 0 ? ns / 1'000'000'000 : -((-ns + 999'999'999) / 1'000'000'000);
    const long long frac = ns - sec * 1'000'000'000LL;
    if (s.videoStart.method == "motion") {
      start = formatText(
          "{\"method\": \"motion\", \"unix_s\": %lld.%09lld, \"correlation\": %.3f, "
          "\"runner_up\": %.3f, \"seconds\": %.3f}",
          sec, frac, s.videoStart.correlation, s.videoStart.runnerUp, s.videoStart.seconds);
    } else {
      start = formatText("{\"method\": \"given\", \"unix_s\": %lld.%09lld}", sec, frac);
    }
  }
  const SelectorConfig& c = o.selector;
  const std::string text = formatText(
      "{\n  \"video\": \"%s\",\n  \"width\": %d,\n  \"height\": %d,\n  \"source_fps\": %.3f,\n"
      "  \"frames_read\": %lld,\n  \"kept\": %lld,\n  \"rejected_blur\": %lld,\n"
      "  \"rejected_overlap\": %lld,\n  \"gap_fills\": %lld,\n  \"seconds\": %.3f,\n"
      "  \"frames_per_second\": %.2f,\n  \"analysis_ms_mean\": %.3f,\n  \"truncated\": %s,\n"
      "  \"interrupted\": %s,\n  \"error\": \"%s\",\n  \"record_error\": \"%s\",\n"
      "  \"telemetry\": %s,\n"
      "  \"video_start\": %s,\n"
      "  \"settings\": {\n    \"mode\": \"%s\",\n"
      "    \"target\": %.3f,\n    \"band\": [%.3f, %.3f],\n    \"analysis_width\": %d,\n"
      "    \"blur_mode\": \"%s\",\n    \"blur_threshold\": %.3f,\n    \"blur_floor\": %.3f,\n"
      "    \"blur_ratio\": %.3f,\n    \"blur_quantile\": %.3f,\n    \"blur_window\": %d,\n"
      "    \"blur_step\": [%d, %d],\n    \"blur_width\": %d,\n    \"orb_features\": %d,\n"
      "    \"paper_threshold\": %.3f,\n    \"paper_min_matches\": %d,\n"
      "    \"min_overlap\": %.3f,\n    \"motion_ratio\": %.3f,\n"
      "    \"motion_min_fraction\": %.4f,\n    \"motion_window\": %d,\n"
      "    \"capture_wait_ms\": %d,\n    \"max_tracks\": %d,\n    \"min_tracks\": %d,\n"
      "    \"min_inliers\": %d,\n    \"ransac_px\": %.3f,\n    \"fast_threshold\": %d,\n"
      "    \"lk_window\": %d,\n    \"lk_levels\": %d,\n    \"blur_warmup\": %d\n  }\n}\n",
      jsonEscape(o.video).c_str(), info.width, info.height, info.fps,
      static_cast<long long>(s.framesRead), static_cast<long long>(s.kept),
      static_cast<long long>(s.rejectedBlur), static_cast<long long>(s.rejectedOverlap),
      static_cast<long long>(s.promoted), s.seconds, s.framesPerSecond, s.analysisMsMean,
      s.truncated ? "true" : "false", s.interrupted ? "true" : "false", jsonEscape(s.error).c_str(),
      jsonEscape(s.recordError).c_str(), tel.c_str(), start.c_str(), toString(c.overlap.mode),
      c.target, c.bandLow, c.bandHigh, c.analysisWidth,
      c.blur.mode == BlurMode::Adaptive ? "adaptive" : "absolute", c.blur.absoluteThreshold,
      c.blur.floor, c.blur.ratio, c.blur.quantile, c.blur.window, c.blur.rowStep, c.blur.colStep,
      c.blur.analysisWidth, c.overlap.orbFeatures, c.overlap.paperThreshold,
      c.overlap.paperMinMatches, c.minOverlap, c.motionRatio, c.motionMinFraction, c.motionWindow,
      c.captureWaitMs, c.overlap.maxTracks, c.overlap.minTracks, c.overlap.minInliers,
      c.overlap.ransacPixels, c.overlap.fastThreshold, c.overlap.lkWindow, c.overlap.lkLevels,
      c.blur.warmup);
  return writeFileAtomically(path, std::string_view(text), error);
}

std::atomic<bool> gStop{false};
// Set while the video is being opened: an open can block for good (a FIFO that no
// writer opens, a stalled network mount), and nothing is written yet to flush.
std::atomic<bool> gOpening{false};
extern "C" void onSignal(int) {
  // A signal while opening, or a second one (something blocks): out at once.
  if (gStop.exchange(true) || gOpening.load()) ::_exit(130);
}

// Marks the opening of the video for the signal handler.
struct OpeningScope {
  OpeningScope() { gOpening.store(true); }
  ~OpeningScope() { gOpening.store(false); }
  OpeningScope(const OpeningScope&) = delete;
  OpeningScope& operator=(const OpeningScope&) = delete;
};

}  // namespace

SelectSummary runSelection(const SelectOptions& given, const ProgressFn& progress,
                           const std::atomic<bool>* stop) {
  SelectOptions opts = given;
  SelectSummary s;
  cv::utils::logging::setLogLevel(cv::utils::logging::LOG_LEVEL_ERROR);
  std::string error;
  if (auto clash = mcapClashes(opts); !clash.empty()) {
    s.error = std::move(clash);
    return s;
  }
  // Said before any work: an earlier run's keyframes would mix with this run's, and
  // so would someone else's numbered pictures (one a keyframe's name would replace).
  if (const EarlierFiles earlier = earlierFiles(opts.outDir); earlier.record && !opts.overwrite) {
    s.error = earlierRunRefused(opts.outDir, earlier.files.size());
    return s;
  } else if (!earlier.files.empty() && !opts.overwrite) {
    s.error = opts.outDir + " holds " + std::to_string(earlier.files.size()) +
              " picture(s) named as keyframes are (six digits, .jpg) but no run's record: "
              "they would mix with this run's keyframes, or be replaced by one; choose another "
              "--out, or --overwrite to run there anyway (they stay unless a keyframe takes "
              "the name)";
    return s;
  }
  // A video file, or a flight record (MCAP from `keyframed run`) to replay.
  std::unique_ptr<FrameSource> source;
  FileSource* file = nullptr;
  McapReplaySource* replay = nullptr;
  std::optional<CameraModel> calibrated;  // --calibration, read once for both passes
  if (!opts.calibration.empty()) {
    CameraModel model;
    if (!loadCameraModel(opts.calibration, model, error)) {
      s.error = error;
      return s;
    }
    calibrated = model;
  }
  if (opts.videoStartAuto && !isMcapFile(opts.video)) {
    // Where the video sits in the tlog, from the motion both recorded: a pass over the
    // video first.
    VideoSyncRequest req;
    req.video = opts.video;
    req.link = loadOverrides(opts.telemetrySets).config.telemetry.link;
    req.link.url = opts.telemetry;
    req.link.decoder.autopilotSystem = opts.autopilotSystem;
    req.link.decoder.autopilotComponent = opts.autopilotComponent;
    req.mount = {opts.mountRollDeg, opts.mountPitchDeg, opts.mountYawDeg, opts.mountGimbal};
    req.analysisWidth = opts.selector.analysisWidth;
    req.camera = calibrated;
    req.hint =
        "check --mount (the camera's angles on the vehicle: an oblique camera's turns "
        "differ from a nadir one's) or give --video-start TIME";
    if (!opts.quiet)
      std::fprintf(stderr, "placing the video in %s by its motion...\n", opts.telemetry.c_str());
    // Its open may block too, and nothing is written before it ends: a signal then
    // ends the command at once.
    std::optional<OpeningScope> placing(std::in_place);
    const VideoSync sync = syncVideoWithTlog(req, stop);
    placing.reset();
    if (stop != nullptr && stop->load()) {  // Ctrl-C: interrupted, not failed
      s.interrupted = true;
      return s;
    }
    if (!sync.ok) {
      s.error = sync.error;
      return s;
    }
    // The motion places the frames where they were exposed: the camera's latency
    // (--time-offset), added again at tagging, is taken out here.
    opts.videoStartUnixNs =
        sync.videoStartUnixNs - static_cast<std::int64_t>(std::llround(opts.timeOffsetMs * 1e6));
    s.videoStart.method = "motion";
    s.videoStart.correlation = sync.match.correlation;
    s.videoStart.runnerUp = sync.match.runnerUp;
    s.videoStart.seconds = sync.seconds;
    if (!opts.quiet) {
      std::fprintf(stderr,
                   "video start %s UTC (unix %.3f): correlation %.2f, next best %.2f, "
                   "%lld of %lld frames turned measurably, %.1f s\n",
                   formatUtcIso(sync.videoStartUnixNs).c_str(),
                   static_cast<double>(sync.videoStartUnixNs) / 1e9, sync.match.correlation,
                   sync.match.runnerUp, static_cast<long long>(sync.turnsKnown),
                   static_cast<long long>(sync.frames), sync.seconds);
      if (*opts.videoStartUnixNs != sync.videoStartUnixNs)
        std::fprintf(stderr, "container time 0 at %s on the camera's clock (--time-offset)\n",
                     formatUtcIso(*opts.videoStartUnixNs).c_str());
    }
  } else if (opts.videoStartUnixNs) {
    s.videoStart.method = "given";
  }
  if (opts.videoStartUnixNs) s.videoStart.unixNs = *opts.videoStartUnixNs;
  std::optional<OpeningScope> opening(std::in_place);
  if (isMcapFile(opts.video)) {
    auto r = McapReplaySource::open(opts.video, error);
    replay = r.get();
    source = std::move(r);
  } else {
    auto f = FileSource::open(opts.video, error);
    file = f.get();
    // The frame's time on the telemetry's clock: as a camera stamps it (realtime),
    // or the container time from --video-start (a tlog's unix times).
    if (f && (opts.realtime || opts.videoStartUnixNs)) {
      source = std::make_unique<PacedSource>(std::move(f), opts.realtime, opts.videoStartUnixNs);
    } else {
      source = std::move(f);
    }
  }
  opening.reset();
  if (!source) {
    s.error = error;
    return s;
  }
  bool overRecord = false;  // the selector is the record's settings + the options
  if (replay != nullptr && !replay->selectionSettings().empty()) {
    // Select as the flight did: its settings, with the selection options given here on
    // top of them.
    const ConfigLoadResult r = loadSelectionOverrides(replay->selectionSettings());
    SelectOptions recorded;
    recorded.selector = r.config.selection;
    if (!r.ok()) {
      std::fprintf(stderr,
                   "keyframed select: warning: the record's selection settings do not load "
                   "(%s): replaying with the defaults and the options given\n",
                   r.errors.front().c_str());
    } else if (!opts.args.empty() || !opts.selectorGiven) {
      if (!opts.args.empty()) {
        // The options again, now over the record's settings (they parsed once
        // already; their agreement with these settings is checked below).
        if (const ParseResult again = parseSelectOptions(opts.args, recorded); !again.ok) {
          s.error = again.error;
          s.badOptions = true;
          return s;
        }
      }
      opts.selector = recorded.selector;
      overRecord = true;
      if (replay->settingsChanges() > 0) {
        std::fprintf(stderr,
                     "keyframed select: warning: the selection settings changed %d time(s) "
                     "during the flight (reloads): replaying with those it started with\n",
                     replay->settingsChanges());
      }
    }
  }
  if (replay != nullptr && !replay->taggingSettings().empty()) {
    // Tag as the flight did (EXIF make and model, the camera mount), the options given
    // here on top.
    const ConfigLoadResult r = loadTaggingOverrides(replay->taggingSettings());
    if (!r.ok()) {
      std::fprintf(stderr,
                   "keyframed select: warning: the record's tagging settings do not load (%s): "
                   "tagging with the defaults and the options given\n",
                   r.errors.front().c_str());
    } else {
      SelectOptions recorded;
      setTagging(recorded, r.config.tagging, r.config.camera.timeOffsetMs);
      if (!opts.args.empty()) {
        if (const ParseResult again = parseSelectOptions(opts.args, recorded); !again.ok) {
          s.error = again.error;
          s.badOptions = true;
          return s;
        }
      }
      setTagging(opts, taggingOf(recorded), recorded.timeOffsetMs);
    }
  }
  if (replay != nullptr && replay->selectionSettings().empty()) {
    std::fprintf(stderr,
                 "keyframed select: warning: the record does not say which selection settings "
                 "the flight used (a record from before they were recorded in every part?): "
                 "replaying with the defaults and the options given\n");
  }
  if (replay != nullptr && !opts.selectorGiven) {
    if (std::string e = checkSelectSettings(opts.selector); !e.empty()) {
      s.error = e + (overRecord ? " (over the record's settings)" : "");
      s.badOptions = true;
      return s;
    }
  }
  if (replay != nullptr && (opts.realtime || opts.videoStartUnixNs || opts.videoStartAuto)) {
    s.error =
        "a flight record replays on its own recorded clock: no --realtime or "
        "--video-start with it";
    s.badOptions = true;
    return s;
  }
  std::optional<CameraModel> camera;
  if (calibrated) {
    camera = calibrated;
  } else if (replay != nullptr && replay->camera()) {
    camera = replay->camera();  // the camera model the flight was tagged with
  } else if (replay != nullptr && replay->calibration()) {
    camera = replay->calibration();  // the intrinsics the flight was recorded with
  } else if (!opts.telemetry.empty()) {
    std::fprintf(stderr,
                 "keyframed select: warning: no --calibration: keyframes carry position and "
                 "attitude but no intrinsics\n");
  }
  if (camera) {
    const std::string w = camera->aspectMismatch(source->info().width, source->info().height);
    if (!w.empty()) {
      std::fprintf(stderr, "keyframed select: warning: %s\n", w.c_str());
      camera = camera->withoutIntrinsics();
    }
    const std::string size = camera->physicalSizeWarning();
    if (!size.empty() && !calibrated && replay != nullptr && !replay->camera()) {
      // The record's CameraCalibration holds pixels only (K, D), no sensor size (a
      // record from before the settings kept the whole camera model).
      std::fprintf(stderr,
                   "keyframed select: warning: the flight record's calibration is in pixels "
                   "only (no sensor size, make or model): give --calibration with the file the "
                   "flight used to tag the keyframes with all of it\n");
    } else if (!size.empty()) {
      std::fprintf(stderr, "keyframed select: warning: %s\n", size.c_str());
    }
    const std::string lens = camera->lensWarning();
    if (!lens.empty()) std::fprintf(stderr, "keyframed select: warning: %s\n", lens.c_str());
    const std::string pix4d = pix4dFisheyeWarning(*camera);
    if (!pix4d.empty()) std::fprintf(stderr, "keyframed select: warning: %s\n", pix4d.c_str());
  }
  // Too small to analyse (a strip of a few rows, a thumbnail): said before any output,
  // not an OpenCV exception part-way.
  if (const std::string small = tooSmallToAnalyse(source->info().width, source->info().height,
                                                  opts.selector.analysisWidth);
      !small.empty()) {
    s.error = opts.video + ": " + small + ", --analysis-width";
    return s;
  }
  if (const std::string large = tooLargeToAnalyse(source->info().width, source->info().height);
      !large.empty()) {
    s.error = opts.video + ": " + large;
    return s;
  }
  std::error_code ec;
  if (opts.overwrite && !removeEarlierRun(opts.outDir, s.error)) return s;
  std::filesystem::create_directories(opts.outDir, ec);
  if (ec || !std::filesystem::is_directory(opts.outDir, ec)) {
    s.error = "cannot create output directory " + opts.outDir;
    return s;
  }
  const std::string ext = opts.decisions == DecisionFormat::Csv ? "csv" : "jsonl";
  s.decisionsPath = opts.outDir + "/decisions." + ext;
  s.summaryPath = opts.outDir + "/summary.json";

  // Telemetry: a tlog is read whole now; a live link gets its own thread. The
  // daemon's [telemetry] settings (--set) first, this command's options on top.
  const DaemonConfig::Telemetry telemetrySettings =
      loadOverrides(opts.telemetrySets).config.telemetry;
  std::unique_ptr<TelemetryService> telemetry;
  CaptureRequests captureRequests;  // MAVLink (telemetry thread) -> this loop
  if (replay != nullptr && opts.telemetry.empty() && !replay->mavlink().empty()) {
    // The flight record's own MAVLink stream, with its arrival times: the frames'
    // timestamps are on the same clock.
    TelemetryServiceConfig tc = telemetrySettings.link;
    tc.url.clear();
    tc.decoder.autopilotSystem = opts.autopilotSystem;
    tc.decoder.autopilotComponent = opts.autopilotComponent;
    telemetry = std::make_unique<TelemetryService>(tc, CameraDescription{});
    // A record made from a tlog keeps the tlog's unix times as its frames' (no offset
    // between log and frame times): that clock is UTC, as it was for the tlog.
    telemetry->startFromPackets(replay->mavlink(), replay->unixOffsetNs() == 0);
    s.telemetry.source = opts.video + " (/mavlink/raw)";
  } else if (!opts.telemetry.empty()) {
    TelemetryServiceConfig tc = telemetrySettings.link;
    tc.url = opts.telemetry;
    tc.systemId = opts.mavlinkSystemId;
    tc.decoder.autopilotSystem = opts.autopilotSystem;
    tc.decoder.autopilotComponent = opts.autopilotComponent;
    CameraDescription cd;
    cd.width = source->info().width;
    cd.height = source->info().height;
    if (camera) {
      if (!camera->make.empty()) cd.vendor = camera->make;  // else the component's own
      if (!camera->model.empty()) cd.model = camera->model;
      cd.focalLengthMm = static_cast<float>(camera->focalLengthMm);
      cd.sensorWidthMm = static_cast<float>(camera->sensorWidthMm);
      cd.sensorHeightMm = static_cast<float>(camera->sensorHeightMm);
    }
    // CAMERA_INFORMATION names the camera as the keyframes' EXIF does (--make, --model).
    if (!opts.make.empty()) cd.vendor = opts.make;
    if (!opts.model.empty()) cd.model = opts.model;
    telemetry = std::make_unique<TelemetryService>(tc, cd);
    telemetry->setGimbalMount(opts.mountGimbal);  // a live link: ask for its attitude too
    logTelemetryEvents(*telemetry);
    // MAV_CMD_IMAGE_START_CAPTURE: the next sharp frame is a keyframe.
    telemetry->setCaptureRequestSink(
        [&captureRequests](bool intervalTick) { return captureRequests.add(intervalTick); });
    if (!telemetry->start(error)) {
      s.error = error;
      return s;
    }
    s.telemetry.source = opts.telemetry;
    if (!telemetry->isReplay() && opts.telemetryStartWaitMs > 0) {
      // A camera that starts before the autopilot is heard would take its first
      // keyframes untagged: give the link a moment to deliver a first pose.
      if (!opts.quiet)
        std::fprintf(stderr, "waiting for telemetry on %s\n", opts.telemetry.c_str());
      const std::int64_t deadline = monotonicNowNs() + opts.telemetryStartWaitMs * 1'000'000LL;
      while (!telemetry->decoder().hasPose() && monotonicNowNs() < deadline &&
             (stop == nullptr || !stop->load())) {
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
      }
      if (!telemetry->decoder().hasPose()) {
        std::fprintf(stderr,
                     "keyframed: warning: no attitude and position from %s after %d ms; "
                     "keyframes are tagged when telemetry arrives\n",
                     opts.telemetry.c_str(), opts.telemetryStartWaitMs);
      }
    }
  }

  DecisionLog log;
  if (!log.open(s.decisionsPath, opts.decisions, error)) {
    s.error = error;
    return s;
  }
  KeyframeWriter writer;
  {
    KeyframeWriterConfig wc;
    wc.dir = opts.outDir;
    wc.quality = opts.jpegQuality;
    wc.camera = camera;
    wc.make = opts.make;
    wc.model = opts.model;
    wc.mount = {opts.mountRollDeg, opts.mountPitchDeg, opts.mountYawDeg, opts.mountGimbal};
    if (!writer.open(wc, error)) {
      s.error = error;
      return s;
    }
  }
  FlightOutputs outputs;  // --mcap, --zenoh-config
  FlightOutputOptions fo;
  fo.mcapPath = opts.mcap;
  // A replay's record carries the preview stream again: images, stored as they are
  // (as `run` stores them); otherwise decisions, MAVLink and keyframes, zstd.
  fo.mcapCompression = replay != nullptr ? "none" : "zstd";
  fo.zenohConfig = opts.zenohConfig;
  fo.vehicle = opts.vehicle;
  // A flight id of its own (the run's start, UTC to the ms): sequence numbers start at
  // 0 in every run, and a ground station that heard an earlier run of this vehicle
  // keeps the two apart rather than taking this one's keyframes for duplicates.
  fo.flight = formatUtcCompact(unixNowNs(), true);
  fo.keyframeDir = opts.outDir;
  fo.offline = !opts.realtime;
  // The record's log times in unix time: --video-start times (with a tlog, paced in
  // real time or not) are unix already; frames paced in real time are on
  // CLOCK_MONOTONIC; a replay keeps the original flight's times; plain container
  // times count from the start of this run.
  if (opts.videoStartUnixNs) {
    fo.startNs = *opts.videoStartUnixNs;
  } else if (opts.realtime) {
    fo.liveClock = true;
  } else if (replay != nullptr) {
    fo.unixOffsetNs = replay->unixOffsetNs();
    fo.startNs = replay->firstTimeNs();
  } else {
    fo.unixOffsetNs = unixNowNs();
  }
  fo.warn = [](const std::string& m) { KF_LOG(Output, Warning) << m; };
  fo.error = [](const std::string& m) { KF_LOG(Output, Error) << m; };
  fo.note = [](const std::string& m) { KF_LOG(Output, Notice) << m; };
  if (!outputs.open(fo, source->info().width, source->info().height, camera ? &*camera : nullptr,
                    error)) {
    s.error = error;
    // Nothing was selected: the empty lists go, or the same command, corrected, would
    // be refused for an earlier run's output. (Open files: unlinked, they write nowhere.)
    std::error_code removeEc;
    std::filesystem::remove(s.decisionsPath, removeEc);
    std::filesystem::remove(opts.outDir + "/keyframes.csv", removeEc);
    return s;
  }
  const LogToRecord logToRecord(outputs);
  outputs.tagging(taggingOverrides(taggingOf(opts), opts.timeOffsetMs),
                  camera ? &*camera : nullptr);
  outputs.settings(fo.liveClock ? monotonicNowNs() : fo.startNs, selectionOverrides(opts.selector));

  KeyframeOutput output(writer, log, outputs, telemetry.get(), opts.telemetryWaitMs,
                        telemetrySettings.link.decoder.store, opts.timeOffsetMs);
  if (telemetry) recordLiveMavlink(*telemetry, outputs);
  bool outputFailed = false;

  MonotonicClock clock;
  // The geometric overlap is measured through the calibrated lens.
  SelectorConfig selector = opts.selector;
  if (camera) selector.overlap.lens = camera->lensModel();
  KeyframeStage stage(selector, &clock, [&](KeyframeEvent&& ev) {
    if (!outputFailed && !output.handle(ev, error)) {
      outputFailed = true;
      s.error = error;
    }
  });

  // The record of an offline run carries its telemetry on (a tlog's packets, or a
  // replayed record's), and a replay's the preview stream too, in time order with the
  // frames, so that it can be replayed in its turn.
  std::optional<MavlinkRecord> mavlinkRecord;
  if (telemetry && telemetry->isReplay() && outputs.recording())
    mavlinkRecord.emplace(outputs, telemetry->decoder());
  std::size_t nextPacket = 0;
  const auto rerecordMavlink = [&](std::int64_t upToNs) {
    if (!mavlinkRecord) return;
    telemetry->advanceReplay(upToNs);  // the autopilot it follows known as in the run
    const auto& packets = telemetry->replayPackets();
    for (; nextPacket < packets.size() && packets[nextPacket].timeNs <= upToNs; ++nextPacket)
      mavlinkRecord->packet(packets[nextPacket]);
  };
  const auto start = std::chrono::steady_clock::now();
  auto lastProgress = start;
  std::optional<std::int64_t> firstFrameNs;
  std::int64_t lastFrameNs = 0;
  Frame frame;
  while (true) {
    if (stop != nullptr && stop->load()) {
      s.interrupted = true;
      break;
    }
    if (opts.maxFrames > 0 && s.framesRead >= opts.maxFrames) {
      s.interrupted = true;
      break;
    }
    const ReadStatus st = source->next(frame, error);
    if (st == ReadStatus::End) {
      // A record cut short (a power cut before its repair) or corrupt part-way: what
      // came before the break was replayed, and it is said, as for a cut video.
      if (replay != nullptr && replay->truncated()) {
        s.truncated = true;
        s.error = opts.video + ": the record ends early (cut short or corrupt): replayed the " +
                  std::to_string(s.framesRead) + " frames before the break";
      }
      break;
    }
    if (st == ReadStatus::Error) {
      s.error = error;
      s.truncated = file != nullptr && file->truncated();
      break;
    }
    if (!firstFrameNs) firstFrameNs = frame.timestampNs;
    lastFrameNs = frame.timestampNs;
    rerecordMavlink(frame.timestampNs);
    if (replay != nullptr && outputs.recording())
      outputs.preview(frame.timestampNs, replay->encoded(), replay->format().c_str());
    if (const int refused = captureRequests.drainInto(stage); refused > 0)
      std::fprintf(stderr, "%d requested capture(s) refused: %d already wait\n", refused,
                   KeyframeSelector::kMaxCaptureRequests);
    // A photograph the autopilot asked for in flight is asked for again at the frame
    // that answered it (a request the live run waited on is served by that frame).
    if (replay != nullptr && replay->commanded()) (void)stage.requestCapture();
    stage.process(frame);
    captureRequests.noteServed(stage);
    s.framesRead = stage.counts().framesRead;
    s.kept = stage.counts().kept;
    if (outputFailed) break;
    outputs.progress(s.framesRead, s.kept);
    const auto now = std::chrono::steady_clock::now();
    if (progress && now - lastProgress > std::chrono::milliseconds(250)) {
      lastProgress = now;
      const double el = std::chrono::duration<double>(now - start).count();
      progress(s.framesRead, source->info().frameCount, s.kept,
               el > 0 ? static_cast<double>(s.framesRead) / el : 0.0);
    }
  }
  // The end of the flight needs covering too: keep the pending candidate.
  // (also after a read error: the video up to the break is covered; not after
  // an output error, which is already the run's failure)
  if (!outputFailed) stage.finish();
  if (const int unserved = captureRequests.close(stage); unserved > 0) {
    s.telemetry.capturesUnserved = static_cast<std::uint64_t>(unserved);
    std::fprintf(stderr,
                 "keyframed select: warning: %d capture(s) asked for over MAVLink not taken: the "
                 "video ended before a usable frame came\n",
                 unserved);
  }
  rerecordMavlink(INT64_MAX);
  {
    const StageCounts& c = stage.counts();
    s.framesRead = c.framesRead;
    s.kept = c.kept;
    s.rejectedBlur = c.rejectedBlur;
    s.rejectedOverlap = c.rejectedOverlap;
    s.promoted = c.promoted;
  }
  if (!log.close(error) && s.error.empty()) s.error = error;
  if (!writer.close(error) && s.error.empty()) s.error = error;
  // A recorder that failed has said so; the keyframes are what must not be lost.
  if (telemetry) telemetry->setRawSink({});
  if (std::string recordError; !outputs.close(
          !s.error.empty() ? "failed" : (s.interrupted ? "interrupted" : "done"), recordError))
    s.recordError = recordError;
  if (telemetry) {
    // Let the telemetry thread send the last CAMERA_IMAGE_CAPTURED reports.
    if (!telemetry->isReplay()) std::this_thread::sleep_for(std::chrono::milliseconds(200));
    telemetry->stop();
    const TelemetryServiceStats ts = telemetry->stats();
    s.telemetry.geotagged = writer.geotagged();
    s.telemetry.clock = toString(telemetry->decoder().clockSource());
    if (const auto off = telemetry->decoder().clockOffsetNs())
      s.telemetry.clockOffsetMs = formatText("%.3f", static_cast<double>(*off) / 1e6);
    if (const double within = telemetry->decoder().clockUncertaintyMs(); !std::isnan(within))
      s.telemetry.clockUncertaintyMs = formatText("%.3f", within);
    if (const auto ahead = telemetry->decoder().recordClockAheadNs()) {
      const double ms = static_cast<double>(*ahead) / 1e6;
      s.telemetry.recordClockAheadMs = formatText("%.3f", ms);
      // Radio latency is tens of ms; beyond half a second the recording station's
      // clock was off, and the frames were placed by the autopilot's GPS time.
      if (std::fabs(ms) > 500.0) {
        std::fprintf(stderr,
                     "keyframed select: warning: the tlog's record times run %.3f s %s the "
                     "autopilot's GPS time (SYSTEM_TIME); the video (--video-start, UTC) was "
                     "placed by GPS time\n",
                     std::fabs(ms) / 1e3, ms > 0 ? "ahead of" : "behind");
      }
    }
    s.telemetry.messages = ts.parser.messages;
    s.telemetry.rejected = ts.parser.rejected;
    s.telemetry.unknownIds = ts.parser.unknownIds;
    s.telemetry.skippedBytes = ts.parser.skippedBytes;
    s.telemetry.otherSources = ts.decoder.otherSources;
    s.telemetry.gimbal = ts.decoder.gimbal;
    s.telemetry.badSamples = ts.decoder.badAttitudes + ts.decoder.badPositions;
    s.telemetry.reboots = ts.decoder.reboots;
    s.telemetry.capturesSent = ts.capturesSent;
    s.telemetry.capturesPending = ts.capturesPending;
    s.telemetry.capturesDropped = ts.capturesDropped;
    s.telemetry.capturesResent = ts.capturesResent;
    s.telemetry.capturesRequested = ts.captureRequests;
    s.telemetry.capturesRefused = ts.captureRefused;
    s.telemetry.linkErrors = ts.linkErrors;
    s.telemetry.reconnects = ts.reconnects;
    s.telemetry.truncated = ts.truncated;
    // A tlog that does not cover the video at all: a wrong --video-start (local time
    // taken for UTC, another day), or another flight's log. Every keyframe is written,
    // none could be tagged: a failure of what was asked for, said with the two spans.
    const auto& packets = telemetry->replayPackets();
    if (replay == nullptr && telemetry->isReplay() && firstFrameNs && !packets.empty() &&
        s.kept > 0 && s.telemetry.geotagged == 0 && s.error.empty()) {
      const std::int64_t ahead = telemetry->decoder().recordClockAheadNs().value_or(0);
      const std::int64_t tlogFirst = packets.front().timeNs - ahead;
      const std::int64_t tlogLast = packets.back().timeNs - ahead;
      if (lastFrameNs < tlogFirst || *firstFrameNs > tlogLast) {
        s.error = "no keyframe could be geotagged: the video (" + formatUtcIso(*firstFrameNs) +
                  " to " + formatUtcIso(lastFrameNs) + ") lies outside the tlog's telemetry (" +
                  formatUtcIso(tlogFirst) + " to " + formatUtcIso(tlogLast) +
                  "): check --video-start (UTC; a time without a zone is taken as UTC), or "
                  "use --video-start auto";
      } else if (telemetry->decoder().autopilotSinceNs() == INT64_MAX &&
                 s.telemetry.otherSources > 0) {
        // Messages, but none from the autopilot followed: the one --autopilot names is
        // not in the tlog, or no HEARTBEAT says which sender flies.
        if (opts.autopilotSystem > 0) {
          std::string which = std::to_string(opts.autopilotSystem);
          if (opts.autopilotComponent > 0) {
            which += ':';
            which += std::to_string(opts.autopilotComponent);
          }
          std::fprintf(stderr,
                       "keyframed select: warning: none of the %lld keyframes was geotagged: "
                       "the tlog has no autopilot %s (--autopilot); its %llu messages are "
                       "other senders'\n",
                       static_cast<long long>(s.kept), which.c_str(),
                       static_cast<unsigned long long>(s.telemetry.otherSources));
        } else {
          std::fprintf(stderr,
                       "keyframed select: warning: none of the %lld keyframes was geotagged: "
                       "the tlog names no autopilot (no HEARTBEAT of one), so its %llu "
                       "messages were not taken as the vehicle's; give --autopilot SYS[:COMP]\n",
                       static_cast<long long>(s.kept),
                       static_cast<unsigned long long>(s.telemetry.otherSources));
        }
      } else {
        std::fprintf(stderr,
                     "keyframed select: warning: none of the %lld keyframes was geotagged; why: "
                     "the geotag column of %s/keyframes.csv\n",
                     static_cast<long long>(s.kept), opts.outDir.c_str());
      }
    }
  }
  if (file != nullptr && file->repeatedFrom() >= 0) {
    std::fprintf(stderr,
                 "keyframed select: warning: frames %lld to %lld (%lld) repeat one picture: a "
                 "still, or a video whose frame size changes part-way (OpenCV's reader then "
                 "hands back the last picture of the first size, and the rest of the video "
                 "is not seen)\n",
                 static_cast<long long>(file->repeatedFrom()),
                 static_cast<long long>(file->repeatedFrom() + file->repeatedFrames() - 1),
                 static_cast<long long>(file->repeatedFrames()));
  }
  s.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  s.framesPerSecond = s.seconds > 0 ? static_cast<double>(s.framesRead) / s.seconds : 0.0;
  s.analysisMsMean =
      s.framesRead > 0 ? stage.counts().analysisNs / static_cast<double>(s.framesRead) / 1e6 : 0.0;
  if (progress) progress(s.framesRead, source->info().frameCount, s.kept, s.framesPerSecond);
  if (!writeSummary(s.summaryPath, opts, source->info(), s, error) && s.error.empty())
    s.error = error;
  return s;
}

int selectMain(const std::vector<std::string>& args) {
  SelectOptions opts;
  const ParseResult pr = parseSelectOptions(args, opts);
  if (!pr.ok) {
    std::fprintf(stderr, "keyframed select: %s\n", oneLine(pr.error).c_str());
    return 2;
  }
  if (pr.help) {
    std::fputs(selectUsage().c_str(), stdout);
    return 0;
  }
  for (const std::string& w : pr.warnings)
    std::fprintf(stderr, "keyframed select: warning: %s\n", w.c_str());
  std::signal(SIGINT, onSignal);
  std::signal(SIGTERM, onSignal);
  const bool showProgress = opts.progress.value_or(isatty(STDERR_FILENO) != 0);
  ProgressFn progress;
  if (showProgress) {
    progress = [](std::int64_t n, std::int64_t total, std::int64_t kept, double fps) {
      if (total > 0)
        std::fprintf(stderr, "\r  frame %lld/%lld  kept %lld  %.1f fps   ",
                     static_cast<long long>(n), static_cast<long long>(total),
                     static_cast<long long>(kept), fps);
      else
        std::fprintf(stderr, "\r  frame %lld  kept %lld  %.1f fps   ", static_cast<long long>(n),
                     static_cast<long long>(kept), fps);
      std::fflush(stderr);
    };
  }
  const SelectSummary s = runSelection(opts, progress, &gStop);
  if (showProgress) std::fputs("\n", stderr);
  if (!opts.quiet && s.framesRead > 0) {
    std::printf(
        "frames read %lld, kept %lld (gap fills %lld), rejected: blur %lld, overlap %lld; "
        "%.1f frames/s (selection %.2f ms/frame)\n"
        "keyframes: %s/\ndecisions: %s\nsummary:   %s\n",
        static_cast<long long>(s.framesRead), static_cast<long long>(s.kept),
        static_cast<long long>(s.promoted), static_cast<long long>(s.rejectedBlur),
        static_cast<long long>(s.rejectedOverlap), s.framesPerSecond, s.analysisMsMean,
        opts.outDir.c_str(), s.decisionsPath.c_str(), s.summaryPath.c_str());
    if (!s.telemetry.source.empty()) {
      std::printf("geotagged %lld of %lld keyframes (clock: %s)%s%s%s\n",
                  static_cast<long long>(s.telemetry.geotagged), static_cast<long long>(s.kept),
                  s.telemetry.clock.c_str(),
                  s.telemetry.geotagged < s.kept ? "; why not: see the geotag column of " : "",
                  s.telemetry.geotagged < s.kept ? opts.outDir.c_str() : "",
                  s.telemetry.geotagged < s.kept ? "/keyframes.csv" : "");
    }
  }
  if (!s.error.empty()) {
    std::fprintf(stderr, "keyframed select: %s\n", s.error.c_str());
    return s.badOptions ? 2 : 3;
  }
  if (gStop.load()) return 130;
  return 0;
}

}  // namespace keyframed
