// `keyframed run`: the live daemon. Threads as in docs/design.md:
//   capture  (CaptureThread: source -> pooled copy -> bounded queue, drops the oldest)
//   analysis (KeyframeStage: selector; never blocks capture)
//   output   (KeyframeOutput: tags, writes, logs, records, publishes; never drops a keyframe)
//   telemetry (TelemetryService: MAVLink link, pose history, camera protocol)
//   main     (signals, systemd notify, watchdog, status, SIGHUP reload)
#include "app/run_command.h"

#include <pthread.h>
#include <sys/resource.h>
#include <unistd.h>

#include <atomic>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <mutex>
#include <optional>
#include <sstream>
#include <thread>
#include <vector>

#include <opencv2/core/utility.hpp>
#include <opencv2/core/utils/logger.hpp>

#include "app/config.h"
#include "app/decision_log.h"
#include "app/keyframe_output.h"
#include "app/keyframe_stage.h"
#include "app/keyframe_writer.h"
#include "app/log.h"
#include "app/log_throttle.h"
#include "app/log_to_record.h"
#include "app/mavlink_record.h"
#include "app/paced_source.h"
#include "app/preview_encoder.h"
#include "app/sd_notify.h"
#include "app/settings.h"
#include "app/telemetry_log.h"
#include "app/text_io.h"
#include "app/video_sync.h"
#include "capture/capture_thread.h"
#include "capture/file_source.h"
#include "capture/v4l2_source.h"
#include "core/thread_name.h"
#include "output/flight_outputs.h"
#if KEYFRAMED_HAVE_IO
#include "output/mcap_repair.h"
#endif
#include "tagging/camera_model.h"
#include "tagging/pix4d_fisheye.h"
#include "telemetry/telemetry_service.h"
#ifdef KEYFRAMED_WITH_LIBCAMERA
#include "capture/libcamera_source.h"
#endif

namespace keyframed {

namespace {

constexpr const char* kUsage =
    R"(usage: keyframed run [--config-dir DIR] [--set SECTION.KEY=VALUE]...

Runs the daemon: captures from the configured camera (or video file), selects
keyframes, tags them with the autopilot's telemetry, writes them under
output.state_dir/flights/<UTC start time>/ (state_dir/latest points at the newest),
records the flight to MCAP and publishes keyframes over Zenoh, until SIGINT or
SIGTERM (or the end of a video file). SIGHUP reloads [selection] and [log]; other
settings take a restart.

Exit status: 0 stopped or the video ended; 1 the camera, link or outputs failed;
2 bad command line; 78 bad configuration (systemd does not restart on 2 and 78).

Configuration: built-in defaults < DIR/keyframed.toml < DIR/conf.d/*.toml < --set
(DIR: --config-dir, else $KEYFRAMED_CONFIG_DIR, else /etc/keyframed); see
`keyframed check-config` and docs/configuration.md.
)";

// sysexits.h's EX_CONFIG: the unit's RestartPreventExitStatus. A typo in a file is
// not fixed by starting again every two seconds, a camera that is not there yet is.
constexpr int kExitConfig = 78;

// "section.key" of every line of toToml() whose value differs between a and b.
std::vector<std::string> changedKeys(const std::string& a, const std::string& b) {
  const auto keyed = [](const std::string& text) {
    std::map<std::string, std::string> out;
    std::istringstream in(text);
    std::string line, section;
    while (std::getline(in, line)) {
      if (line.starts_with("[")) {
        section = line.substr(1, line.find(']') - 1);
      } else if (const auto eq = line.find(" = ");
                 eq != std::string::npos && !line.starts_with("#")) {
        out[section + "." + line.substr(0, eq)] = line.substr(eq + 3);
      }
    }
    return out;
  };
  const auto ka = keyed(a), kb = keyed(b);
  std::vector<std::string> keys;
  for (const auto& [k, v] : kb) {
    const auto it = ka.find(k);
    if (it == ka.end() || it->second != v) keys.push_back(k);
  }
  for (const auto& [k, v] : ka) {
    if (!kb.contains(k)) keys.push_back(k);
  }
  return keys;
}

// CPU seconds spent decoding video (0 for cameras).
double decodeCpuSeconds(const FrameSource& source) {
  const auto* paced = dynamic_cast<const PacedSource*>(&source);
  return paced != nullptr ? paced->decodeCpuSeconds() : 0.0;
}

// <state_dir>/flights/<stamp>[-N], and <state_dir>/latest -> it.
bool makeFlightDir(const std::string& stateDir, std::string& dir, std::string& error) {
  namespace fs = std::filesystem;
  std::error_code ec;
  const fs::path flights = fs::path(stateDir) / "flights";
  fs::create_directories(flights, ec);
  if (ec) {
    error = "cannot create " + flights.string() + ": " + ec.message();
    return false;
  }
  const std::string stamp = formatUtcCompact(unixNowNs(), false);
  fs::path p = flights / stamp;
  // A few starts in one second at most (a restart loop); past that something is wrong.
  for (int n = 1; fs::exists(p); ++n) {
    if (n > 1000) {
      error = "cannot name a new flight directory in " + flights.string() + ": " + stamp + " to " +
              p.filename().string() + " exist";
      return false;
    }
    p = flights / (stamp + "-" + std::to_string(n));
  }
  fs::create_directories(p / "keyframes", ec);
  if (ec) {
    error = "cannot create " + p.string() + ": " + ec.message();
    return false;
  }
  dir = p.string();
  const fs::path latest = fs::path(stateDir) / "latest";
  const fs::path tmp = fs::path(stateDir) / ".latest.tmp";
  fs::remove(tmp, ec);
  fs::create_directory_symlink(fs::path("flights") / p.filename(), tmp, ec);
  if (!ec) fs::rename(tmp, latest, ec);
  if (ec) KF_LOG(App, Warning) << "cannot update " << latest.string() << ": " << ec.message();
  return true;
}

constexpr int kStateDirPermanent = 2;

// 0 when stateDir/flights exists (made if need be) and may be written; else the error
// and 2 when restarting will not help (read-only, not permitted, a path through a
// file, a name too long), 1 when it may (a full disk, an I/O error, a disk not yet
// mounted).
int checkStateDir(const std::string& stateDir, std::string& error) {
  namespace fs = std::filesystem;
  const fs::path flights = fs::path(stateDir) / "flights";
  std::error_code ec;
  fs::create_directories(flights, ec);
  int err = ec ? ec.value() : 0;
  if (err == 0 && ::access(flights.c_str(), W_OK) != 0) err = errno;
  if (err == 0) return 0;
  error = "cannot write " + flights.string() + ": " + std::strerror(err);
  if (err == EROFS || err == EACCES || err == EPERM) {
    error +=
        " (under systemd only the unit's StateDirectory, /var/lib/keyframed, is writable: "
        "add the directory with ReadWritePaths= in a drop-in, docs/deploy.md)";
    return kStateDirPermanent;
  }
  if (err == ENOTDIR || err == EEXIST || err == ENAMETOOLONG || err == ELOOP) {
    return kStateDirPermanent;
  }
  return 1;
}

// `videoClock`: a file replayed with its tlog, its frames stamped on the recorded
// flight's clock (camera.start_time + container time) even when paced in real time.
// `placedStartNs`: camera.start_time = "auto", resolved (Daemon::placeVideoByMotion).
std::unique_ptr<FrameSource> openSource(const DaemonConfig::Camera& c, bool videoClock,
                                        std::optional<std::int64_t> placedStartNs,
                                        std::string& error) {
  switch (c.source) {
    case DaemonConfig::Source::File: {
      auto file = FileSource::open(c.path, error);
      if (!file) return nullptr;
      // As decoded, or as a camera would deliver it (the name was checked with the
      // configuration).
      if (!file->setOutputFormat(filePixelFormat(c.pixelFormat).value_or(PixelFormat::BGR24),
                                 error)) {
        return nullptr;
      }
      std::optional<std::int64_t> start = placedStartNs;
      if (!start && !c.startTime.empty()) {
        std::int64_t ns = 0;
        if (!parseUtcTime(c.startTime, ns)) {
          error = "camera.start_time: not an ISO 8601 UTC time or unix seconds: " + c.startTime;
          return nullptr;
        }
        start = ns;
      }
      if (c.realtime && !videoClock) start.reset();  // a camera's clock: CLOCK_MONOTONIC
      return std::make_unique<PacedSource>(std::move(file), c.realtime, start);
    }
    case DaemonConfig::Source::V4l2: {
      V4l2Options o;
      o.device = c.device;
      if (o.device.empty()) {
        o.device = V4l2Source::pickDevice(V4l2Source::listDevices());
        if (o.device.empty()) {
          error = "no V4L2 capture device found (camera.device to name one)";
          return nullptr;
        }
      }
      o.format = c.pixelFormat == "auto" ? "" : c.pixelFormat;
      o.width = c.width;
      o.height = c.height;
      o.fps = c.fps;
      o.autoReopen = true;                // an unplugged camera is waited for, not fatal
      o.followCamera = c.device.empty();  // picked: found again wherever it comes back
      return V4l2Source::open(o, error);
    }
    case DaemonConfig::Source::Libcamera: {
#ifdef KEYFRAMED_WITH_LIBCAMERA
      LibcameraOptions o;
      o.cameraId = c.device;
      o.format = c.pixelFormat == "auto" ? "" : c.pixelFormat;
      o.width = c.width;
      o.height = c.height;
      o.fps = c.fps;
      return LibcameraSource::open(o, error);
#else
      error = "camera.source = \"libcamera\": this keyframed was built without libcamera";
      return nullptr;
#endif
    }
  }
  error = "unknown camera source";
  return nullptr;
}

struct RunStats {
  std::atomic<std::int64_t> analysed{0};
  std::atomic<std::int64_t> kept{0};
  std::atomic<std::int64_t> written{0};
  std::atomic<std::int64_t> writeErrors{0};
  std::atomic<std::int64_t> lastFrameNs{0};
};

double cpuSeconds() {
  rusage ru{};
  getrusage(RUSAGE_SELF, &ru);
  return static_cast<double>(ru.ru_utime.tv_sec + ru.ru_stime.tv_sec) +
         static_cast<double>(ru.ru_utime.tv_usec + ru.ru_stime.tv_usec) / 1e6;
}

// Peak RSS of this process image. Not getrusage's ru_maxrss: Linux carries that
// over execve, so it would report the parent's peak when the parent was larger.
double maxRssMb() {
  std::ifstream f("/proc/self/status");
  std::string line;
  while (std::getline(f, line)) {
    if (line.rfind("VmHWM:", 0) == 0) return std::strtod(line.c_str() + 6, nullptr) / 1024.0;
  }
  return 0.0;
}

// Earlier flights' records that a crash left unfinished, repaired on a thread of
// the lowest priority while this flight runs; stopped (the file it was on left as
// it was, for the next start) and joined when the daemon ends.
class RecordRepair {
 public:
  RecordRepair() = default;
  RecordRepair(const RecordRepair&) = delete;
  RecordRepair& operator=(const RecordRepair&) = delete;
  ~RecordRepair() {
    stop_ = 1;
    if (thread_.joinable()) thread_.join();
  }
  void start(const std::string& flightsDir, const std::string& currentFlight) {
#if KEYFRAMED_HAVE_IO
    thread_ = std::thread([this, flightsDir, currentFlight] {
      nameThisThread("kf-repair");
      setpriority(PRIO_PROCESS, static_cast<id_t>(gettid()), 19);
      for (const McapRepair& r : repairFlightRecords(flightsDir, currentFlight, stop_)) {
        if (r.removed) {
          KF_LOG(Output, Notice) << "flight record part " << r.path
                                 << " was created but never written (a crash or power cut as "
                                    "it began): removed";
        } else if (r.error.empty()) {
          KF_LOG(Output, Notice) << "flight record " << r.path
                                 << " was left unfinished (a crash or power cut): rewritten "
                                    "complete with the "
                                 << r.messages << " messages that read back";
        } else if (stop_.load() == 0) {
          KF_LOG(Output, Warning) << "flight record " << r.path
                                  << " is unfinished and could not be repaired: " << r.error;
        }
      }
    });
#else
    (void)flightsDir;
    (void)currentFlight;
#endif
  }

 private:
  std::atomic<int> stop_{0};
  std::thread thread_;
};

class Daemon {
 public:
  Daemon(DaemonConfig config, ConfigSources sources)
      : config_(std::move(config)), sources_(std::move(sources)) {}
  int run();

 private:
  // camera.start_time = "auto": where the video starts in its tlog (app/video_sync.h),
  // answering signals meanwhile. False on failure (logged); stopped: a signal came.
  bool placeVideoByMotion(const sigset_t& sigs, std::int64_t& startNs, bool& stopped);
  void analysisLoop();
  void outputLoop();
  void outputOne(const KeyframeEvent& event, std::string& error, LogThrottle& errorLog);
  // Says how many keyframes a full disk held back were saved since it last said so.
  void logSavedLate();
  void reload();
  void publishPose();
  bool writeSummary(double seconds, const std::string& state, std::string& error);
  // Frames the camera could not deliver since the capture started (not those it could
  // not deliver while its buffers held stale frames, before it).
  [[nodiscard]] std::uint64_t lostInCamera() const {
    const std::uint64_t lost = source_->lostFrames();
    const std::uint64_t before = capture_ ? capture_->stats().lostBeforeStart : 0;
    return lost > before ? lost - before : 0;
  }

  DaemonConfig config_;
  ConfigSources sources_;
  Notifier notifier_;
  std::string flightDir_;
  bool ready_ = false;                // READY=1 sent (the first frame arrived); main thread
  bool reloadPending_ = false;        // SIGHUP before the outputs were open; main thread
  std::size_t leftAtStop_ = 0;        // frames still queued when the analysis stopped
  std::int64_t savedLateLogged_ = 0;  // of writer_.savedLate() (output thread, then main)
  // Frames on a recorded flight's clock (a file with its tlog) instead of CLOCK_MONOTONIC:
  // "now" on that clock is CLOCK_MONOTONIC + the offset found at the first frame.
  bool videoClock_ = false;
  std::atomic<std::int64_t> clockOffsetNs_{0};
  bool clockOffsetFound_ = false;  // analysis thread
  std::atomic<bool> analysisFailed_{false};
  void analyse();
  // A tlog's packets into the flight record as the frames reach their time (analysis
  // thread), as a live link's are recorded on arrival.
  std::optional<MavlinkRecord> replayRecord_;
  std::size_t replayRecorded_ = 0;
  void recordReplayUpTo(std::int64_t timeNs);
  // Once, at the first frame: what the camera's timestamps mark, and whether
  // camera.time_offset_ms corrects for it.
  void logTimestampOrigin() const;
  // The frame into the record's preview stream (and Zenoh's preview key).
  void preview(const Frame& frame);
  [[nodiscard]] std::int64_t frameClockNowNs() const {
    return monotonicNowNs() + clockOffsetNs_.load();
  }
  RecordRepair repair_;
  std::unique_ptr<FrameSource> source_;
  double sourceFps_ = 0.0;  // source_->info().fps before the capture thread started
  std::unique_ptr<FramePool> pool_;
  std::unique_ptr<FrameQueue> queue_;
  std::unique_ptr<CaptureThread> capture_;
  std::unique_ptr<TelemetryService> telemetry_;
  std::optional<CameraModel> camera_;
  KeyframeWriter writer_;
  DecisionLog log_;
  FlightOutputs outputs_;
  std::unique_ptr<LogToRecord> logToRecord_;  // the log into the MCAP; goes before outputs_
  std::unique_ptr<KeyframeStage> stage_;
  std::unique_ptr<KeyframeOutput> output_;
  // Analysis -> output: blocks the analysis when the output falls behind, so that no
  // keyframe is ever dropped (frames are dropped earlier, at the capture queue). Every
  // frame sends one (its decision, a few hundred bytes; a keyframe's pixels from
  // KeyframeStage's pool): 96 are 3 s at 30 fps, past a keyframe's wait for telemetry
  // (telemetry.wait_ms, 1 s) and its fsyncs on an SD card, which 16 (0.5 s) were not.
  BoundedQueue<KeyframeEvent> events_{96};
  RunStats stats_;
  std::atomic<bool> stopAnalysis_{false};
  std::mutex reloadMutex_;
  std::optional<SelectorConfig> pendingSelection_;
  // The selection settings with the calibrated lens, which the overlap is measured
  // through (geometric mode).
  SelectorConfig throughLens(SelectorConfig selection) const {
    if (camera_) selection.overlap.lens = camera_->lensModel();
    return selection;
  }
  CaptureRequests captureRequests_;       // MAVLink (telemetry thread) -> analysis
  std::atomic<int> capturesUnserved_{0};  // taken, but the source ended first
  StageCounts finalCounts_;
  std::unique_ptr<PreviewEncoder> preview_;  // made once the source's frame rate is known
  std::vector<std::uint8_t> previewData_, previewStill_;
  bool previewFailed_ = false;  // said once
};

void Daemon::analysisLoop() {
  // An exception (out of memory, OpenCV's) ends the analysis, not the process: the
  // keyframes so far are flushed and the run ends as failed.
  try {
    analyse();
  } catch (const std::exception& e) {
    KF_LOG(Select, Error) << "analysis failed: " << e.what();
    analysisFailed_.store(true);
  }
  try {
    stage_->finish();  // the last stretch is covered too
    recordReplayUpTo(std::numeric_limits<std::int64_t>::max());
  } catch (const std::exception& e) {
    KF_LOG(Select, Error) << "analysis failed at the end: " << e.what();
    analysisFailed_.store(true);
  }
  // Captures asked for from now on are denied; those taken that no usable frame
  // answered are said, not left as if served.
  if (const int unserved = captureRequests_.close(*stage_); unserved > 0) {
    capturesUnserved_.store(unserved);
    KF_LOG(Select, Warning) << unserved
                            << " capture(s) asked for over MAVLink not taken: the source ended "
                               "before a usable frame came";
  }
  finalCounts_ = stage_->counts();
  stats_.kept.store(finalCounts_.kept);
  events_.close();
}

void Daemon::analyse() {
  while (true) {
    // Taken under the lock, applied outside it: applying may hand a keyframe to the
    // output and wait for room there (a slow disk), and a reload meanwhile (the main
    // thread, which also feeds the watchdog) must not wait for that.
    std::optional<SelectorConfig> settings;
    {
      std::lock_guard lock(reloadMutex_);
      settings.swap(pendingSelection_);
    }
    if (settings) {
      const bool restart = stage_->restartsChain(*settings);
      stage_->reconfigure(*settings);
      KF_LOG(Select, Notice) << "selection settings reloaded after frame "
                             << stage_->counts().framesRead - 1
                             << (restart ? ": a new overlap chain starts at the next sharp frame"
                                         : ": the overlap chain goes on");
    }
    if (stopAnalysis_.load()) break;
    if (const int refused = captureRequests_.drainInto(*stage_); refused > 0) {
      KF_LOG(Select, Warning) << refused << " requested capture(s) refused: "
                              << KeyframeSelector::kMaxCaptureRequests << " already wait";
    }
    std::optional<FramePtr> item = queue_->pop(std::chrono::milliseconds(200));
    if (!item) {
      if (queue_->closed() && queue_->size() == 0) break;
      continue;
    }
    stats_.lastFrameNs.store(monotonicNowNs());
    if (videoClock_ && !clockOffsetFound_) {
      clockOffsetNs_.store((*item)->frame.timestampNs - monotonicNowNs());
      clockOffsetFound_ = true;
    }
    stage_->process((*item)->frame);
    recordReplayUpTo((*item)->frame.timestampNs);
    captureRequests_.noteServed(*stage_);
    if (outputs_.recording() || outputs_.publishing()) preview((*item)->frame);
    stats_.analysed.store(stage_->counts().framesRead);
    stats_.kept.store(stage_->counts().kept);
  }
}

void Daemon::preview(const Frame& frame) {
  const auto failed = [this] {
    if (!preview_->error().empty() && !previewFailed_) {
      previewFailed_ = true;
      KF_LOG(Output, Error) << "preview: " << preview_->error()
                            << " (the run goes on without a preview)";
    }
  };
  if (!outputs_.recording()) {
    // No record (output.mcap off, or stopped by a full disk): only Zenoh's still,
    // twice a second, wants a picture.
    if (!outputs_.previewStillDue()) return;
    if (preview_->still(frame, previewStill_))
      outputs_.previewStill(previewStill_);
    else
      failed();
    return;
  }
  if (!preview_->encode(frame, previewData_)) {
    failed();
    return;
  }
  outputs_.preview(frame.timestampNs, previewData_, preview_->format());
  // JPEGs go to Zenoh as they are (FlightOutputs::preview); an H.264 picture or a
  // full-size PNG as a JPEG still.
  const std::string_view kind = preview_->format();
  if (kind != "jpeg" && outputs_.previewStillDue() &&
      (kind == "h264" ? preview_->lastAsJpeg(previewStill_)
                      : preview_->still(frame, previewStill_))) {
    outputs_.previewStill(previewStill_);
  }
}

void Daemon::recordReplayUpTo(std::int64_t timeNs) {
  if (!replayRecord_) return;
  telemetry_->advanceReplay(timeNs);  // the autopilot it follows known as live
  const auto& packets = telemetry_->replayPackets();
  for (; replayRecorded_ < packets.size() && packets[replayRecorded_].timeNs <= timeNs;
       ++replayRecorded_) {
    replayRecord_->packet(packets[replayRecorded_]);
  }
}

void Daemon::outputLoop() {
  std::string error;
  LogThrottle errorLog;  // once per kind, then every 10 s
  while (std::optional<KeyframeEvent> ev = events_.pop()) {
    // Whatever fails with one event (out of memory), the events queued after it are
    // still written: never std::terminate with keyframes in the queue.
    try {
      outputOne(*ev, error, errorLog);
    } catch (const std::exception& e) {
      stats_.writeErrors.fetch_add(1);
      KF_LOG(Output, Error) << "keyframe output failed: " << e.what();
    }
  }
}

void Daemon::logSavedLate() {
  if (const std::int64_t late = writer_.savedLate(); late > savedLateLogged_) {
    KF_LOG(Output, Notice) << late - savedLateLogged_
                           << " keyframes a full disk held back are saved now";
    savedLateLogged_ = late;
  }
}

void Daemon::outputOne(const KeyframeEvent& event, std::string& error, LogThrottle& errorLog) {
  const Decision& d = event.decision;
  if (d.kept) {
    KF_LOG(Select, Debug) << "keyframe " << d.index << ": " << toString(d.reason) << ", overlap "
                          << (std::isfinite(d.overlap) ? formatFixed(d.overlap, 3) : "none")
                          << ", sharpness " << formatFixed(d.sharpness, 1) << " (threshold "
                          << formatFixed(d.threshold, 1) << ")";
  }
  if (event.promoted) {
    KF_LOG(Select, Debug) << "keyframe " << d.promotedIndex
                          << ": gap fill, the sharpest since the last keyframe";
  }
  bool handled = false;
  try {
    handled = output_->handle(event, error);
  } catch (const std::exception& e) {  // one keyframe's failure, not the rest's
    error = std::string("keyframe output failed: ") + e.what();
  }
  if (!handled) {
    // Something could not be saved (disk full, ...): selection, recording and
    // publishing of what can be go on.
    stats_.writeErrors.fetch_add(1);
    // The kind: the reason after the last ": " ("No space left on device"), not the path.
    const auto colon = error.rfind(": ");
    const std::string_view kind = colon == std::string::npos
                                      ? std::string_view(error)
                                      : std::string_view(error).substr(colon + 2);
    if (const auto held = errorLog.pass(kind, monotonicNowNs())) {
      KF_LOG(Output, Error) << error
                            << (*held > 0 ? " (and " + std::to_string(*held) + " more write errors)"
                                          : std::string());
    }
  }
  logSavedLate();
  stats_.written.store(writer_.count());
  outputs_.progress(stats_.analysed.load(), writer_.count());
}

void Daemon::logTimestampOrigin() const {
  const TimestampOrigin origin = source_->timestampOrigin();
  const double offset = config_.camera.timeOffsetMs;
  std::string line = std::string("frame timestamps mark the ") + describe(origin) +
                     "; keyframes are tagged for that instant";
  if (offset != 0.0) {
    line += std::string(offset > 0.0 ? " plus " : " minus ") + formatFixed(std::fabs(offset), 1) +
            " ms (camera.time_offset_ms)";
  }
  if (offset == 0.0 &&
      (origin == TimestampOrigin::EndOfFrame || origin == TimestampOrigin::Arrival)) {
    // The source's rate as it opened: info() is the capture thread's while it runs.
    const double fps = sourceFps_ > 0.0 ? sourceFps_ : config_.camera.fps;
    line += ", which comes up to a frame period (" + formatFixed(1000.0 / fps, 1) +
            " ms) or more after the exposure: camera.time_offset_ms corrects the geotags of a "
            "moving aircraft (docs/capture.md)";
  }
  KF_LOG(Capture, Info) << line;
}

// About once a second, keyframed/<vehicle>/telemetry: the pose a quarter second ago
// (so that samples on both sides have arrived), or why there is none.
void Daemon::publishPose() {
  const std::int64_t t = frameClockNowNs() - 250'000'000;
  const Pose p = telemetry_->decoder().poseAt(t);
  std::string text;
  if (p.position && p.attitude) {
    const auto& g = *p.position;
    const auto& q = *p.attitude;
    text = formatText(
        "{\"time_ns\":%lld,\"lat\":%.9f,\"lon\":%.9f,\"alt_amsl\":%.3f,"
        "\"alt_rel\":%.3f,\"q\":[%.6f,%.6f,%.6f,%.6f],\"fix_type\":%d,"
        "\"keyframes\":%lld}",
        static_cast<long long>(t), g.latDeg, g.lonDeg, g.altAmslM, g.altRelM, q.w, q.x, q.y, q.z,
        p.gps.fixType, static_cast<long long>(stats_.written.load()));
  } else {
    const std::string why = jsonEscape(p.staleReason);
    text = formatText("{\"time_ns\":%lld,\"stale\":\"%s\",\"keyframes\":%lld}",
                      static_cast<long long>(t), why.c_str(),
                      static_cast<long long>(stats_.written.load()));
  }
  outputs_.telemetry(text);
}

void Daemon::reload() {
  if (ready_) notifier_.reloading();
  ConfigLoadResult r = loadConfig(sources_);
  if (!r.ok()) {
    for (const auto& e : r.errors) KF_LOG(App, Error) << "reload: " << e;
    KF_LOG(App, Error) << "reload: configuration invalid, keeping the running settings";
  } else {
    logging::configure(r.config.log);
    std::lock_guard lock(reloadMutex_);
    // Only [selection] and [log] change a running daemon; say which other keys
    // changed and wait for a restart, rather than let an operator think they did.
    DaemonConfig rest = r.config;
    rest.selection = config_.selection;
    rest.log = config_.log;
    if (const auto keys = changedKeys(toToml(config_), toToml(rest)); !keys.empty()) {
      std::string list;
      for (const auto& k : keys) list += (list.empty() ? "" : ", ") + k;
      KF_LOG(App, Warning) << "reload: " << list
                           << " changed: only [selection] and [log] apply on reload, the rest "
                              "on restart (systemctl restart keyframed)";
    }
    const std::string settings = selectionOverrides(r.config.selection);
    if (settings == selectionOverrides(config_.selection)) {
      // A reload for [log], or none at all: the overlap chain goes on.
      KF_LOG(Select, Notice) << "reload: selection settings unchanged";
    } else {
      pendingSelection_ = throughLens(r.config.selection);
      config_.selection = r.config.selection;
      outputs_.settings(frameClockNowNs(), settings);
    }
  }
  // READY again only once it was ready: a reload before the first frame must not say
  // the start-up is over.
  if (ready_) notifier_.ready();
}

bool Daemon::writeSummary(double seconds, const std::string& state, std::string& error) {
  const CaptureThread::Stats cs = capture_->stats();
  const StageCounts& c = finalCounts_;
  const std::uint64_t dropped = queue_->dropped() + cs.noBuffer;
  const std::uint64_t lost = lostInCamera();
  std::string tel = "null";
  if (telemetry_) {
    const TelemetryServiceStats ts = telemetry_->stats();
    const auto off = telemetry_->decoder().clockOffsetNs();
    const double within = telemetry_->decoder().clockUncertaintyMs();
    const std::string uncertainty = std::isnan(within) ? "null" : formatText("%.3f", within);
    const std::string b = formatText(
        "\"geotagged\": %lld, \"clock\": \"%s\", "
        "\"clock_offset_ms\": %s, \"clock_uncertainty_ms\": %s, \"messages\": %llu, "
        "\"rejected_frames\": %llu, "
        "\"unknown_ids\": %llu, \"skipped_bytes\": %llu, \"other_sources\": %llu, "
        "\"captures_sent\": %llu, "
        "\"captures_pending\": %llu, "
        "\"captures_dropped\": %llu, \"captures_resent\": %llu, "
        "\"captures_requested\": %llu, \"captures_refused\": %llu, "
        "\"captures_unserved\": %d, "
        "\"link_errors\": %llu, "
        "\"reconnects\": %llu, \"gimbal_messages\": %llu, \"bad_samples\": %llu, "
        "\"autopilot_reboots\": %llu}",
        static_cast<long long>(writer_.geotagged()), toString(telemetry_->decoder().clockSource()),
        off ? std::to_string(static_cast<double>(*off) / 1e6).c_str() : "null", uncertainty.c_str(),
        static_cast<unsigned long long>(ts.parser.messages),
        static_cast<unsigned long long>(ts.parser.rejected),
        static_cast<unsigned long long>(ts.parser.unknownIds),
        static_cast<unsigned long long>(ts.parser.skippedBytes),
        static_cast<unsigned long long>(ts.decoder.otherSources),
        static_cast<unsigned long long>(ts.capturesSent),
        static_cast<unsigned long long>(ts.capturesPending),
        static_cast<unsigned long long>(ts.capturesDropped),
        static_cast<unsigned long long>(ts.capturesResent),
        static_cast<unsigned long long>(ts.captureRequests),
        static_cast<unsigned long long>(ts.captureRefused), capturesUnserved_.load(),
        static_cast<unsigned long long>(ts.linkErrors),
        static_cast<unsigned long long>(ts.reconnects),
        static_cast<unsigned long long>(ts.decoder.gimbal),
        static_cast<unsigned long long>(ts.decoder.badAttitudes + ts.decoder.badPositions),
        static_cast<unsigned long long>(ts.decoder.reboots));
    // The URL (a device path, a file) as text of a JSON string.
    tel = "{\"source\": \"" + jsonEscape(config_.telemetry.link.url) + "\", " + b;
  }
  const SourceInfo& info = source_->info();
  const double cpu = cpuSeconds();
  const double decode = decodeCpuSeconds(*source_);
  const std::string counts = formatText(
      "  \"width\": %d,\n  \"height\": %d,\n"
      "  \"frames_captured\": %llu,\n  \"frames_dropped\": %llu,\n"
      "  \"frames_lost_in_camera\": %llu,\n  \"frames_stale_at_start\": %llu,\n"
      "  \"frames_left_at_stop\": %llu,\n"
      "  \"frames_read\": %lld,\n"
      "  \"kept\": %lld,\n  \"written\": %lld,\n  \"unsaved\": %lld,\n  \"saved_late\": %lld,\n"
      "  \"write_errors\": %lld,\n  \"index_sync_errors\": %lld,\n"
      "  \"rejected_blur\": %lld,\n  \"rejected_overlap\": %lld,\n  \"gap_fills\": %lld,\n"
      "  \"capture_errors\": %llu,\n  \"seconds\": %.3f,\n  \"frames_per_second\": %.2f,\n"
      "  \"analysis_ms_mean\": %.3f,\n  \"cpu_seconds\": %.3f,\n  \"cpu_percent\": %.1f,\n"
      "  \"decode_cpu_seconds\": %.3f,\n  \"cpu_percent_without_decode\": %.1f,\n"
      "  \"max_rss_mb\": %.1f,\n",
      info.width, info.height, static_cast<unsigned long long>(cs.captured),
      static_cast<unsigned long long>(dropped), static_cast<unsigned long long>(lost),
      static_cast<unsigned long long>(cs.stale), static_cast<unsigned long long>(leftAtStop_),
      static_cast<long long>(c.framesRead), static_cast<long long>(c.kept),
      static_cast<long long>(writer_.saved()),
      static_cast<long long>(writer_.count() - writer_.saved()),
      static_cast<long long>(writer_.savedLate()),
      static_cast<long long>(stats_.writeErrors.load()),
      static_cast<long long>(writer_.syncErrors()), static_cast<long long>(c.rejectedBlur),
      static_cast<long long>(c.rejectedOverlap), static_cast<long long>(c.promoted),
      static_cast<unsigned long long>(cs.errors), seconds,
      seconds > 0 ? static_cast<double>(c.framesRead) / seconds : 0.0,
      c.framesRead > 0 ? c.analysisNs / static_cast<double>(c.framesRead) / 1e6 : 0.0, cpu,
      seconds > 0 ? 100.0 * cpu / seconds : 0.0, decode,
      seconds > 0 ? 100.0 * (cpu - decode) / seconds : 0.0, maxRssMb());
  // The source's description (a file's path, a V4L2 card's name) is any text: escaped.
  const std::string offset = formatText("%.3f", config_.camera.timeOffsetMs);
  const std::string json = "{\n  \"state\": \"" + jsonEscape(state) + "\",\n  \"source\": \"" +
                           jsonEscape(info.description) + "\",\n  \"frame_timestamps\": \"" +
                           describe(source_->timestampOrigin()) +
                           "\",\n  \"time_offset_ms\": " + offset + ",\n" + counts +
                           "  \"telemetry\": " + tel + "\n}\n";
  return writeFileAtomically(flightDir_ + "/summary.json", std::string_view(json), error);
}

bool Daemon::placeVideoByMotion(const sigset_t& sigs, std::int64_t& startNs, bool& stopped) {
  VideoSyncRequest req;
  req.video = config_.camera.path;
  req.link = config_.telemetry.link;
  req.camera = camera_;
  req.mount = {config_.tagging.mountRollDeg, config_.tagging.mountPitchDeg,
               config_.tagging.mountYawDeg, config_.tagging.mountGimbal};
  req.analysisWidth = config_.selection.analysisWidth;
  req.hint =
      "check tagging.mount_roll/pitch/yaw (an oblique camera's turns differ from a "
      "nadir one's) or set camera.start_time to the video's start";
  KF_LOG(App, Notice) << "camera.start_time = auto: placing " << req.video << " in " << req.link.url
                      << " by their motion";
  // The pass runs beside this thread, which keeps answering signals.
  std::atomic<bool> stop{false};
  std::atomic<bool> done{false};
  VideoSync sync;
  std::thread worker([&] {
    try {
      sync = syncVideoWithTlog(req, &stop);
    } catch (const std::exception& e) {  // never std::terminate from a worker
      sync = VideoSync{};
      sync.error = std::string("the pass over the video failed: ") + e.what();
    }
    done.store(true);
  });
  // Not ready before the camera starts: under systemd (Type=notify) a long pass would
  // run into TimeoutStartSec, so the start timeout is pushed on while it runs.
  auto lastExtend = std::chrono::steady_clock::now() - std::chrono::hours(1);
  while (!done.load()) {
    if (std::chrono::steady_clock::now() - lastExtend > std::chrono::seconds(10)) {
      notifier_.extendTimeout(std::chrono::seconds(30));
      notifier_.status("placing the video in its tlog by their motion");
      lastExtend = std::chrono::steady_clock::now();
    }
    timespec wait{0, 50'000'000};
    const int sig = sigtimedwait(&sigs, nullptr, &wait);
    if (sig == SIGINT || sig == SIGTERM) {
      KF_LOG(App, Notice) << (sig == SIGINT ? "SIGINT" : "SIGTERM")
                          << ": stopping before the video was placed";
      stop.store(true);
      stopped = true;
    }
    if (sig == SIGHUP) {
      // Taken once the outputs are open (the record notes the new settings), not lost.
      KF_LOG(App, Notice) << "SIGHUP: the configuration is reloaded once the video is placed";
      reloadPending_ = true;
    }
  }
  worker.join();
  if (stopped) return true;
  if (!sync.ok) {
    KF_LOG(App, Error) << "camera.start_time = auto: " << sync.error;
    return false;
  }
  // The motion places the frames where they were exposed: camera.time_offset_ms, added
  // again at tagging, is taken out here.
  startNs = sync.videoStartUnixNs -
            static_cast<std::int64_t>(std::llround(config_.camera.timeOffsetMs * 1e6));
  KF_LOG(App, Notice) << "video start " << formatUtcIso(sync.videoStartUnixNs)
                      << (startNs != sync.videoStartUnixNs
                              ? " (container time 0 at " + formatUtcIso(startNs) +
                                    " on the camera's clock: camera.time_offset_ms taken out)"
                              : std::string())
                      << " (correlation " << formatFixed(sync.match.correlation, 2)
                      << ", next best " << formatFixed(sync.match.runnerUp, 2) << ", "
                      << sync.turnsKnown << " of " << sync.frames << " frames turned measurably, "
                      << formatFixed(sync.seconds, 1) << " s)";
  return true;
}

int Daemon::run() {
  std::string error;
  // Signals are taken by the main thread alone (sigtimedwait below): block them
  // before any thread starts so every thread inherits the mask.
  sigset_t sigs;
  sigemptyset(&sigs);
  sigaddset(&sigs, SIGINT);
  sigaddset(&sigs, SIGTERM);
  sigaddset(&sigs, SIGHUP);
  pthread_sigmask(SIG_BLOCK, &sigs, nullptr);

  // A state directory the daemon may not write (read-only under the unit's
  // ProtectSystem=strict, outside its StateDirectory) will not become writable by
  // restarting: a configuration error, said before the camera is opened.
  if (const int rc = checkStateDir(config_.output.stateDir, error); rc != 0) {
    KF_LOG(Output, Error) << "output.state_dir: " << error;
    return rc == kStateDirPermanent ? kExitConfig : 1;
  }
#ifndef KEYFRAMED_WITH_LIBCAMERA
  if (config_.camera.source == DaemonConfig::Source::Libcamera) {
    KF_LOG(Capture, Error) << "camera.source = \"libcamera\": this keyframed was built without "
                              "libcamera (use \"v4l2\", or build with libcamera-dev installed)";
    return kExitConfig;
  }
#endif
  if (!config_.tagging.calibration.empty()) {
    CameraModel m;
    if (!loadCameraModel(config_.tagging.calibration, m, error)) {
      KF_LOG(App, Error) << "tagging.calibration: " << error;
      return kExitConfig;
    }
    camera_ = m;
  } else if (config_.tagging.camera) {
    camera_ = config_.tagging.camera;  // [tagging.camera], checked when loaded
  } else {
    KF_LOG(Tagging, Warning)
        << "no tagging.calibration or [tagging.camera]: keyframes carry no intrinsics";
  }
  // camera.start_time = "auto" resolved; the setting stays "auto" (a reload compares it).
  std::optional<std::int64_t> placedStartNs;
  if (config_.camera.source == DaemonConfig::Source::File && config_.camera.startTime == "auto") {
    std::int64_t startNs = 0;
    bool stopped = false;
    if (!placeVideoByMotion(sigs, startNs, stopped)) return 1;
    if (stopped) return 0;
    placedStartNs = startNs;
  }
  // Frames on the video's own clock: a file replayed with its tlog (camera.start_time
  // + container time, the tlog's unix times), or read as fast as it decodes (container
  // time from camera.start_time when given, else from 0: this run's start in unix time).
  std::optional<std::int64_t> videoStartNs;
  std::int64_t videoUnixOffsetNs = 0;
  if (config_.camera.source == DaemonConfig::Source::File &&
      (isTlogUrl(config_.telemetry.link.url) || !config_.camera.realtime)) {
    std::int64_t ns = 0;
    if (placedStartNs) {
      videoStartNs = placedStartNs;
    } else if (!config_.camera.startTime.empty() && parseUtcTime(config_.camera.startTime, ns)) {
      videoStartNs = ns;  // checked at load; a tlog requires it
    } else {
      videoStartNs = 0;
      videoUnixOffsetNs = unixNowNs();
    }
  }
  videoClock_ = videoStartNs.has_value();
  if (videoStartNs) clockOffsetNs_.store(*videoStartNs - monotonicNowNs());  // until a frame
  if (config_.camera.source == DaemonConfig::Source::File) {
    // A file source may be a FIFO (MJPEG from another program), whose open waits for a
    // writer however long: it opens beside this thread, which keeps answering signals.
    // The state is shared, not borrowed: a stop leaves the open behind, unfinished.
    struct Opening {
      std::unique_ptr<FrameSource> source;
      std::string error;
      std::atomic<bool> done{false};
    };
    auto opening = std::make_shared<Opening>();
    std::thread([opening, camera = config_.camera, clock = videoClock_, placedStartNs] {
      // A decoder's worker threads (FFmpeg's, a file source's) take this name.
      nameThisThread("kf-camera-open");
      try {
        opening->source = openSource(camera, clock, placedStartNs, opening->error);
      } catch (const std::exception& e) {  // never std::terminate from a worker
        opening->error = e.what();
      }
      opening->done.store(true);
    }).detach();
    while (!opening->done.load()) {
      timespec wait{0, 50'000'000};
      const int sig = sigtimedwait(&sigs, nullptr, &wait);
      if (sig == SIGINT || sig == SIGTERM) {
        KF_LOG(App, Notice) << (sig == SIGINT ? "SIGINT" : "SIGTERM") << ": stopping while "
                            << config_.camera.path << " was still opening (nothing recorded)";
        return 0;
      }
      if (sig == SIGHUP) {
        KF_LOG(App, Notice) << "SIGHUP: the configuration is reloaded once the video is open";
        reloadPending_ = true;
      }
    }
    source_ = std::move(opening->source);
    error = opening->error;
  } else {
    source_ = openSource(config_.camera, videoClock_, placedStartNs, error);
  }
  if (!source_) {
    KF_LOG(Capture, Error) << toString(config_.camera.source) << ": " << error;
    return 1;
  }
  const SourceInfo& info = source_->info();
  if (const std::string small =
          tooSmallToAnalyse(info.width, info.height, config_.selection.analysisWidth);
      !small.empty()) {
    KF_LOG(Capture, Error) << info.description << ": " << small << " (selection.analysis_width)";
    return kExitConfig;  // the camera's mode or the setting: a restart changes neither
  }
  if (const std::string large = tooLargeToAnalyse(info.width, info.height); !large.empty()) {
    KF_LOG(Capture, Error) << info.description << ": " << large << " (camera.width, height)";
    return kExitConfig;
  }
  KF_LOG(Capture, Notice) << "capturing from " << info.description << " (" << info.width << "x"
                          << info.height << " @ " << info.fps << " fps)";
  preview_ = std::make_unique<PreviewEncoder>(static_cast<int>(config_.output.previewWidth),
                                              config_.output.previewFormat == "h264"
                                                  ? PreviewEncoder::Format::H264
                                                  : PreviewEncoder::Format::Jpeg,
                                              info.fps);
  // A camera that does not offer the configured size gives its nearest one: say so, the
  // keyframes and the calibration's scaling depend on it.
  if (config_.camera.source != DaemonConfig::Source::File &&
      (info.width != config_.camera.width || info.height != config_.camera.height)) {
    KF_LOG(Capture, Warning) << "the camera delivers " << info.width << "x" << info.height
                             << ", not the configured camera.width x camera.height "
                             << config_.camera.width << "x" << config_.camera.height
                             << " (the nearest size it offers)";
  }
  // Nor does every camera reach the configured rate (a USB 2 webcam's uncompressed
  // 1080p: 5 fps); the overlap between frames, and the keyframes, depend on it.
  if (config_.camera.source != DaemonConfig::Source::File && info.fps > 0.0 &&
      config_.camera.fps > 0.0 && info.fps < config_.camera.fps * 0.99) {
    KF_LOG(Capture, Warning) << "the camera runs at " << info.fps
                             << " fps, not the configured camera.fps " << config_.camera.fps
                             << " (the fastest it offers at this size and format)";
  }
  if (camera_) {
    if (const std::string w = camera_->aspectMismatch(info.width, info.height); !w.empty()) {
      KF_LOG(Tagging, Warning) << w;
      camera_ = camera_->withoutIntrinsics();
    }
    if (const std::string w = camera_->physicalSizeWarning(); !w.empty())
      KF_LOG(Tagging, Warning) << w;
    if (const std::string w = camera_->lensWarning(); !w.empty()) KF_LOG(Tagging, Warning) << w;
    if (const std::string w = pix4dFisheyeWarning(*camera_); !w.empty())
      KF_LOG(Tagging, Warning) << w;
  }
  if (!makeFlightDir(config_.output.stateDir, flightDir_, error)) {
    KF_LOG(Output, Error) << error;
    return 1;
  }
  KF_LOG(Output, Notice) << "flight directory " << flightDir_;
  repair_.start(std::filesystem::path(flightDir_).parent_path().string(), flightDir_);

  if (!config_.telemetry.link.url.empty()) {
    CameraDescription cd;
    cd.width = info.width;
    cd.height = info.height;
    if (camera_) {
      if (!camera_->make.empty()) cd.vendor = camera_->make;  // else the component's own
      if (!camera_->model.empty()) cd.model = camera_->model;
      cd.focalLengthMm = static_cast<float>(camera_->focalLengthMm);
      cd.sensorWidthMm = static_cast<float>(camera_->sensorWidthMm);
      cd.sensorHeightMm = static_cast<float>(camera_->sensorHeightMm);
    }
    // The autopilot's CAMERA_INFORMATION names the camera as the keyframes' EXIF does.
    if (!config_.tagging.make.empty()) cd.vendor = config_.tagging.make;
    if (!config_.tagging.model.empty()) cd.model = config_.tagging.model;
    // An autopilot on USB may be powered after the companion: its serial device
    // appears later, and the camera need not wait for it (nor restart for it).
    TelemetryServiceConfig tc = config_.telemetry.link;
    tc.waitForSerialDevice = true;
    telemetry_ = std::make_unique<TelemetryService>(tc, cd);
    telemetry_->setGimbalMount(config_.tagging.mountGimbal);  // ask for its attitude too
    logTelemetryEvents(*telemetry_);
    // MAV_CMD_IMAGE_START_CAPTURE: the next sharp frame is a keyframe.
    telemetry_->setCaptureRequestSink(
        [this](bool intervalTick) { return captureRequests_.add(intervalTick); });
  }
  if (!log_.open(flightDir_ + "/decisions.csv", DecisionFormat::Csv, error)) {
    KF_LOG(Output, Error) << error;
    return 1;
  }
  KeyframeWriterConfig wc;
  wc.dir = flightDir_ + "/keyframes";
  wc.quality = config_.tagging.jpegQuality;
  wc.camera = camera_;
  if (config_.tagging.systemClockUtc && videoClock_) {
    // A recorded flight's frames are stamped in unix time (or container time, offset).
    wc.utcFallback = [videoUnixOffsetNs](std::int64_t ns) -> std::optional<std::int64_t> {
      return (ns + videoUnixOffsetNs) / 1000;
    };
  } else if (config_.tagging.systemClockUtc) {
    // Frames are stamped on CLOCK_MONOTONIC: the companion's UTC at that instant.
    wc.utcFallback = [](std::int64_t monoNs) -> std::optional<std::int64_t> {
      return (unixNowNs() - (monotonicNowNs() - monoNs)) / 1000;
    };
  }
  wc.make = config_.tagging.make;
  wc.model = config_.tagging.model;
  wc.mount = {config_.tagging.mountRollDeg, config_.tagging.mountPitchDeg,
              config_.tagging.mountYawDeg, config_.tagging.mountGimbal};
  if (!writer_.open(wc, error)) {
    KF_LOG(Output, Error) << error;
    return 1;
  }
  FlightOutputOptions fo;
  if (config_.output.mcap) fo.mcapPath = flightDir_ + "/flight.mcap";
  fo.mcapRotateBytes = static_cast<std::uint64_t>(config_.output.mcapRotateMb) << 20;
  fo.mcapRotateSeconds = config_.output.mcapRotateS;
  fo.mcapFsync = config_.output.mcapFsync;
  // Preview frames (JPEG, PNG, H.264) are most of the record and do not compress.
  fo.mcapCompression = config_.output.mcapCompression != "auto" ? config_.output.mcapCompression
                       : config_.output.previewWidth > 0        ? "none"
                                                                : "zstd";
  fo.liveClock = !videoClock_;  // frames and MAVLink on CLOCK_MONOTONIC
  if (videoStartNs) {           // or a recorded flight's unix time, or container time
    fo.startNs = *videoStartNs;
    fo.unixOffsetNs = videoUnixOffsetNs;
  }
  fo.warn = [](const std::string& m) { KF_LOG(Output, Warning) << m; };
  fo.error = [](const std::string& m) { KF_LOG(Output, Error) << m; };
  fo.note = [](const std::string& m) { KF_LOG(Output, Notice) << m; };
  fo.zenoh = config_.zenoh.enabled;
  fo.zenohConfig = config_.zenoh.config;
  fo.zenohSetting = "zenoh.config";
  fo.zenohRetryMs = static_cast<int>(config_.zenoh.openRetryS * 1000);
  fo.vehicle = config_.zenoh.vehicle;
  if (fo.vehicle.empty()) {
    char host[256] = {};
    gethostname(host, sizeof host - 1);
    // A host name is letters, digits and '-' (and '.' between labels), 63 at most: a
    // vehicle's name as it is; anything else (an odd hostname) becomes '_'.
    std::string name(host);
    for (char& ch : name) {
      if (!(std::isalnum(static_cast<unsigned char>(ch)) || ch == '-' || ch == '.')) ch = '_';
    }
    if (name.size() > 64) name.resize(64);
    fo.vehicle = vehicleNameError(name).empty() ? name : "uav";
  }
  fo.keyframeDir = wc.dir;
  // The ground station tells this run's keyframes (sequence numbers from 0 again)
  // from an earlier run's by the flight directory's name.
  fo.flight = std::filesystem::path(flightDir_).filename().string();
  fo.flightsDir = std::filesystem::path(flightDir_).parent_path().string();
  fo.offline = false;  // live: the recorder drops (and counts) rather than stall
  if (!outputs_.open(fo, info.width, info.height, camera_ ? &*camera_ : nullptr, error)) {
    KF_LOG(Output, Error) << error;
    return 1;
  }
  logToRecord_ = std::make_unique<LogToRecord>(outputs_);
  outputs_.tagging(taggingOverrides(config_.tagging, config_.camera.timeOffsetMs),
                   camera_ ? &*camera_ : nullptr);
  outputs_.settings(frameClockNowNs(), selectionOverrides(config_.selection));

  if (telemetry_) {
    // The link opens once the flight record listens: every packet from the first is
    // recorded, so that a replay of the record tags the first keyframes too.
    recordLiveMavlink(*telemetry_, outputs_);
    if (!telemetry_->start(error)) {
      KF_LOG(Telemetry, Error) << "telemetry.url: " << error;
      return 1;
    }
    if (telemetry_->isReplay() && outputs_.recording())
      replayRecord_.emplace(outputs_, telemetry_->decoder());
  }
  MonotonicClock clock;
  stage_ = std::make_unique<KeyframeStage>(
      throughLens(config_.selection), &clock,
      [this](KeyframeEvent&& ev) { events_.pushWait(std::move(ev)); });
  output_ = std::make_unique<KeyframeOutput>(
      writer_, log_, outputs_, telemetry_.get(), config_.telemetry.waitMs,
      config_.telemetry.link.decoder.store, config_.camera.timeOffsetMs);
  // Room for camera.queue_ms of the analysis falling behind (a burst of keyframes, a
  // busy companion): frames past that are dropped, oldest first, and counted.
  // Sized for the largest frame a source delivers (BGR, 3 bytes a pixel).
  const SourceInfo& si = source_->info();
  sourceFps_ = si.fps;
  // A camera that does not say its rate (a V4L2 driver without VIDIOC_G_PARM) is
  // taken to run at the configured one, not to need the smallest queue.
  const double queueFps = si.fps > 0.0 ? si.fps : config_.camera.fps;
  const std::size_t queueFrames =
      queueFramesFor(config_.camera.queueMs, queueFps,
                     static_cast<std::size_t>(si.width) * static_cast<std::size_t>(si.height) * 3);
  KF_LOG(Capture, Info) << "frame queue: " << queueFrames << " frames (" << config_.camera.queueMs
                        << " ms at " << queueFps << " fps, " << kQueueBudgetBytes / (1 << 20)
                        << " MiB at most)";
  queue_ = std::make_unique<FrameQueue>(queueFrames);
  pool_ = std::make_unique<FramePool>(queueFrames + 3);  // + analysing, + capturing, + spare
  // A camera may come back (V4L2 reopens it): never give up on it; the watchdog
  // says when it is gone too long. A file that keeps failing to decode will not.
  constexpr int kFileMaxErrors = 10;
  capture_ = std::make_unique<CaptureThread>(
      *source_, *pool_, *queue_,
      config_.camera.source == DaemonConfig::Source::File ? kFileMaxErrors : 0);

  if (reloadPending_) {  // a SIGHUP while the video was being placed
    reloadPending_ = false;
    reload();
  }
  bool stopNow = false;  // a signal while waiting for telemetry: stop the usual way
  if (telemetry_ && !telemetry_->isReplay() && config_.telemetry.startWaitMs > 0) {
    // Keyframes taken before the autopilot is heard would go untagged: give the link
    // a moment (telemetry.start_wait_ms) to deliver a first pose. Signals still work.
    KF_LOG(Telemetry, Notice) << "waiting up to " << config_.telemetry.startWaitMs
                              << " ms for telemetry on " << config_.telemetry.link.url;
    // READY comes with the first frame, after this wait: systemd's start timeout
    // (90 s by default) must not run out first.
    notifier_.extendTimeout(std::chrono::milliseconds(config_.telemetry.startWaitMs + 30'000));
    notifier_.status("waiting for telemetry on " + config_.telemetry.link.url);
    const std::int64_t deadline = monotonicNowNs() + config_.telemetry.startWaitMs * 1'000'000LL;
    while (!telemetry_->decoder().hasPose() && monotonicNowNs() < deadline) {
      timespec wait{0, 20'000'000};
      const int sig = sigtimedwait(&sigs, nullptr, &wait);
      if (sig == SIGINT || sig == SIGTERM) {
        KF_LOG(App, Notice) << (sig == SIGINT ? "SIGINT" : "SIGTERM")
                            << ": stopping before the camera started";
        stopNow = true;
        break;
      }
      if (sig == SIGHUP) reload();  // taken now, not lost
    }
    if (!stopNow && !telemetry_->decoder().hasPose()) {
      KF_LOG(Telemetry, Warning) << "no attitude and position yet from "
                                 << config_.telemetry.link.url
                                 << "; keyframes are tagged once telemetry arrives";
    }
  }
  const auto start = std::chrono::steady_clock::now();
  std::thread output([this] {
    nameThisThread("kf-output");
    outputLoop();
  });
  std::thread analysis([this] {
    nameThisThread("kf-analysis");
    analysisLoop();
  });
  std::string state = "done";
  if (stopNow) {
    state = "stopped";
  } else if (config_.camera.source != DaemonConfig::Source::File) {
    // The camera has streamed since it opened: what its buffers hold now is from
    // before the waits above (Zenoh, telemetry), and the first of it would become the
    // first keyframe, out of date and before any pose. Frames exposed more than a
    // frame period and a half before now are thrown away.
    const double fps = sourceFps_ > 0.0 ? sourceFps_ : config_.camera.fps;
    const auto period = static_cast<std::int64_t>(1.5e9 / (fps > 0.0 ? fps : 30.0));
    capture_->start(monotonicNowNs() - period);
  } else {
    capture_->start();
  }

  auto lastStatus = std::chrono::steady_clock::now();
  std::int64_t lastAnalysed = 0;
  const auto ping =
      notifier_.watchdogPingInterval().count() > 0
          ? std::chrono::duration_cast<std::chrono::milliseconds>(notifier_.watchdogPingInterval())
          : std::chrono::milliseconds(1000);
  auto lastPing = std::chrono::steady_clock::now();
  std::uint64_t lastCaptured = 0;  // the capture thread's count, and when it last grew
  std::int64_t lastCaptureNs = 0;
  while (!stopNow) {
    timespec wait{0, 100'000'000};
    const int sig = sigtimedwait(&sigs, nullptr, &wait);
    if (sig == SIGINT || sig == SIGTERM) {
      KF_LOG(App, Notice) << (sig == SIGINT ? "SIGINT" : "SIGTERM") << ": stopping";
      state = "stopped";
      break;
    }
    if (sig == SIGHUP) reload();
    // Frames arrive while the camera delivers them and the analysis takes them, both
    // within the last 2 s: frames still queued when the camera went away do not count
    // (at a few frames a second they would keep the watchdog fed for seconds), nor a
    // camera that delivers into an analysis that hangs.
    const std::int64_t nowNs = monotonicNowNs();
    if (const std::uint64_t captured = capture_->stats().captured; captured != lastCaptured) {
      lastCaptured = captured;
      lastCaptureNs = nowNs;
    }
    const std::int64_t last = stats_.lastFrameNs.load();
    constexpr std::int64_t kFrameSilenceNs = 2'000'000'000LL;
    const bool framesArrive = last > 0 && nowNs - last < kFrameSilenceNs && lastCaptureNs > 0 &&
                              nowNs - lastCaptureNs < kFrameSilenceNs;
    if (!ready_ && last > 0) {
      ready_ = true;  // the camera has delivered its first frame
      notifier_.ready("first frame received");
      KF_LOG(App, Notice) << "ready: first frame received";
      logTimestampOrigin();
    }
    const auto now = std::chrono::steady_clock::now();
    if (framesArrive && now - lastPing >= ping) {
      notifier_.watchdog();  // only while frames really arrive
      lastPing = now;
    }
    if (now - lastStatus >= std::chrono::seconds(1)) {
      const double el = std::chrono::duration<double>(now - lastStatus).count();
      const std::int64_t analysed = stats_.analysed.load();
      char buf[160];
      // Dropped: by us (the analysis fell behind) and before us (the camera's driver
      // had no free buffer: the capture thread fell behind).
      std::snprintf(buf, sizeof buf, "%.1f fps, %lld keyframes, %llu dropped%s",
                    static_cast<double>(analysed - lastAnalysed) / el,
                    static_cast<long long>(stats_.written.load()),
                    static_cast<unsigned long long>(queue_->dropped() + capture_->stats().noBuffer +
                                                    lostInCamera()),
                    framesArrive || !ready_ ? "" : ", no frames");
      notifier_.status(buf);
      lastStatus = now;
      if (telemetry_) publishPose();
      lastAnalysed = analysed;
    }
    if (analysisFailed_.load()) {
      state = "failed";
      break;
    }
    if (!capture_->running()) {
      if (!capture_->ended()) {
        KF_LOG(Capture, Error) << "capture stopped: " << capture_->lastError();
        state = "capture_failed";
      }
      break;
    }
  }
  notifier_.stopping("flushing");
  // A source stuck in a read it cannot interrupt (a pipe whose writer went silent) must
  // not keep the rest from flushing: it is left behind, and the process exits past it.
  constexpr std::chrono::milliseconds kCaptureStopWait{2000};
  const bool captureStopped = capture_->stopWithin(kCaptureStopWait);
  if (!captureStopped) {
    KF_LOG(Capture, Warning) << "the source did not stop within " << kCaptureStopWait.count() / 1000
                             << " s (blocked in a read): flushing without it";
  }
  queue_->close();
  // A signal: stop now, keep the candidate. A failed capture: the frames before the
  // failure are good, analyse them all.
  if (state == "stopped") stopAnalysis_.store(true);
  analysis.join();
  output.join();
  leftAtStop_ = queue_->size();  // a stop does not wait for them: counted, not analysed
  if (analysisFailed_.load()) state = "failed";  // it may have failed while flushing
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  bool ok = true;
  if (!log_.close(error)) {
    KF_LOG(Output, Error) << error;
    ok = false;
  }
  if (!writer_.close(error)) {
    KF_LOG(Output, Error) << error;
    ok = false;
  }
  logSavedLate();
  if (telemetry_) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));  // last capture reports
    telemetry_->stop();
    telemetry_->setRawSink({});
  }
  // The summary before the flight record and the link close: a congested link may hold
  // the stop for seconds, and the summary is on disk whatever happens then.
  if (!writeSummary(seconds, state, error)) {
    KF_LOG(Output, Error) << error;
    ok = false;
  }
  // A recorder that failed said so (its error line) when it happened: not again here.
  static_cast<void>(outputs_.close(state, error));
  // A keyframe or decision row that could not be saved (a full disk, an I/O error):
  // the run's outputs are not complete, whatever else went well.
  if (const std::int64_t failed = stats_.writeErrors.load(); failed > 0) {
    const std::int64_t unsaved = writer_.count() - writer_.saved();
    KF_LOG(Output, Error) << failed << " writes failed in this run, "
                          << (unsaved > 0 ? std::to_string(unsaved) + " keyframes not saved"
                                          : "every keyframe saved in the end")
                          << (writer_.savedLate() > 0 ? " (" + std::to_string(writer_.savedLate()) +
                                                            " saved late, once the disk had room)"
                                                      : std::string());
    ok = false;
  }
  const CaptureThread::Stats cs = capture_->stats();
  KF_LOG(App, Notice) << "stopped (" << state << "): " << cs.captured << " frames captured, "
                      << queue_->dropped() + cs.noBuffer << " dropped, " << lostInCamera()
                      << " lost in the camera, " << writer_.count() << " keyframes"
                      << (writer_.saved() != writer_.count()
                              ? " (" + std::to_string(writer_.saved()) + " saved)"
                              : std::string())
                      << " in " << flightDir_;
  const int rc = !ok || state == "capture_failed" || state == "failed" ? 1 : 0;
  if (!captureStopped) {
    // Everything is flushed; the capture thread still holds the source, the pool and
    // the queue, so nothing of it may be destroyed: leave without destructors.
    std::fflush(nullptr);
    std::_Exit(rc);
  }
  return rc;
}

}  // namespace

int runMain(const std::vector<std::string>& argsIn) {
  // Blocked from the start, before the configuration loads and OpenCV starts its
  // threads (which inherit the mask): a SIGHUP (systemctl reload) or SIGTERM in the
  // first few hundred ms would otherwise kill the process with the default action.
  // Daemon::run takes them with sigtimedwait.
  sigset_t early;
  sigemptyset(&early);
  for (const int s : {SIGINT, SIGTERM, SIGHUP}) sigaddset(&early, s);
  pthread_sigmask(SIG_BLOCK, &early, nullptr);
  std::vector<std::string> args = argsIn;
  ConfigSources sources;
  if (std::string e = takeConfigArgs(args, sources); !e.empty()) {
    std::fprintf(stderr, "keyframed run: %s\n", oneLine(e).c_str());
    return 2;
  }
  for (const auto& a : args) {
    if (a == "-h" || a == "--help") {
      std::fputs(kUsage, stdout);
      return 0;
    }
    std::fprintf(stderr, "keyframed run: unknown argument '%s' (see keyframed run --help)\n",
                 oneLine(a).c_str());
    return 2;
  }
  cv::utils::logging::setLogLevel(cv::utils::logging::LOG_LEVEL_ERROR);
  // OpenCV's calls run on the thread that makes them, not on a pool of its own: the
  // daemon's threads are the ones DESIGN.md lists, each stage's CPU is its thread's
  // (the file source's colour conversion counts as decoding), and no pool spins.
  cv::setNumThreads(1);
  ConfigLoadResult r = loadConfig(sources);
  if (!r.ok()) {
    for (const auto& e : r.errors) std::fprintf(stderr, "keyframed: %s\n", e.c_str());
    return kExitConfig;
  }
  if (std::string w = logging::configure(r.config.log); !w.empty()) {
    std::fprintf(stderr, "keyframed: %s\n", w.c_str());
  }
  Daemon daemon(std::move(r.config), std::move(sources));
  return daemon.run();
}

}  // namespace keyframed
