#include "app/keyframe_output.h"

#include <time.h>

#include <chrono>
#include <optional>
#include <thread>

namespace keyframed {

void recordRawMavlink(TelemetryService& telemetry, FlightOutputs& outputs) {
  if (telemetry.isReplay()) return;
  telemetry.setRawSink([&outputs](const mavlink_message_t& msg, std::int64_t timeNs) {
    std::uint8_t buf[MAVLINK_MAX_PACKET_LEN];
    const std::uint16_t n = mavlink_msg_to_send_buffer(buf, &msg);
    outputs.mavlink(timeNs, msg.sysid, msg.compid, msg.msgid,
                    std::span<const std::uint8_t>(buf, n));
  });
}

KeyframeOutput::KeyframeOutput(KeyframeWriter& writer, DecisionLog& log, FlightOutputs& outputs,
                               TelemetryService* telemetry, int telemetryWaitMs)
    : writer_(writer),
      log_(log),
      outputs_(outputs),
      telemetry_(telemetry),
      telemetryWaitMs_(telemetryWaitMs) {}

bool KeyframeOutput::writeKeyframe(const Frame& frame, std::string& note, std::string& error) {
  std::optional<Pose> pose;
  if (telemetry_ != nullptr) {
    if (!telemetry_->isReplay()) {
      // Telemetry for this instant may still be on its way: wait a little.
      const std::int64_t deadline = monotonicNowNs() + telemetryWaitMs_ * 1'000'000LL;
      while (!telemetry_->decoder().covers(frame.timestampNs) && monotonicNowNs() < deadline) {
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
      }
    }
    pose = telemetry_->decoder().poseAt(frame.timestampNs);
  }
  KeyframeRecord rec;
  if (!writer_.write(frame, pose ? &*pose : nullptr, rec, error)) return false;
  outputs_.keyframe(rec, writer_.lastJpeg());
  note = rec.geotag;
  if (telemetry_ != nullptr && !telemetry_->isReplay()) {
    CaptureReport report;
    report.timeNs = frame.timestampNs;
    report.imageIndex = static_cast<std::int32_t>(rec.sequence);
    report.pose = rec.pose;
    report.cameraAttitude = rec.cameraToNed;
    report.fileUrl = "file://" + rec.file;
    telemetry_->reportCapture(report);
  }
  return true;
}

bool KeyframeOutput::handle(const KeyframeEvent& ev, std::string& error) {
  std::string note;
  if (ev.endOfStream) {
    if (!ev.promoted) return true;
    if (!writeKeyframe(ev.promoted->frame, note, error)) return false;
    log_.markGapFill(ev.promoted->frame.index);
    log_.setGeotag(ev.promoted->frame.index, note);
    return true;
  }
  const Decision& d = ev.decision;
  if (outputs_.active()) outputs_.decision(d, DecisionLog::jsonRow(d));
  if (ev.promoted) {
    if (!writeKeyframe(ev.promoted->frame, note, error)) return false;
    log_.setGeotag(ev.promoted->frame.index, note);
  }
  note.clear();
  if (d.kept && ev.keyframe) {
    if (!writeKeyframe(ev.keyframe->frame, note, error)) return false;
  }
  return log_.add(d, error, note);
}

}  // namespace keyframed
