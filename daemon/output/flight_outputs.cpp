#include "output/flight_outputs.h"

#include <chrono>
#include <cmath>
#include <cstdio>
#include <string_view>

#include "app/log_throttle.h"
#include "app/text_io.h"
#include "tagging/camera_model_toml.h"
#include "tagging/camera_mount.h"
#include "telemetry/pose.h"

#ifdef KEYFRAMED_HAVE_IO
#include <atomic>
#include <condition_variable>
#include <deque>
#include <mutex>
#include <optional>
#include <thread>
#include <utility>
#include <vector>

#include "core/thread_name.h"
#include "output/foxglove_proto.h"
#include "output/h264.h"
#include "output/keyframe_publisher.h"
#include "output/mcap_recorder.h"
#endif

namespace keyframed {

#ifdef KEYFRAMED_HAVE_IO
namespace {

constexpr const char* kCameraFrame = "camera";

// CLOCK_MONOTONIC (libstdc++'s steady_clock), the clock of a live run's frames.
std::int64_t wallNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

std::int64_t unixNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

proto::LogLevel foxgloveLevel(int syslogLevel) {
  if (syslogLevel <= 3) return proto::LogLevel::Error;
  if (syslogLevel == 4) return proto::LogLevel::Warning;
  if (syslogLevel <= 6) return proto::LogLevel::Info;
  return proto::LogLevel::Debug;
}

std::string num(double v, int decimals) {
  if (!std::isfinite(v)) return "";
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, v);
  return buf;
}

std::string jnum(double v, int decimals) {
  const std::string s = num(v, decimals);
  return s.empty() ? "null" : s;
}

}  // namespace

struct FlightOutputs::Impl {
  struct Scores {
    std::int64_t index = -1;  // the frame's; -1: none
    double sharpness = 0, threshold = 0, overlap = 0;
    int features = 0;
    const char* reason = "";
  };
  FlightOutputOptions options;
  std::unique_ptr<McapRecorder> recorder;
  std::unique_ptr<KeyframePublisher> publisher;
  // The newest frames' scores, for a keyframe's metadata: the last kMaxScores by
  // frame index, and the fallback candidate's, however long no keyframe comes (a
  // vehicle standing on the ground for an hour). A ring made once: nothing is
  // allocated per frame.
  static constexpr std::size_t kMaxScores = 1800;
  std::vector<Scores> scores = std::vector<Scores>(kMaxScores);
  Scores candidate;
  [[nodiscard]] const Scores* scoresOf(std::int64_t index) const {
    const Scores& s = scores[static_cast<std::size_t>(index) % kMaxScores];
    if (s.index == index) return &s;
    return candidate.index == index ? &candidate : nullptr;
  }
  std::int64_t lastStatusNs = 0;
  std::string taggingLines;  // tagging(): for every settings message
  std::string cameraToml;
  std::int64_t lastPreviewNs = 0;
  std::int64_t framesRead = 0;
  std::int64_t kept = 0;
  // Failed keyframe puts: every keyframe is still tried; the log gets one line at
  // most every 10 s, with the count since the last line. Under failMutex: a put thread
  // left blocked at close() (abandoned) may still count one when its put ends.
  std::mutex failMutex;
  std::int64_t publishFailures = 0;
  LogThrottle publishFailureLog;
  KeyframePut putForTesting;
  // A live run puts keyframes on a thread of their own: a Block put waits while the
  // link is congested (up to Zenoh's own timeout, seconds), and must not hold up the
  // output thread, and through it analysis and capture. At most kMaxQueuedPuts wait;
  // past that a keyframe is left to the queryable (it is on disk, and the ground
  // station fetches it when it sees the gap). An offline run puts in line.
  struct Put {
    std::int64_t sequence;
    std::vector<std::uint8_t> jpeg;
    std::string meta;
    bool onDisk = true;  // the queryable can serve it (else the link is its only way out)
  };
  static constexpr std::size_t kMaxQueuedPuts = 8;
  // Keyframes the disk did not take wait for the link past kMaxQueuedPuts (the link is
  // their way out), but not past this many bytes: a full disk over a slow radio would
  // grow the queue by the keyframe rate for as long as it lasts. Past it they are
  // served by the queryable from memory (KeyframePublisher::keepUnsaved).
  static constexpr std::size_t kMaxQueuedPutBytes = 32u << 20;
  std::mutex putMutex;
  std::condition_variable putCv;
  std::deque<Put> puts;
  std::size_t putBytes = 0;   // the JPEGs in puts
  std::int64_t putting = -1;  // the sequence number being put, -1: none
  // Of `count` keyframes, how many are out: put, or left to the queryable. Not those
  // still queued (nor any after the first of them): a ground station told of them
  // would ask the queryable for what is on its way, doubling it on a slow link.
  std::int64_t keyframesOut(std::int64_t count) {
    std::lock_guard lock(putMutex);
    std::int64_t out = count;
    if (putting >= 0) out = std::min(out, putting);
    if (!puts.empty()) out = std::min(out, puts.front().sequence);
    return out;
  }
  bool putStop = false;
  bool putDone = false;  // putLoop has returned (putDoneCv)
  std::condition_variable putDoneCv;
  // A put still blocked on a congested link this long after the drain time is left
  // behind (the thread, this Impl and the publisher it uses with it): a stop must end
  // within systemd's TimeoutStopSec (15 s), and Zenoh holds a blocked put for
  // block.wait_before_close (60 s) per batch.
  static constexpr auto kStopGrace = std::chrono::seconds(3);
  bool abandoned = false;
  std::chrono::steady_clock::time_point putDrainEnd;  // (stopping) put nothing after it
  std::int64_t putsSkippedAtStop = 0;                 // left to the queryable at close()
  std::thread putThread;
  std::int64_t putsSkipped = 0;  // left to the queryable (output thread)
  LogThrottle putSkipLog;

  void put(std::int64_t sequence, std::span<const std::uint8_t> jpeg, const std::string& meta) {
    // Every keyframe is put, whatever happened to the one before: Zenoh reconnects by
    // itself, and a ground station fetches what it missed from the queryable.
    std::string error;
    const bool ok = putForTesting ? putForTesting(jpeg, meta, error)
                                  : publisher->publishKeyframe(sequence, jpeg, meta, error);
    if (!ok) {
      std::optional<std::uint64_t> held;
      std::int64_t failures = 0;
      {
        const std::lock_guard failLock(failMutex);
        failures = ++publishFailures;
        held = publishFailureLog.pass("", wallNs());
      }
      if (held) {
        warn("zenoh: keyframe " + std::to_string(sequence) + " not published: " + error + " (" +
             std::to_string(*held + 1) + " failed since the last report, " +
             std::to_string(failures) + " in all)");
      }
    }
  }
  void putLoop() {
    std::unique_lock lock(putMutex);
    while (true) {
      putCv.wait(lock, [this] { return putStop || !puts.empty(); });
      if (puts.empty()) return;  // stopping, all put
      if (putStop && std::chrono::steady_clock::now() >= putDrainEnd) {
        // Stopping and out of time: those on disk are left to the queryable; one the
        // disk did not take has no other way out, and is still put.
        const auto before = puts.size();
        std::erase_if(puts, [this](const Put& q) {
          if (q.onDisk) putBytes -= q.jpeg.size();
          return q.onDisk;
        });
        putsSkippedAtStop += static_cast<std::int64_t>(before - puts.size());
        if (puts.empty()) return;
      }
      Put p = std::move(puts.front());
      puts.pop_front();
      putBytes -= p.jpeg.size();
      putting = p.sequence;
      lock.unlock();
      put(p.sequence, p.jpeg, p.meta);
      lock.lock();
      putting = -1;
    }
  }
  // The keyframes still queued are put before it returns, for the drain time (and
  // kStopGrace more for the put under way); false when a put was still blocked then,
  // and the thread was left to it (abandoned).
  bool stopPuts() {
    std::unique_lock lock(putMutex);
    putStop = true;
    putDrainEnd = std::chrono::steady_clock::now() +
                  std::chrono::milliseconds(std::max(options.stopDrainMs, 0));
    putCv.notify_all();
    if (!putThread.joinable()) return true;
    if (!putDoneCv.wait_until(lock, putDrainEnd + kStopGrace, [this] { return putDone; })) {
      lock.unlock();
      putThread.detach();
      abandoned = true;
      return false;
    }
    lock.unlock();
    putThread.join();
    return true;
  }
  void runPuts() {
    putLoop();
    std::lock_guard lock(putMutex);
    putDone = true;
    putDoneCv.notify_all();
  }
  // The record's "now" on the callers' clock: a live run reads CLOCK_MONOTONIC,
  // an offline run the time of the latest frame.
  std::atomic<std::int64_t> frameNs{0};
  std::mutex logMutex;  // log() (any thread) against close() taking the recorder away

  std::int64_t nowNs() const { return options.liveClock ? wallNs() : frameNs.load(); }
  // ,"flight":"ID" for a status message, or nothing without a flight id.
  std::string flightField() const {
    return options.flight.empty() ? std::string() : ",\"flight\":\"" + options.flight + "\"";
  }
  void note(const std::string& message) const {
    if (options.note) {
      options.note(message);
    } else {
      std::fprintf(stderr, "keyframed: %s\n", message.c_str());
    }
  }
  void error(const std::string& message) const {
    if (options.error) {
      options.error(message);
    } else {
      warn(message);
    }
  }
  void warn(const std::string& message) const {
    if (options.warn) {
      options.warn(message);
    } else {
      std::fprintf(stderr, "keyframed: %s\n", message.c_str());
    }
  }
};

FlightOutputs::FlightOutputs() : impl_(std::make_unique<Impl>()) {}

FlightOutputs::~FlightOutputs() {
  std::string ignored;
  close("stopped", ignored);
  // A put left blocked at the stop still uses the Impl (and its publisher): kept for
  // it, as the process ends.
  if (impl_->abandoned) static_cast<void>(impl_.release());
}

bool FlightOutputs::active() const {
  return impl_->recorder != nullptr || impl_->publisher != nullptr;
}

bool FlightOutputs::recording() const {
  return impl_->recorder != nullptr && !impl_->recorder->failed();
}

std::uint64_t FlightOutputs::recordedMessages() const {
  return impl_->recorder != nullptr ? impl_->recorder->stats().written : 0;
}

bool FlightOutputs::open(const FlightOutputOptions& o, int width, int height,
                         const CameraModel* camera, std::string& error) {
  impl_->options = o;
  // MCAP log times are unix time (what Foxglove and `mcap info` show).
  if (o.liveClock) impl_->options.unixOffsetNs = unixNs() - wallNs();
  impl_->frameNs.store(o.startNs);
  if (!o.mcapPath.empty()) {
    McapRecorderOptions ro;
    ro.path = o.mcapPath;
    ro.fsync = o.mcapFsync;
    ro.compression = o.mcapCompression;
    ro.timeOffsetNs = impl_->options.unixOffsetNs;
    ro.blockWhenFull = o.offline;
    ro.onNewPart = [impl = impl_.get()](const std::string& path) {
      impl->note("MCAP: recording continues in " + path);
    };
    ro.onFailure = [impl = impl_.get()](const std::string& line) { impl->error(line); };
    ro.rotateBytes = o.mcapRotateBytes;
    ro.rotateSeconds = o.mcapRotateSeconds;
    auto rec = std::make_unique<McapRecorder>();
    if (!rec->open(ro, error)) {
      error = "--mcap: " + error;
      return false;
    }
    impl_->recorder = std::move(rec);
    if (camera != nullptr && camera->calibrated()) {
      // Intrinsics at the video's resolution, as the keyframes carry them.
      const CameraModel c = (camera->width != width || camera->height != height)
                                ? camera->scaledTo(width, height)
                                : *camera;
      proto::CameraCalibrationMsg m;
      m.frameId = kCameraFrame;
      m.width = static_cast<std::uint32_t>(width);
      m.height = static_cast<std::uint32_t>(height);
      m.d = c.distortion;
      // Otherwise plumb_bob: a camera model carries k1 k2 p1 p2 k3 at most.
      if (c.lens == CameraModel::Lens::Fisheye) {
        m.distortionModel = "kannala_brandt";  // OpenCV's fisheye k1..k4
      }
      m.k = {c.fx, 0, c.cx, 0, c.fy, c.cy, 0, 0, 1};
      m.p = {c.fx, 0, c.cx, 0, 0, c.fy, c.cy, 0, 0, 0, 1, 0};
      m.timeNs = impl_->nowNs() + impl_->options.unixOffsetNs;
      impl_->recorder->record(McapTopic::Calibration, impl_->nowNs(), proto::cameraCalibration(m));
    }
    log(6, "output",
        "recording started (" + std::to_string(width) + "x" + std::to_string(height) + ")");
  }
  if (o.zenoh || !o.zenohConfig.empty()) {
    KeyframePublisherOptions po;
    po.configFile = o.zenohConfig;
    po.vehicle = o.vehicle;
    po.keyframeDir = o.keyframeDir;
    po.flight = o.flight;
    po.flightsDir = o.flightsDir;
    po.retryMs = o.zenohRetryMs;
    po.onLate = [impl = impl_.get()](const std::string& message) { impl->note(message); };
    po.keyframesOut = [impl = impl_.get()](std::int64_t n) { return impl->keyframesOut(n); };
    impl_->publisher = KeyframePublisher::open(po, error);
    if (!impl_->publisher) {
      error = o.zenohSetting + ": " + error;
      impl_->recorder.reset();
      return false;
    }
    if (!impl_->publisher->live()) {
      // Recording and keyframes go on; the ground station fetches what it missed.
      const int ms = o.zenohRetryMs;
      impl_->warn(o.zenohSetting + ": " + error + "; trying again every " +
                  (ms % 1000 == 0 ? std::to_string(ms / 1000) + " s" : std::to_string(ms) + " ms") +
                  ", publishing nothing until then");
      error.clear();
    }
    std::string ignored;
    impl_->publisher->publishStatus(
        "{\"state\":\"running\",\"frames\":0,\"kept\":0" + impl_->flightField() + "}", ignored);
    if (!o.offline)
      impl_->putThread = std::thread([impl = impl_.get()] {
        nameThisThread("kf-zenoh-put");
        impl->runPuts();
      });
  }
  return true;
}

void FlightOutputs::decision(const Decision& d) {
  if (!impl_->options.liveClock) impl_->frameNs.store(d.timestampNs);
  if (active()) {
    if (d.index >= 0) {
      const Impl::Scores s{d.index,   d.sharpness, d.threshold,
                           d.overlap, d.features,  toString(d.reason)};
      impl_->scores[static_cast<std::size_t>(d.index) % Impl::kMaxScores] = s;
      if (d.candidate) impl_->candidate = s;
    }
  }
}

void FlightOutputs::recordDecision(const Decision& d, const std::string& decisionJson) {
  if (impl_->recorder)
    impl_->recorder->recordText(McapTopic::Decision, d.timestampNs, decisionJson);
}

void FlightOutputs::mavlink(std::int64_t timeNs, std::uint32_t systemId, std::uint32_t componentId,
                            std::uint32_t messageId, std::span<const std::uint8_t> packet) {
  if (McapRecorder* r = impl_->recorder.get())
    r->record(McapTopic::Mavlink, timeNs,
              proto::mavlinkPacket(timeNs, systemId, componentId, messageId, packet,
                                   r->buffer(packet.size() + 32)));
}

void FlightOutputs::vehicleLocation(std::int64_t timeNs, double latDeg, double lonDeg,
                                    double altAmslM) {
  if (!impl_->recorder) return;
  proto::LocationFixMsg f;
  f.timeNs = timeNs;
  f.frameId = "vehicle";
  f.latitude = latDeg;
  f.longitude = lonDeg;
  f.altitude = altAmslM;
  impl_->recorder->record(McapTopic::VehicleLocation, timeNs,
                          proto::locationFix(f, impl_->recorder->buffer(160 + f.frameId.size())));
}

void FlightOutputs::vehicleAttitude(std::int64_t timeNs, const Quaternion& q) {
  if (McapRecorder* r = impl_->recorder.get())
    r->record(McapTopic::VehiclePose, timeNs,
              proto::poseInFrame(timeNs, "ned", {0, 0, 0}, {q.x, q.y, q.z, q.w}, r->buffer(128)));
}

void FlightOutputs::settings(std::int64_t timeNs, const std::string& selectionLines) {
  if (!impl_->recorder) return;
  std::string json = "{\"selection\":\"" + jsonEscape(selectionLines) + "\"";
  if (!impl_->taggingLines.empty())
    json += ",\"tagging\":\"" + jsonEscape(impl_->taggingLines) + "\"";
  if (!impl_->cameraToml.empty()) json += ",\"camera\":\"" + jsonEscape(impl_->cameraToml) + "\"";
  impl_->recorder->recordText(McapTopic::Settings, timeNs, json + "}");
}

void FlightOutputs::tagging(const std::string& taggingLines, const CameraModel* camera) {
  impl_->taggingLines = taggingLines;
  impl_->cameraToml = camera != nullptr ? "[camera]\n" + cameraTomlKeys(*camera) : std::string();
}

void FlightOutputs::preview(std::int64_t timeNs, std::span<const std::uint8_t> image,
                            const char* format) {
  const std::string_view kind(format);
  if (McapRecorder* r = impl_->recorder.get()) {
    // As much as the message builders reserve: a buffer that fits is not grown.
    std::vector<std::uint8_t> into = r->buffer(image.size() + 64 + std::strlen(kCameraFrame));
    if (kind == "h264")
      r->record(McapTopic::Video, timeNs,
                proto::compressedVideo(timeNs, kCameraFrame, image, format, std::move(into)), 0,
                h264HasIdr(image));
    else
      r->record(McapTopic::Preview, timeNs,
                proto::compressedImage(timeNs, kCameraFrame, image, format, std::move(into)));
  }
  // PNG (lossless, full size) and H.264 pictures reach Zenoh as a previewStill().
  if (kind == "jpeg") previewStill(image);
}

bool FlightOutputs::previewStillDue() const {
  return impl_->publisher && wallNs() - impl_->lastPreviewNs >= 500'000'000;
}

void FlightOutputs::previewStill(std::span<const std::uint8_t> jpeg) {
  if (!previewStillDue()) return;
  impl_->lastPreviewNs = wallNs();
  std::string ignored;
  impl_->publisher->publishPreview(jpeg, ignored);
}

void FlightOutputs::telemetry(const std::string& json) {
  if (!impl_->publisher) return;
  std::string ignored;
  impl_->publisher->publishTelemetry(json, ignored);
}

bool FlightOutputs::publishing() const {
  return impl_->publisher != nullptr;
}

void FlightOutputs::keyframe(const KeyframeRecord& rec, std::span<const std::uint8_t> jpeg) {
  if (!active()) return;
  ++impl_->kept;
  KeyframeMeta m;
  m.vehicle = impl_->options.vehicle;
  m.flight = impl_->options.flight;
  m.sequence = rec.sequence;
  m.frameIndex = rec.frameIndex;
  m.file = KeyframeWriter::fileName(rec.frameIndex);
  m.timeNs = rec.timeNs;
  m.decidedNs = rec.decidedNs;
  const Pose& p = rec.pose;
  if (p.utcUs) m.utcUs = std::to_string(*p.utcUs);
  if (p.position) {
    m.lat = num(p.position->latDeg, 9);
    m.lon = num(p.position->lonDeg, 9);
    m.altAmsl = num(p.position->altAmslM, 4);
    m.altRel = num(p.position->altRelM, 4);
  }
  if (rec.cameraToNed) {
    const Quaternion& q = *rec.cameraToNed;
    m.camQw = num(q.w, 9);
    m.camQx = num(q.x, 9);
    m.camQy = num(q.y, 9);
    m.camQz = num(q.z, 9);
    const Pix4dAngles a = pix4dAngles(q);
    m.yaw = num(a.yawDeg, 4);
    m.pitch = num(a.pitchDeg, 4);
    m.roll = num(a.rollDeg, 4);
  }
  m.hdop = num(p.gps.hdop, 2);
  if (p.position) m.fixType = std::to_string(p.gps.fixType);
  m.geotag = rec.geotag;
  if (const Impl::Scores* found = impl_->scoresOf(rec.frameIndex)) {
    const Impl::Scores& s = *found;
    m.scoresJson = "{\"sharpness\":" + jnum(s.sharpness, 3) +
                   ",\"threshold\":" + jnum(s.threshold, 3) + ",\"overlap\":" + jnum(s.overlap, 4) +
                   ",\"features\":" + std::to_string(s.features) + ",\"reason\":\"" + s.reason +
                   "\"}";
  }
  const std::string meta = toJson(m);

  if (impl_->recorder) {
    impl_->recorder->record(McapTopic::Keyframe, rec.timeNs,
                            proto::compressedImage(rec.timeNs, kCameraFrame, jpeg, "jpeg"),
                            static_cast<std::uint32_t>(rec.sequence + 1));
    impl_->recorder->recordText(McapTopic::KeyframeMeta, rec.timeNs, meta);
    if (p.position) {
      proto::LocationFixMsg f;
      f.timeNs = rec.timeNs;
      f.frameId = kCameraFrame;
      f.latitude = p.position->latDeg;
      f.longitude = p.position->lonDeg;
      f.altitude = p.position->altAmslM;
      if (std::isfinite(p.gps.hAccuracyM) && std::isfinite(p.gps.vAccuracyM)) {
        const double h = p.gps.hAccuracyM * p.gps.hAccuracyM;
        f.varianceEnu = std::array<double, 3>{h, h, p.gps.vAccuracyM * p.gps.vAccuracyM};
      }
      impl_->recorder->record(McapTopic::Location, rec.timeNs, proto::locationFix(f));
    }
    if (rec.cameraToNed) {
      const Quaternion& q = *rec.cameraToNed;
      impl_->recorder->record(
          McapTopic::CameraPose, rec.timeNs,
          proto::poseInFrame(rec.timeNs, "ned", {0, 0, 0}, {q.x, q.y, q.z, q.w}));
    }
  }
  if (!impl_->publisher) return;
  // Not on disk for the queryable (a full disk took the JPEG or its index row): it
  // serves this one from memory.
  if (!rec.indexed) impl_->publisher->keepUnsaved(rec.sequence, jpeg, meta);
  if (impl_->options.offline) {
    impl_->put(rec.sequence, jpeg, meta);
    return;
  }
  // Its metadata for a query from now on, queued or left to the queryable: one that
  // overtakes the put (the ground station asking for a gap) gets the live message's.
  impl_->publisher->remember(rec.sequence, meta);
  {
    std::lock_guard lock(impl_->putMutex);
    // One that could not be saved (a full disk) is not on disk for the queryable: the
    // link is its only way out, so it waits for the link whatever the queue holds.
    if (impl_->puts.size() < Impl::kMaxQueuedPuts ||
        (!rec.indexed && impl_->putBytes + jpeg.size() <= Impl::kMaxQueuedPutBytes)) {
      impl_->putBytes += jpeg.size();
      impl_->puts.push_back({rec.sequence, {jpeg.begin(), jpeg.end()}, meta, rec.indexed});
      impl_->putCv.notify_one();
      return;
    }
  }
  ++impl_->putsSkipped;
  if (const auto held = impl_->putSkipLog.pass("", wallNs())) {
    impl_->warn("zenoh: the link is too slow, keyframe " + std::to_string(rec.sequence) +
                " left to the queryable (" + std::to_string(*held + 1) +
                " since the last report, " + std::to_string(impl_->putsSkipped) + " in all)");
  }
}

void FlightOutputs::keyframesIndexedLate(std::span<const std::int64_t> sequences) {
  if (impl_->publisher && !sequences.empty()) impl_->publisher->forgetUnsaved(sequences);
}

void FlightOutputs::log(int level, std::string_view category, std::string_view message) {
  std::lock_guard lock(impl_->logMutex);
  McapRecorder* recorder = impl_->recorder.get();
  if (recorder == nullptr) return;
  const std::int64_t t = impl_->nowNs();
  recorder->tryRecord(McapTopic::Log, t,
                      proto::log(t + impl_->options.unixOffsetNs, foxgloveLevel(level),
                                 std::string(message), "keyframed." + std::string(category)));
}

void FlightOutputs::setKeyframePutForTesting(KeyframePut put) {
  impl_->putForTesting = std::move(put);
}

std::int64_t FlightOutputs::keyframesOut(std::int64_t kept) const {
  return impl_->keyframesOut(kept);
}

void FlightOutputs::progress(std::int64_t framesRead, std::int64_t kept) {
  impl_->framesRead = framesRead;
  if (!impl_->publisher) return;
  const std::int64_t now = wallNs();
  if (now - impl_->lastStatusNs < 1'000'000'000) return;
  impl_->lastStatusNs = now;
  std::string ignored;
  impl_->publisher->publishStatus(
      "{\"state\":\"running\",\"frames\":" + std::to_string(framesRead) +
          ",\"kept\":" + std::to_string(keyframesOut(kept)) + impl_->flightField() + "}",
      ignored);
}

bool FlightOutputs::close(const std::string& state, std::string& error) {
  bool ok = true;
  // What is queued goes out before the final status (for a while).
  if (!impl_->abandoned && !impl_->stopPuts()) {
    impl_->warn(
        "zenoh: a keyframe put still blocked on the congested link after the stop's drain "
        "time was left behind (the keyframe is on disk: a later run's queryable serves it)");
  }
  std::int64_t skippedAtStop = 0;
  {
    // Under the lock: a put thread left blocked (abandoned) still counts these.
    const std::lock_guard putLock(impl_->putMutex);
    skippedAtStop = std::exchange(impl_->putsSkippedAtStop, 0);
  }
  if (skippedAtStop > 0) {
    impl_->warn("zenoh: " + std::to_string(skippedAtStop) +
                " keyframes still queued for the link at the stop left to the queryable "
                "(on disk; the next run serves them with flight=ID)");
  }
  if (impl_->putsSkipped > 0) {
    impl_->warn("zenoh: " + std::to_string(impl_->putsSkipped) +
                " keyframes left to the queryable in this flight (the link was too slow)");
    impl_->putsSkipped = 0;
  }
  std::uint64_t failuresHeldBack = 0;
  std::int64_t failures = 0;
  {
    const std::lock_guard failLock(impl_->failMutex);
    failuresHeldBack = impl_->publishFailureLog.heldBack();
    failures = impl_->publishFailures;
    impl_->publishFailureLog.reset();
  }
  if (impl_->publisher && !impl_->publisher->live()) {
    impl_->warn("zenoh: no session opened in this flight: its " + std::to_string(impl_->kept) +
                " keyframes were not published (they are on disk; a later run's queryable "
                "serves them with flight=ID)");
  } else if (failuresHeldBack > 0) {
    impl_->warn("zenoh: " + std::to_string(failures) +
                " keyframe puts failed in this flight (the queryable serves them)");
  }
  if (impl_->publisher) {
    // Reliable, waiting, unless a put was left blocked: then it would wait behind it.
    std::string ignored;
    impl_->publisher->publishStatus(
        "{\"state\":\"" + state + "\",\"frames\":" + std::to_string(impl_->framesRead) +
            ",\"kept\":" + std::to_string(impl_->kept) + impl_->flightField() + "}",
        ignored, /*last=*/!impl_->abandoned);
  }
  std::unique_ptr<McapRecorder> recorder;
  {
    std::lock_guard lock(impl_->logMutex);
    recorder = std::move(impl_->recorder);
  }
  if (recorder) {
    ok = recorder->close(error);
    if (const std::uint64_t dropped = recorder->stats().dropped; dropped > 0) {
      impl_->warn("MCAP: " + std::to_string(dropped) +
                  " messages not recorded (the writer fell behind or stopped; a live run drops "
                  "rather than stall)");
    }
  }
  // The publisher last: closing its queryable finishes the query being answered,
  // which on a slow link can take long, and drops those still queued (their queriers
  // get no reply and ask again); the record is complete by then. One a put left
  // blocked still uses stays, as the process ends.
  if (impl_->abandoned)
    static_cast<void>(impl_->publisher.release());
  else
    impl_->publisher.reset();
  return ok;
}

std::string zenohConfigError(const std::string& path) {
  std::string error;
  if (ZenohSession::checkConfigFile(path, error)) return {};
  return error;
}

#else  // built without the Rust I/O crate

std::string zenohConfigError(const std::string&) {
  return {};
}

struct FlightOutputs::Impl {};

FlightOutputs::FlightOutputs() : impl_(std::make_unique<Impl>()) {}
FlightOutputs::~FlightOutputs() = default;

bool FlightOutputs::active() const {
  return false;
}
bool FlightOutputs::recording() const {
  return false;
}

std::uint64_t FlightOutputs::recordedMessages() const {
  return 0;
}

bool FlightOutputs::open(const FlightOutputOptions& o, int, int, const CameraModel*,
                         std::string& error) {
  if (!o.mcapPath.empty() || !o.zenohConfig.empty() || o.zenoh) {
    error = "this keyframed was built without MCAP and Zenoh support (KEYFRAMED_WITH_IO=OFF)";
    return false;
  }
  return true;
}
void FlightOutputs::decision(const Decision&) {}
void FlightOutputs::recordDecision(const Decision&, const std::string&) {}
void FlightOutputs::keyframe(const KeyframeRecord&, std::span<const std::uint8_t>) {}
void FlightOutputs::keyframesIndexedLate(std::span<const std::int64_t>) {}
void FlightOutputs::preview(std::int64_t, std::span<const std::uint8_t>, const char*) {}
bool FlightOutputs::previewStillDue() const {
  return false;
}
void FlightOutputs::previewStill(std::span<const std::uint8_t>) {}
void FlightOutputs::settings(std::int64_t, const std::string&) {}
void FlightOutputs::tagging(const std::string&, const CameraModel*) {}
void FlightOutputs::telemetry(const std::string&) {}
bool FlightOutputs::publishing() const {
  return false;
}
void FlightOutputs::mavlink(std::int64_t, std::uint32_t, std::uint32_t, std::uint32_t,
                            std::span<const std::uint8_t>) {}
void FlightOutputs::vehicleLocation(std::int64_t, double, double, double) {}
void FlightOutputs::vehicleAttitude(std::int64_t, const Quaternion&) {}
void FlightOutputs::progress(std::int64_t, std::int64_t) {}
void FlightOutputs::log(int, std::string_view, std::string_view) {}
bool FlightOutputs::close(const std::string&, std::string&) {
  return true;
}
void FlightOutputs::setKeyframePutForTesting(KeyframePut) {}

#endif

}  // namespace keyframed
