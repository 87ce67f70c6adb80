#include "telemetry/telemetry_service.h"

#include <algorithm>
#include <climits>
#include <cstdio>
#include <cstring>
#include <limits>
#include <vector>

#include "core/thread_name.h"
#include "telemetry/tlog.h"

namespace keyframed {

namespace {
constexpr std::int64_t kSecond = 1'000'000'000;
// Requests are remembered for 10 s, however many: at 40 Hz (before the clock has
// settled) a count of 16 forgot a request after 0.4 s, and a slow radio link (a
// 57600-baud telemetry radio with a queue) answers later than that, so that every
// answer was refused. The count only bounds memory.
constexpr std::size_t kTimesyncRequestsKept = 512;
constexpr std::int64_t kTimesyncRequestAgeNs = 10 * kSecond;
// A drifting clock offset is logged at most every 10 s, when it moved by 5 ms.
constexpr std::int64_t kClockLogIntervalNs = 10 * kSecond;
constexpr std::int64_t kClockLogChangeNs = 5'000'000;
constexpr std::int64_t kSilenceNs = 3 * kSecond;  // no bytes this long: the link is down
constexpr std::int64_t kCaptureWarningIntervalNs = 10 * kSecond;
// A single-capture command repeating the last one's sender and sequence number within
// this time is a retransmission (its acknowledgement was lost), not a new request.
constexpr std::int64_t kCaptureRepeatNs = 10 * kSecond;

std::string formatMs(double ms, int decimals = 3) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f ms", decimals, ms);
  return buf;
}

std::string formatHz(double hz) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%g Hz", hz);
  return buf;
}
}  // namespace

Quaternion mavlinkCameraAttitude(const Quaternion& cameraToNed) {
  // MAVLink camera axes (x optical, y right, z down) in OpenCV camera axes: x -> z,
  // y -> x, z -> y, the rotation by -120 degrees about (1, 1, 1).
  constexpr Quaternion kMavlinkToOpenCv{0.5, -0.5, -0.5, -0.5};
  return normalized(multiply(cameraToNed, kMavlinkToOpenCv));
}

TelemetryService::TelemetryService(TelemetryServiceConfig config, CameraDescription camera)
    : config_(std::move(config)),
      camera_(std::move(camera)),
      decoder_(config_.decoder),
      encoder_(std::make_unique<MavlinkEncoder>(0, 0, config_.mavlink1)) {}

TelemetryService::~TelemetryService() {
  stop();
}

bool TelemetryService::start(std::string& error) {
  auto link = openMavlinkLink(config_.url, error, config_.waitForSerialDevice);
  if (!link) return false;
  if (!error.empty()) {  // the device is not there yet
    log(TelemetryLogLevel::Warning,
        error + ": going on without telemetry; opened when it appears (tried every second)");
    error.clear();
    startUnopened_ = true;
  }
  return start(std::move(link), error);
}

bool TelemetryService::start(std::unique_ptr<MavlinkLink> link, std::string& error) {
  link_ = std::move(link);
  if (!link_) {
    error = "no MAVLink link";
    return false;
  }
  replay_ = link_->isReplay();
  startNs_ = monotonicNowNs();
  if (replay_) {
    // A recording: read it all now, with its own timestamps (unix time); the decoder
    // gets it as the frames go (advanceReplay).
    decoder_.setLocalClockIsUtc(true);
    std::vector<std::uint8_t> buf(512);
    std::size_t n = 0;
    std::int64_t t = 0;
    while (link_->read(buf.data(), buf.size(), n, t, 0, error) == MavlinkLink::Status::Data)
      replayPackets_.push_back({t, std::vector<std::uint8_t>(buf.begin(), buf.begin() + n)});
    error.clear();
    if (const std::size_t mended = mendRecordTimes(replayPackets_); mended > 0) {
      log(TelemetryLogLevel::Warning,
          config_.url + ": " + std::to_string(mended) +
              " record time(s) out of line with the records around them (a corrupt "
              "timestamp?) taken as the record's before");
    }
    std::lock_guard lock(mutex_);
    stats_.replayDone = true;
    stats_.truncated = link_->truncated();
    replaySkippedBytes_ = link_->skippedBytes();
    stats_.parser.skippedBytes = replaySkippedBytes_;
    return true;
  }
  stop_ = false;
  thread_ = std::thread([this] {
    nameThisThread("kf-telemetry");
    run();
  });
  return true;
}

void TelemetryService::startFromPackets(std::vector<TimedPacket> packets, bool utc) {
  replay_ = true;
  replayUtc_ = utc;
  decoder_.setLocalClockIsUtc(utc);
  startNs_ = monotonicNowNs();
  replayPackets_ = std::move(packets);
  std::lock_guard lock(mutex_);
  stats_.replayDone = true;
}

void TelemetryService::advanceReplay(std::int64_t localNs) {
  if (!replay_) return;
  std::lock_guard replayLock(replayMutex_);
  constexpr std::int64_t kMax = std::numeric_limits<std::int64_t>::max();
  const std::size_t from = replayFed_;
  // A tlog whose record times run ahead of the autopilot's GPS time (a station's clock
  // set wrong; the frames follow GPS time) is fed that much further ahead, one that
  // runs behind that much less far: once SYSTEM_TIME has told by how much. That may
  // change with any packet, so the limit is worked out again after each one that
  // changed it: fed to the old limit, a station minutes behind would push the
  // history past the frame's own samples (PoseStore keeps two minutes).
  for (bool again = true; again;) {
    again = false;
    const std::optional<std::int64_t> ahead = decoder_.recordClockAheadNs();
    const std::int64_t lead =
        kReplayLeadNs + std::clamp<std::int64_t>(ahead.value_or(0), -kMax / 4, kMax / 4);
    // Until SYSTEM_TIME says how far ahead the record times run, a frame time before
    // the first record feeds the records' start: a station clock further ahead than
    // the lead would otherwise never let the first SYSTEM_TIME through.
    const std::int64_t base = replayPackets_.empty() || ahead
                                  ? localNs
                                  : std::max(localNs, replayPackets_.front().timeNs);
    const std::int64_t until =
        lead >= 0 && base > kMax - lead ? kMax : std::max(base, -kMax / 2) + lead;
    while (replayFed_ < replayPackets_.size() && replayPackets_[replayFed_].timeNs <= until) {
      const TimedPacket& p = replayPackets_[replayFed_++];
      parser_.feed(p.bytes.data(), p.bytes.size(), [&](const mavlink_message_t& m) {
        decoder_.handle(m, p.timeNs);
        if (m.msgid == MAVLINK_MSG_ID_TIMESYNC && !replayUtc_) replayTimesync(m, p.timeNs);
      });
      if (decoder_.recordClockAheadNs() != ahead) {
        again = true;
        break;
      }
    }
  }
  if (replayFed_ == from) return;
  std::lock_guard lock(mutex_);
  stats_.parser = parser_.stats();
  stats_.parser.skippedBytes += replaySkippedBytes_;
}

void TelemetryService::replayTimesync(const mavlink_message_t& msg, std::int64_t timeNs) {
  // A flight record's MAVLink is on the live run's clock, TIMESYNC answers included:
  // the clock is mapped by them again, as it was live (by arrivals alone it would be
  // off by the link's smallest latency, tens of ms over a radio). The requests are
  // not in the record: an answer from the autopilot echoing a time of ours from the
  // last few seconds (as onTimesync keeps them) stands for one.
  mavlink_timesync_t ts;
  mavlink_msg_timesync_decode(&msg, &ts);
  if (ts.tc1 == 0 || msg.sysid != decoder_.autopilotSystem() ||
      msg.compid != decoder_.autopilotComponent() || ts.ts1 > timeNs ||
      timeNs - ts.ts1 > kTimesyncRequestAgeNs) {
    return;
  }
  decoder_.handleTimesync(ts.tc1, ts.ts1, timeNs);
}

void TelemetryService::stop() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
  advanceReplay(std::numeric_limits<std::int64_t>::max());
}

void TelemetryService::setRawSink(RawSink sink) {
  std::lock_guard lock(sinkMutex_);
  sink_ = std::move(sink);
}

void TelemetryService::setLogSink(LogSink sink) {
  std::lock_guard lock(logMutex_);
  logSink_ = std::move(sink);
}

void TelemetryService::log(TelemetryLogLevel level, const std::string& message) {
  std::lock_guard lock(logMutex_);
  if (logSink_) logSink_(level, message);
}

void TelemetryService::reportCapture(const CaptureReport& report) {
  std::lock_guard lock(mutex_);
  queue_.push_back(report);
  while (queue_.size() > std::max<std::size_t>(config_.maxPendingCaptures, 1)) {
    queue_.pop_front();  // the link has been down for long: keep the newest
    ++stats_.capturesDropped;
  }
  stats_.capturesPending = queue_.size();
  ++stats_.capturesReported;
}

TelemetryServiceStats TelemetryService::stats() const {
  std::lock_guard lock(mutex_);
  TelemetryServiceStats s = stats_;
  s.decoder = decoder_.stats();
  return s;
}

std::uint32_t TelemetryService::bootMs() const {
  return static_cast<std::uint32_t>((monotonicNowNs() - startNs_) / 1'000'000);
}

std::uint32_t TelemetryService::bootMsAt(std::int64_t localNs) const {
  if (const auto off = decoder_.clockOffsetNs(); off && localNs >= *off)
    return static_cast<std::uint32_t>((localNs - *off) / 1'000'000);
  return bootMs();
}

std::uint8_t TelemetryService::systemId() const {
  if (config_.systemId > 0) return static_cast<std::uint8_t>(config_.systemId);
  const int sys = decoder_.autopilotSystem();
  return static_cast<std::uint8_t>(sys > 0 ? sys : 1);
}

bool TelemetryService::send(const std::vector<std::uint8_t>& bytes) {
  if (!link_) return false;
  std::string error;
  if (link_->write(bytes.data(), bytes.size(), error)) return true;
  if (!error.empty()) {
    std::lock_guard lock(mutex_);
    ++stats_.linkErrors;
  }
  return false;
}

void TelemetryService::sendHeartbeat() {
  send(
      encoder_->encode([&](std::uint8_t, std::uint8_t, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_heartbeat_pack_status(
            systemId(), static_cast<std::uint8_t>(config_.componentId), st, m, MAV_TYPE_CAMERA,
            MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE);
      }));
}

void TelemetryService::sendTimesync(std::int64_t nowNs) {
  // Remembered so that only answers to our own requests are used.
  while (!timesyncRequests_.empty() &&
         (timesyncRequests_.size() >= kTimesyncRequestsKept ||
          timesyncRequests_.front() < nowNs - kTimesyncRequestAgeNs)) {
    timesyncRequests_.pop_front();
  }
  timesyncRequests_.push_back(nowNs);
  send(
      encoder_->encode([&](std::uint8_t, std::uint8_t, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_timesync_pack_status(systemId(), static_cast<std::uint8_t>(config_.componentId),
                                         st, m, 0, nowNs);
      }));
}

void TelemetryService::sendCameraInformation() {
  std::uint8_t vendor[32] = {};
  std::uint8_t model[32] = {};
  std::memcpy(vendor, camera_.vendor.data(), std::min<std::size_t>(31, camera_.vendor.size()));
  std::memcpy(model, camera_.model.data(), std::min<std::size_t>(31, camera_.model.size()));
  const char uri[140] = {};
  send(
      encoder_->encode([&](std::uint8_t, std::uint8_t, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_camera_information_pack_status(
            systemId(), static_cast<std::uint8_t>(config_.componentId), st, m,
            bootMsAt(monotonicNowNs()), vendor, model, 0, camera_.focalLengthMm,
            camera_.sensorWidthMm, camera_.sensorHeightMm,
            static_cast<std::uint16_t>(camera_.width), static_cast<std::uint16_t>(camera_.height),
            0, captureSink_ ? CAMERA_CAP_FLAGS_CAPTURE_IMAGE : 0, 0, uri, 0, 0);
      }));
  std::lock_guard lock(mutex_);
  ++stats_.infoSent;
}

void TelemetryService::requestMessageRates(std::int64_t nowNs) {
  if (!(config_.messageRateHz > 0.0)) return;
  // Only once the autopilot has spoken (as TIMESYNC): the commands go to the sender
  // the link heard last, and the tries would run out before it is heard.
  const int sys = decoder_.autopilotSystem();
  if (sys == 0 || !autopilotHeard_) return;
  const int who = sys << 8 | decoder_.autopilotComponent();
  const std::uint64_t reboots = decoder_.stats().reboots;
  if (who != rates_.autopilot || reboots != rates_.reboots) {  // new, or rebooted
    rates_ = {};
    rates_.autopilot = who;
    rates_.reboots = reboots;
    rates_.nextNs = nowNs;
  }
  if (rates_.done || nowNs < rates_.nextNs) return;
  constexpr int kRounds = 3;  // two seconds apart: a lost command, or one never answered
  if (rates_.rounds >= kRounds) {
    rates_.done = true;
    log(TelemetryLogLevel::Warning,
        "no answer to MAV_CMD_SET_MESSAGE_INTERVAL: the autopilot's own stream rates apply "
        "(attitude samples further apart than telemetry.attitude_gap_ms are not used)");
    return;
  }
  ++rates_.rounds;
  rates_.nextNs = nowNs + 2 * kSecond;
  const double hz = config_.messageRateHz;
  std::vector<std::pair<std::uint32_t, double>> wanted = {
      {MAVLINK_MSG_ID_ATTITUDE, hz},
      {MAVLINK_MSG_ID_GLOBAL_POSITION_INT, hz},
      {MAVLINK_MSG_ID_GPS_RAW_INT, std::min(hz, 5.0)},
      {MAVLINK_MSG_ID_SYSTEM_TIME, std::min(hz, 1.0)},
  };
  if (gimbalMount_) wanted.emplace_back(MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS, hz);
  for (const auto& w : wanted) {
    const std::uint32_t id = w.first;  // not a structured binding: clang 14 lambdas
    const float intervalUs = static_cast<float>(std::round(1e6 / w.second));
    send(encoder_->encode(
        [&](std::uint8_t, std::uint8_t, mavlink_status_t* st, mavlink_message_t* m) {
          mavlink_msg_command_long_pack_status(
              systemId(), static_cast<std::uint8_t>(config_.componentId), st, m,
              static_cast<std::uint8_t>(sys), static_cast<std::uint8_t>(who & 0xff),
              MAV_CMD_SET_MESSAGE_INTERVAL, static_cast<std::uint8_t>(rates_.rounds - 1),
              static_cast<float>(id), intervalUs, 0, 0, 0, 0, 0);
        }));
  }
  std::lock_guard lock(mutex_);
  stats_.rateRequests += wanted.size();
}

void TelemetryService::onCommandAck(const mavlink_message_t& msg) {
  mavlink_command_ack_t a;
  mavlink_msg_command_ack_decode(&msg, &a);
  const int from = msg.sysid << 8 | msg.compid;
  if (a.command != MAV_CMD_SET_MESSAGE_INTERVAL || rates_.autopilot == 0 ||
      from != rates_.autopilot || a.result == MAV_RESULT_IN_PROGRESS) {
    return;
  }
  // On a shared link the autopilot also answers a ground station's own request: one
  // addressed to another (MAVLink 2 says to whom; MAVLink 1 leaves 0) is not ours.
  if (a.target_system != 0 &&
      (a.target_system != systemId() || a.target_component != config_.componentId)) {
    return;
  }
  const bool accepted = a.result == MAV_RESULT_ACCEPTED;
  {
    std::lock_guard lock(mutex_);
    ++(accepted ? stats_.rateAccepted : stats_.rateRefused);
  }
  if (rates_.done) return;
  rates_.done = true;  // one answer is enough to know it heard us
  if (accepted) {
    log(TelemetryLogLevel::Notice, std::string("asked the autopilot for attitude and position") +
                                       (gimbalMount_ ? " and the gimbal's attitude" : "") + " at " +
                                       formatHz(config_.messageRateHz));
  } else {
    log(TelemetryLogLevel::Warning,
        "the autopilot refused MAV_CMD_SET_MESSAGE_INTERVAL (result " + std::to_string(a.result) +
            "): set its stream rates for this link (ArduPilot: SRn_EXTRA1, SRn_POSITION" +
            (gimbalMount_ ? ", SRn_EXTRA3" : "") + ") to " + formatHz(config_.messageRateHz));
  }
}

void TelemetryService::sendCommandAck(std::uint16_t command, std::uint8_t result,
                                      std::uint8_t targetSys, std::uint8_t targetComp) {
  send(encoder_->encode([&](std::uint8_t, std::uint8_t, mavlink_status_t* st,
                            mavlink_message_t* m) {
    mavlink_msg_command_ack_pack_status(systemId(), static_cast<std::uint8_t>(config_.componentId),
                                        st, m, command, result, 0, 0, targetSys, targetComp);
  }));
}

bool TelemetryService::sendCapture(const CaptureReport& r) {
  // Without a position, INT32_MAX ("unknown", as CAMERA_FOV_STATUS of the same camera
  // protocol defines it for the camera's position): never 0,0, a real place.
  std::int32_t lat = INT32_MAX, lon = INT32_MAX, alt = INT32_MAX, rel = INT32_MAX;
  if (r.pose.position) {
    lat = static_cast<std::int32_t>(std::llround(r.pose.position->latDeg * 1e7));
    lon = static_cast<std::int32_t>(std::llround(r.pose.position->lonDeg * 1e7));
    alt = static_cast<std::int32_t>(std::llround(r.pose.position->altAmslM * 1e3));
    rel = static_cast<std::int32_t>(std::llround(r.pose.position->altRelM * 1e3));
  }
  float q[4] = {NAN, NAN, NAN, NAN};
  if (r.cameraAttitude) {
    const Quaternion m = mavlinkCameraAttitude(*r.cameraAttitude);
    q[0] = static_cast<float>(m.w);
    q[1] = static_cast<float>(m.x);
    q[2] = static_cast<float>(m.y);
    q[3] = static_cast<float>(m.z);
  }
  char url[205] = {};  // the generated pack copies the full 205 bytes
  if (r.saved) std::memcpy(url, r.fileUrl.data(), std::min<std::size_t>(204, r.fileUrl.size()));
  const std::uint64_t utc = r.pose.utcUs ? static_cast<std::uint64_t>(*r.pose.utcUs) : 0;
  // time_boot_ms is the autopilot's clock where the mapping is known, as in every
  // message of the camera's. A frame from before the autopilot's boot (queued across a
  // reboot) keeps bootMs().
  const std::uint32_t boot = bootMsAt(r.timeNs);
  return send(
      encoder_->encode([&](std::uint8_t, std::uint8_t, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_camera_image_captured_pack_status(
            systemId(), static_cast<std::uint8_t>(config_.componentId), st, m, boot, utc, 0, lat,
            lon, alt, rel, q, r.imageIndex, r.saved ? 1 : 0, url);
      }));
}

void TelemetryService::sendPendingCaptures(std::int64_t nowNs) {
  for (;;) {
    CaptureReport c;
    {
      std::lock_guard lock(mutex_);
      if (queue_.empty()) return;
      c = queue_.front();
    }
    if (!sendCapture(c)) {
      // No peer yet, or the link refused it: keep it (and the rest) for later.
      if (nowNs - lastCaptureWarningNs_ >= kCaptureWarningIntervalNs) {
        lastCaptureWarningNs_ = nowNs;
        std::size_t pending = 0;
        {
          std::lock_guard lock(mutex_);
          pending = queue_.size();
        }
        log(TelemetryLogLevel::Warning, "cannot send CAMERA_IMAGE_CAPTURED on " +
                                            link_->describe() + ": " + std::to_string(pending) +
                                            " capture report(s) kept until the link takes them");
      }
      return;
    }
    std::lock_guard lock(mutex_);
    // reportCapture may have pushed it out of a full queue meanwhile.
    if (!queue_.empty() && queue_.front().imageIndex == c.imageIndex) queue_.pop_front();
    ++stats_.capturesSent;
    stats_.capturesPending = queue_.size();
    history_.push_back(std::move(c));
    while (history_.size() > config_.captureHistory) history_.pop_front();
  }
}

void TelemetryService::resendCaptures(const mavlink_command_long_t& c,
                                      const mavlink_message_t& msg) {
  // param2: the first image index, -1 for all; param3: 0 just that one, -1 all
  // following, else the last index of the range (CAMERA_IMAGE_CAPTURED's description).
  const double p2 = c.param2, p3 = c.param3;
  if (!std::isfinite(p2) || !std::isfinite(p3)) {
    sendCommandAck(c.command, MAV_RESULT_DENIED, msg.sysid, msg.compid);
    return;
  }
  const auto first = static_cast<std::int64_t>(std::llround(p2));
  const auto rangeEnd = static_cast<std::int64_t>(std::llround(p3));
  std::int64_t lo = first, hi = first;
  if (first < 0) {
    lo = INT64_MIN;
    hi = INT64_MAX;
  } else if (rangeEnd < 0) {
    hi = INT64_MAX;
  } else if (rangeEnd > 0) {
    hi = rangeEnd;
  }
  std::vector<CaptureReport> found;
  {
    std::lock_guard lock(mutex_);
    for (const auto& r : history_) {
      if (r.imageIndex >= lo && r.imageIndex <= hi) found.push_back(r);
    }
  }
  // An index we never sent, or one too old to be kept: nothing to send.
  sendCommandAck(c.command, found.empty() ? MAV_RESULT_FAILED : MAV_RESULT_ACCEPTED, msg.sysid,
                 msg.compid);
  std::uint64_t sent = 0;
  for (const auto& r : found) sent += sendCapture(r) ? 1 : 0;
  std::lock_guard lock(mutex_);
  stats_.capturesResent += sent;
}

CaptureAnswer TelemetryService::requestCapture(bool intervalTick) {
  const CaptureAnswer answer = captureSink_ ? captureSink_(intervalTick) : CaptureAnswer::Ended;
  std::lock_guard lock(mutex_);
  ++(answer == CaptureAnswer::Taken ? stats_.captureRequests : stats_.captureRefused);
  return answer;
}

bool TelemetryService::forOurCamera(const mavlink_command_long_t& c, const mavlink_message_t& msg) {
  // param1: the target camera, 0 (or NaN) for all; 1-6 are cameras attached to the
  // autopilot, 7-255 a MAVLink camera's component id.
  const bool all = !std::isfinite(c.param1) || std::lround(c.param1) == 0;
  if (all || std::lround(c.param1) == config_.componentId) return true;
  // Addressed to us, for another camera: say no; a broadcast is for the others.
  if (c.target_component == config_.componentId)
    sendCommandAck(c.command, MAV_RESULT_DENIED, msg.sysid, msg.compid);
  return false;
}

void TelemetryService::startCapture(const mavlink_command_long_t& c, const mavlink_message_t& msg) {
  // param2: interval in s; param3: number of images, 0 until IMAGE_STOP_CAPTURE;
  // param4: for a single image, a sequence number that a retransmitted command
  // repeats (so that it is not taken twice).
  if (!captureSink_) {
    if (c.target_component == config_.componentId)
      sendCommandAck(c.command, MAV_RESULT_UNSUPPORTED, msg.sysid, msg.compid);
    return;
  }
  if (!forOurCamera(c, msg)) return;
  const double interval = c.param2, count = c.param3;
  if (!std::isfinite(interval) || !std::isfinite(count) || interval < 0 || count < 0 ||
      count > 1e6 || interval > 86400 || (count != 1 && interval < kMinCaptureIntervalS)) {
    sendCommandAck(c.command, MAV_RESULT_DENIED, msg.sysid, msg.compid);
    return;
  }
  const std::int64_t images = std::llround(count);
  const std::string who =
      "system " + std::to_string(msg.sysid) + " component " + std::to_string(msg.compid);
  if (images == 1) {
    const int sequence = std::isfinite(c.param4) ? static_cast<int>(std::lround(c.param4)) : 0;
    const std::int64_t now = monotonicNowNs();
    const int sender = msg.sysid << 8 | msg.compid;
    if (sequence > 0 && sequence == lastCapture_.sequence && sender == lastCapture_.sender &&
        now - lastCapture_.timeNs < kCaptureRepeatNs) {
      // The same command again (our acknowledgement was lost): already taken.
      sendCommandAck(c.command, MAV_RESULT_ACCEPTED, msg.sysid, msg.compid);
      return;
    }
    const CaptureAnswer answer = requestCapture(false);
    const bool taken = answer == CaptureAnswer::Taken;
    if (taken && sequence > 0) lastCapture_ = {sequence, sender, now};
    sendCommandAck(c.command, ackFor(answer), msg.sysid, msg.compid);
    log(TelemetryLogLevel::Notice,
        taken ? "capture requested by " + who
              : "capture refused for " + who +
                    (answer == CaptureAnswer::Busy ? " (too many waiting)"
                                                   : " (the video source has ended)"));
    return;
  }
  // The first at once: the answer to it is the command's.
  const std::int64_t now = monotonicNowNs();
  const CaptureAnswer first = requestCapture(true);
  sendCommandAck(c.command, ackFor(first == CaptureAnswer::Busy ? CaptureAnswer::Taken : first),
                 msg.sysid, msg.compid);
  if (first == CaptureAnswer::Ended) {
    captureIntervalNs_ = 0;
    log(TelemetryLogLevel::Notice,
        "interval capture refused for " + who + " (the video source has ended)");
    return;
  }
  captureIntervalNs_ = static_cast<std::int64_t>(interval * 1e9);
  capturesLeft_ = images;
  nextCaptureNs_ = now + captureIntervalNs_;
  if (capturesLeft_ > 0 && --capturesLeft_ == 0) captureIntervalNs_ = 0;
  char text[160];
  std::snprintf(text, sizeof text, "interval capture requested by %s: every %.3f s, %s",
                who.c_str(), interval,
                images == 0 ? "until stopped" : (std::to_string(images) + " images").c_str());
  log(TelemetryLogLevel::Notice, text);
}

std::uint8_t TelemetryService::ackFor(CaptureAnswer answer) {
  switch (answer) {
    case CaptureAnswer::Taken: return MAV_RESULT_ACCEPTED;
    case CaptureAnswer::Busy: return MAV_RESULT_TEMPORARILY_REJECTED;
    case CaptureAnswer::Ended: break;
  }
  return MAV_RESULT_DENIED;
}

void TelemetryService::runCaptureInterval(std::int64_t nowNs) {
  if (captureIntervalNs_ <= 0 || nowNs < nextCaptureNs_) return;
  // Skipped while an earlier one still waits for a usable frame, as a busy camera
  // would: a stretch of blurred frames must not end in a burst of identical images.
  if (requestCapture(true) == CaptureAnswer::Ended) {
    captureIntervalNs_ = 0;
    log(TelemetryLogLevel::Notice, "interval capture stopped: the video source has ended");
    return;
  }
  // On schedule without drift; after a stall, the next a whole interval later.
  nextCaptureNs_ += captureIntervalNs_;
  if (nextCaptureNs_ <= nowNs) nextCaptureNs_ = nowNs + captureIntervalNs_;
  if (capturesLeft_ > 0 && --capturesLeft_ == 0) captureIntervalNs_ = 0;
}

void TelemetryService::sendCaptureStatus() {
  // image_status: 0 idle, 3 an interval capture running (MAVLink's CAMERA_CAPTURE_STATUS).
  const bool interval = captureIntervalNs_ > 0;
  std::int32_t images = 0;
  {
    std::lock_guard lock(mutex_);
    images = static_cast<std::int32_t>(
        std::min<std::uint64_t>(stats_.capturesReported, std::numeric_limits<std::int32_t>::max()));
  }
  send(
      encoder_->encode([&](std::uint8_t, std::uint8_t, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_camera_capture_status_pack_status(
            systemId(), static_cast<std::uint8_t>(config_.componentId), st, m,
            bootMsAt(monotonicNowNs()), interval ? 3 : 0, 0,
            interval ? static_cast<float>(static_cast<double>(captureIntervalNs_) / 1e9) : 0.0F, 0,
            NAN, images, 0);
      }));
}

void TelemetryService::onTimesync(const mavlink_message_t& msg, std::int64_t timeNs) {
  mavlink_timesync_t ts;
  mavlink_msg_timesync_decode(&msg, &ts);
  // A request (the autopilot's, syncing with its onboard computer) is not answered:
  // nothing the autopilot gets from us is on our clock, and PX4 takes every answer for
  // its one onboard computer's clock (this dialect's TIMESYNC has no target ids to say
  // whose it is), so ours beside MAVROS's or a VIO computer's would reset its estimate.
  if (ts.tc1 == 0) return;
  // An answer: used only when it comes from the autopilot we follow and echoes one of
  // our recent requests. Others (a ground station answering the autopilot's own
  // request, a second vehicle, a stale duplicate) would set the clock to theirs.
  const int sys = decoder_.autopilotSystem();
  const int comp = decoder_.autopilotComponent();
  const auto it = std::find(timesyncRequests_.begin(), timesyncRequests_.end(), ts.ts1);
  if (sys == 0 || msg.sysid != sys || msg.compid != comp || it == timesyncRequests_.end()) {
    std::lock_guard lock(mutex_);
    ++stats_.timesyncRejected;
    return;
  }
  timesyncRequests_.erase(it);  // one answer per request
  decoder_.handleTimesync(ts.tc1, ts.ts1, timeNs);
}

void TelemetryService::onCommand(const mavlink_command_long_t& c, const mavlink_message_t& msg) {
  const bool forUs = (c.target_system == 0 || c.target_system == systemId()) &&
                     (c.target_component == 0 || c.target_component == config_.componentId);
  if (!forUs) return;
  const bool requestMessage = c.command == MAV_CMD_REQUEST_MESSAGE && std::isfinite(c.param1);
  const long requested = requestMessage ? std::lround(c.param1) : -1;
  if (requested == MAVLINK_MSG_ID_CAMERA_INFORMATION ||
      c.command == MAV_CMD_REQUEST_CAMERA_INFORMATION) {
    sendCommandAck(c.command, MAV_RESULT_ACCEPTED, msg.sysid, msg.compid);
    sendCameraInformation();
  } else if (requested == MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED) {
    resendCaptures(c, msg);
  } else if (requested == MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS ||
             c.command == MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS) {
    sendCommandAck(c.command, MAV_RESULT_ACCEPTED, msg.sysid, msg.compid);
    sendCaptureStatus();
  } else if (c.command == MAV_CMD_IMAGE_START_CAPTURE) {
    startCapture(c, msg);
  } else if (c.command == MAV_CMD_IMAGE_STOP_CAPTURE) {
    if (!captureSink_) {
      if (c.target_component == config_.componentId)
        sendCommandAck(c.command, MAV_RESULT_UNSUPPORTED, msg.sysid, msg.compid);
      return;
    }
    if (!forOurCamera(c, msg)) return;
    const bool running = captureIntervalNs_ > 0;
    captureIntervalNs_ = 0;
    sendCommandAck(c.command, MAV_RESULT_ACCEPTED, msg.sysid, msg.compid);
    if (running) log(TelemetryLogLevel::Notice, "interval capture stopped");
  } else if (c.target_component == config_.componentId) {
    sendCommandAck(c.command, MAV_RESULT_UNSUPPORTED, msg.sysid, msg.compid);
  }
}

void TelemetryService::onMessage(const mavlink_message_t& msg, std::int64_t timeNs) {
  if (msg.msgid == MAVLINK_MSG_ID_TIMESYNC) {
    onTimesync(msg, timeNs);
    return;
  }
  if (msg.msgid == MAVLINK_MSG_ID_COMMAND_LONG && config_.camera) {
    mavlink_command_long_t c;
    mavlink_msg_command_long_decode(&msg, &c);
    onCommand(c, msg);
    return;
  }
  if (msg.msgid == MAVLINK_MSG_ID_COMMAND_INT && config_.camera) {
    // The camera protocol's commands take no position: the same as a COMMAND_LONG
    // (answered with the same COMMAND_ACK), rather than left unanswered.
    mavlink_command_int_t ci;
    mavlink_msg_command_int_decode(&msg, &ci);
    mavlink_command_long_t c{};
    c.target_system = ci.target_system;
    c.target_component = ci.target_component;
    c.command = ci.command;
    c.param1 = ci.param1;
    c.param2 = ci.param2;
    c.param3 = ci.param3;
    c.param4 = ci.param4;
    c.param5 = static_cast<float>(ci.x);
    c.param6 = static_cast<float>(ci.y);
    c.param7 = ci.z;
    onCommand(c, msg);
    return;
  }
  if (msg.msgid == MAVLINK_MSG_ID_COMMAND_ACK) onCommandAck(msg);
  decoder_.handle(msg, timeNs);
}

void TelemetryService::logClock(std::int64_t nowNs) {
  // Said once both ids are known: `--autopilot 2` fixes the system, and its HEARTBEAT
  // then the component.
  const int sys = decoder_.autopilotSystem();
  const int comp = decoder_.autopilotComponent();
  if (sys != 0 && comp != 0 && sys * 256 + comp != loggedAutopilot_) {
    loggedAutopilot_ = sys * 256 + comp;
    log(TelemetryLogLevel::Notice, "following the autopilot at system " + std::to_string(sys) +
                                       " component " + std::to_string(comp));
  }
  const std::uint64_t reboots = decoder_.stats().reboots;
  if (reboots != loggedReboots_) {
    loggedReboots_ = reboots;
    log(TelemetryLogLevel::Warning,
        "the autopilot's clock went back (a reboot): pose history and clock estimate cleared");
  }
  const ClockMapper::Source source = decoder_.clockSource();
  const auto offset = decoder_.clockOffsetNs();
  const bool first = loggedSource_ == ClockMapper::Source::None;
  const bool sourceChanged = source != loggedSource_;
  const bool moved = offset && std::llabs(*offset - loggedOffsetNs_) > kClockLogChangeNs;
  if (!sourceChanged && !moved) return;
  // A new source (TIMESYNC answered, or no longer) is said at once, at most once a
  // second; a drifting offset at most every 10 s.
  if (!first && nowNs - lastClockLogNs_ < (sourceChanged ? kSecond : kClockLogIntervalNs)) return;
  const ClockMapper::Source previous = loggedSource_;
  lastClockLogNs_ = nowNs;
  loggedSource_ = source;
  if (!offset) {
    log(TelemetryLogLevel::Warning, "autopilot clock: no estimate any more");
    return;
  }
  const double change = first ? 0.0 : static_cast<double>(*offset - loggedOffsetNs_) / 1e6;
  loggedOffsetNs_ = *offset;
  std::string text = std::string("autopilot clock: ") + toString(source) + ", offset " +
                     formatMs(static_cast<double>(*offset) / 1e6) + " (local - autopilot)";
  const double rtt = decoder_.clockRoundTripMs();
  const double within = decoder_.clockUncertaintyMs();
  if (!std::isnan(within)) text += " within " + formatMs(within);
  text += std::isnan(rtt) ? ", no TIMESYNC round trip" : ", best round trip " + formatMs(rtt);
  if (!first) text += ", changed by " + formatMs(change);
  TelemetryLogLevel level = first ? TelemetryLogLevel::Notice : TelemetryLogLevel::Info;
  if (!first && source != previous) {
    level = source == ClockMapper::Source::Timesync ? TelemetryLogLevel::Notice
                                                    : TelemetryLogLevel::Warning;
    if (source != ClockMapper::Source::Timesync) text += " (no TIMESYNC answers for a while)";
  }
  log(level, text);
}

void TelemetryService::run() {
  std::vector<std::uint8_t> buf(2048);
  std::int64_t lastHeartbeat = 0;
  std::int64_t lastTimesync = 0;
  std::int64_t lastData = monotonicNowNs();
  std::int64_t nextReopen = monotonicNowNs() + kSecond;
  bool broken = startUnopened_;  // said at start(): reopened quietly until it is there
  bool silent = false;
  const std::string name = link_->describe();
  while (!stop_) {
    const std::int64_t now = monotonicNowNs();
    runCaptureInterval(now);  // the camera goes on while the link is down
    if (broken) {
      if (now < nextReopen) {
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
        continue;
      }
      std::string error;
      if (link_->reopen(error)) {
        broken = false;
        lastData = now;
        // The rest of a frame half read before the drop is gone: the first bytes now
        // are not its continuation.
        parser_.reset();
        log(TelemetryLogLevel::Notice, "MAVLink link " + name + " reopened");
        std::lock_guard lock(mutex_);
        ++stats_.reconnects;
      } else {
        nextReopen = now + kSecond;
        continue;
      }
    }
    if (config_.camera && now - lastHeartbeat >= kSecond) {
      lastHeartbeat = now;
      sendHeartbeat();
    }
    // 40 Hz until the clock estimate has settled (three answers: a tenth of a second on
    // a quick link, a few requests of 30 bytes), so that the first keyframe is not
    // held for it; then 1 Hz.
    const std::int64_t timesyncInterval = decoder_.clockSettled() ? kSecond : kSecond / 40;
    // Only once the autopilot has spoken: before, on a port that hears several senders,
    // the requests would go to whoever sent last (another vehicle, a ground station).
    if (config_.timesync && autopilotHeard_ && now - lastTimesync >= timesyncInterval) {
      lastTimesync = now;
      sendTimesync(now);
    }
    requestMessageRates(now);
    // An autopilot heard in MAVLink 1 only for 3 s does not read MAVLink 2 (TIMESYNC
    // would go unanswered): answer in its version. Back to 2 once it speaks 2.
    if (!config_.mavlink1 && !autopilotV2_ && !encoder_->mavlink1() && autopilotV1SinceNs_ != 0 &&
        now - autopilotV1SinceNs_ > 3 * kSecond) {
      encoder_->setMavlink1(true);
      log(TelemetryLogLevel::Notice,
          "the autopilot speaks MAVLink 1 only: sending MAVLink 1 too (CAMERA_INFORMATION and "
          "CAMERA_IMAGE_CAPTURED exist only in MAVLink 2: set the autopilot's port to "
          "MAVLink 2, ArduPilot: SERIALn_PROTOCOL = 2, for the camera protocol)");
    } else if (!config_.mavlink1 && autopilotV2_ && encoder_->mavlink1()) {
      encoder_->setMavlink1(false);
      log(TelemetryLogLevel::Notice, "the autopilot speaks MAVLink 2: sending MAVLink 2 again");
    }
    sendPendingCaptures(now);
    logClock(now);
    if (!silent && now - lastData > kSilenceNs) {
      silent = true;
      log(TelemetryLogLevel::Warning, "no MAVLink data on " + name + " for " +
                                          std::to_string((now - lastData) / kSecond) + " s");
    }

    std::size_t n = 0;
    std::int64_t t = 0;
    std::string error;
    switch (link_->read(buf.data(), buf.size(), n, t, 50, error)) {
      case MavlinkLink::Status::Data: {
        if (silent) {
          silent = false;
          log(TelemetryLogLevel::Notice, "MAVLink data on " + name + " again after " +
                                             formatMs(static_cast<double>(t - lastData) / 1e6, 0));
        }
        lastData = t;
        bool fromAutopilot = false;
        const auto good = [&](const mavlink_message_t& m) {
          onMessage(m, t);
          const bool autopilot =
              m.sysid == decoder_.autopilotSystem() && m.compid == decoder_.autopilotComponent();
          fromAutopilot = fromAutopilot || autopilot;
          if (autopilot && m.magic == MAVLINK_STX) autopilotV2_ = true;
          if (autopilot && autopilotV1SinceNs_ == 0) autopilotV1SinceNs_ = t;
          std::lock_guard lock(sinkMutex_);
          if (sink_) sink_(m, t);
        };
        const auto otherDialect = [&](const mavlink_message_t& m) {
          // Another dialect's message (ArduPilot's, PX4's): recorded, not decoded.
          std::lock_guard lock(sinkMutex_);
          if (sink_) sink_(m, t);
        };
        // A datagram holds whole frames: one it leaves unfinished (cut short, another
        // protocol's) must not swallow the next datagram's start.
        if (link_->datagrams()) {
          parser_.feedDatagram(buf.data(), n, good, otherDialect);
        } else {
          parser_.feed(buf.data(), n, good, otherDialect);
        }
        // udpin: answer the autopilot, not whoever else sends to the port.
        if (fromAutopilot) {
          link_->pinPeerToLastSender();
          autopilotHeard_ = true;
        }
        std::lock_guard lock(mutex_);
        stats_.parser = parser_.stats();
        break;
      }
      case MavlinkLink::Status::Timeout: break;
      case MavlinkLink::Status::End: stop_ = true; break;
      case MavlinkLink::Status::Error: {
        log(TelemetryLogLevel::Warning,
            "MAVLink link " + name + ": " + (error.empty() ? "error" : error) + "; reopening");
        std::lock_guard lock(mutex_);
        ++stats_.linkErrors;
        broken = true;
        nextReopen = now + 200'000'000;
        break;
      }
    }
  }
  // The last keyframes may have been reported just before stop().
  if (!broken) sendPendingCaptures(monotonicNowNs());
}

}  // namespace keyframed
