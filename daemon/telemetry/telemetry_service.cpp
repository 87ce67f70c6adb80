#include "telemetry/telemetry_service.h"

#include <cstring>
#include <vector>

namespace keyframed {

TelemetryService::TelemetryService(TelemetryServiceConfig config, CameraDescription camera)
    : config_(std::move(config)), camera_(std::move(camera)), decoder_(config_.decoder) {}

TelemetryService::~TelemetryService() {
  stop();
}

bool TelemetryService::start(std::string& error) {
  link_ = openMavlinkLink(config_.url, error);
  if (!link_) return false;
  replay_ = link_->isReplay();
  startNs_ = monotonicNowNs();
  if (replay_) {
    // A recording: read it all now, with its own timestamps.
    std::vector<std::uint8_t> buf(512);
    std::size_t n = 0;
    std::int64_t t = 0;
    while (link_->read(buf.data(), buf.size(), n, t, 0, error) == MavlinkLink::Status::Data) {
      parser_.feed(buf.data(), n, [&](const mavlink_message_t& m) { decoder_.handle(m, t); });
    }
    error.clear();
    std::lock_guard lock(mutex_);
    stats_.replayDone = true;
    stats_.truncated = link_->truncated();
    stats_.parser = parser_.stats();
    return true;
  }
  encoder_ = std::make_unique<MavlinkEncoder>(0, 0, config_.mavlink1);
  stop_ = false;
  thread_ = std::thread([this] { run(); });
  return true;
}

void TelemetryService::startFromPackets(
    const std::vector<std::pair<std::int64_t, std::vector<std::uint8_t>>>& packets) {
  replay_ = true;
  startNs_ = monotonicNowNs();
  for (const auto& packet : packets) {
    const std::int64_t t = packet.first;  // (clang 14 cannot capture a structured binding)
    parser_.feed(packet.second.data(), packet.second.size(),
                 [&](const mavlink_message_t& m) { decoder_.handle(m, t); });
  }
  std::lock_guard lock(mutex_);
  stats_.replayDone = true;
  stats_.parser = parser_.stats();
}

void TelemetryService::stop() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
}

void TelemetryService::setRawSink(RawSink sink) {
  std::lock_guard lock(sinkMutex_);
  sink_ = std::move(sink);
}

void TelemetryService::reportCapture(const CaptureReport& report) {
  std::lock_guard lock(mutex_);
  queue_.push_back(report);
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

std::uint8_t TelemetryService::systemId() const {
  if (config_.systemId > 0) return static_cast<std::uint8_t>(config_.systemId);
  const int sys = decoder_.autopilotSystem();
  return static_cast<std::uint8_t>(sys > 0 ? sys : 1);
}

void TelemetryService::send(const std::vector<std::uint8_t>& bytes) {
  std::string error;
  if (!link_->write(bytes.data(), bytes.size(), error) && !error.empty()) {
    std::lock_guard lock(mutex_);
    ++stats_.linkErrors;
  }
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
            systemId(), static_cast<std::uint8_t>(config_.componentId), st, m, bootMs(), vendor,
            model, 0, camera_.focalLengthMm, camera_.sensorWidthMm, camera_.sensorHeightMm,
            static_cast<std::uint16_t>(camera_.width), static_cast<std::uint16_t>(camera_.height),
            0, CAMERA_CAP_FLAGS_CAPTURE_IMAGE, 0, uri, 0, 0);
      }));
  std::lock_guard lock(mutex_);
  ++stats_.infoSent;
}

void TelemetryService::sendCommandAck(std::uint16_t command, std::uint8_t result,
                                      std::uint8_t targetSys, std::uint8_t targetComp) {
  send(encoder_->encode([&](std::uint8_t, std::uint8_t, mavlink_status_t* st,
                            mavlink_message_t* m) {
    mavlink_msg_command_ack_pack_status(systemId(), static_cast<std::uint8_t>(config_.componentId),
                                        st, m, command, result, 0, 0, targetSys, targetComp);
  }));
}

void TelemetryService::sendCapture(const CaptureReport& r) {
  std::int32_t lat = 0, lon = 0, alt = 0, rel = 0;
  if (r.pose.position) {
    lat = static_cast<std::int32_t>(std::llround(r.pose.position->latDeg * 1e7));
    lon = static_cast<std::int32_t>(std::llround(r.pose.position->lonDeg * 1e7));
    alt = static_cast<std::int32_t>(std::llround(r.pose.position->altAmslM * 1e3));
    rel = static_cast<std::int32_t>(std::llround(r.pose.position->altRelM * 1e3));
  }
  float q[4] = {NAN, NAN, NAN, NAN};
  if (r.cameraAttitude) {
    q[0] = static_cast<float>(r.cameraAttitude->w);
    q[1] = static_cast<float>(r.cameraAttitude->x);
    q[2] = static_cast<float>(r.cameraAttitude->y);
    q[3] = static_cast<float>(r.cameraAttitude->z);
  }
  char url[205] = {};  // the generated pack copies the full 205 bytes
  std::memcpy(url, r.fileUrl.data(), std::min<std::size_t>(204, r.fileUrl.size()));
  const std::uint64_t utc = r.pose.utcUs ? static_cast<std::uint64_t>(*r.pose.utcUs) : 0;
  // time_boot_ms is the autopilot's clock where the mapping is known.
  std::uint32_t boot = bootMs();
  if (const auto off = decoder_.clockOffsetNs()) {
    boot = static_cast<std::uint32_t>((r.timeNs - *off) / 1'000'000);
  }
  send(
      encoder_->encode([&](std::uint8_t, std::uint8_t, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_camera_image_captured_pack_status(
            systemId(), static_cast<std::uint8_t>(config_.componentId), st, m, boot, utc, 0, lat,
            lon, alt, rel, q, r.imageIndex, 1, url);
      }));
  std::lock_guard lock(mutex_);
  ++stats_.capturesSent;
}

void TelemetryService::onMessage(const mavlink_message_t& msg, std::int64_t timeNs) {
  if (msg.msgid == MAVLINK_MSG_ID_TIMESYNC) {
    mavlink_timesync_t ts;
    mavlink_msg_timesync_decode(&msg, &ts);
    if (ts.tc1 != 0) {
      // An answer to one of ours (ts1 echoes our time).
      decoder_.handleTimesync(ts.tc1, ts.ts1, timeNs);
    } else if (config_.camera) {
      // Someone syncs with us: answer with our clock.
      const std::int64_t now = monotonicNowNs();
      send(encoder_->encode(
          [&](std::uint8_t, std::uint8_t, mavlink_status_t* st, mavlink_message_t* m) {
            mavlink_msg_timesync_pack_status(
                systemId(), static_cast<std::uint8_t>(config_.componentId), st, m, now, ts.ts1);
          }));
    }
    return;
  }
  if (msg.msgid == MAVLINK_MSG_ID_COMMAND_LONG && config_.camera) {
    mavlink_command_long_t c;
    mavlink_msg_command_long_decode(&msg, &c);
    const bool forUs = (c.target_system == 0 || c.target_system == systemId()) &&
                       (c.target_component == 0 || c.target_component == config_.componentId);
    if (!forUs) return;
    if (c.command == MAV_CMD_REQUEST_MESSAGE &&
        static_cast<int>(c.param1) == MAVLINK_MSG_ID_CAMERA_INFORMATION) {
      sendCommandAck(c.command, MAV_RESULT_ACCEPTED, msg.sysid, msg.compid);
      sendCameraInformation();
    } else if (c.command == MAV_CMD_REQUEST_CAMERA_INFORMATION) {
      sendCommandAck(c.command, MAV_RESULT_ACCEPTED, msg.sysid, msg.compid);
      sendCameraInformation();
    } else if (c.target_component == config_.componentId) {
      sendCommandAck(c.command, MAV_RESULT_UNSUPPORTED, msg.sysid, msg.compid);
    }
    return;
  }
  decoder_.handle(msg, timeNs);
}

void TelemetryService::run() {
  std::vector<std::uint8_t> buf(2048);
  std::int64_t lastHeartbeat = 0;
  std::int64_t lastTimesync = 0;
  std::int64_t lastData = monotonicNowNs();
  std::int64_t nextReopen = 0;
  bool broken = false;
  while (!stop_) {
    const std::int64_t now = monotonicNowNs();
    if (broken) {
      if (now < nextReopen) {
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
        continue;
      }
      std::string error;
      if (link_->reopen(error)) {
        broken = false;
        std::lock_guard lock(mutex_);
        ++stats_.reconnects;
      } else {
        nextReopen = now + 1'000'000'000;
        continue;
      }
    }
    if (config_.camera && now - lastHeartbeat >= 1'000'000'000) {
      lastHeartbeat = now;
      sendHeartbeat();
    }
    if (config_.timesync && decoder_.autopilotSystem() != 0 &&
        now - lastTimesync >= 1'000'000'000) {
      lastTimesync = now;
      sendTimesync(now);
    }
    std::deque<CaptureReport> captures;
    {
      std::lock_guard lock(mutex_);
      captures.swap(queue_);
    }
    for (const auto& c : captures) sendCapture(c);

    std::size_t n = 0;
    std::int64_t t = 0;
    std::string error;
    switch (link_->read(buf.data(), buf.size(), n, t, 50, error)) {
      case MavlinkLink::Status::Data:
        lastData = t;
        parser_.feed(buf.data(), n, [&](const mavlink_message_t& m) {
          onMessage(m, t);
          std::lock_guard lock(sinkMutex_);
          if (sink_) sink_(m, t);
        });
        {
          std::lock_guard lock(mutex_);
          stats_.parser = parser_.stats();
        }
        break;
      case MavlinkLink::Status::Timeout: break;
      case MavlinkLink::Status::End: stop_ = true; break;
      case MavlinkLink::Status::Error: {
        std::lock_guard lock(mutex_);
        ++stats_.linkErrors;
        broken = true;
        nextReopen = now + 200'000'000;
        break;
      }
    }
    (void)lastData;
  }
}

}  // namespace keyframed
