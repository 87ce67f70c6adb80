#include "app/mavlink_record.h"

#include <array>

namespace keyframed {

bool MavlinkRecord::fromKnownSender(const mavlink_message_t& msg) {
  const int sender = msg.sysid << 8 | msg.compid;
  if (mavlink_get_msg_entry(msg.msgid) != nullptr) {  // checked: its sender is real
    if (senders_.size() < 1024) senders_.insert(sender);
    return true;
  }
  return senders_.contains(sender);  // another dialect's, from a component heard
}

void MavlinkRecord::message(const mavlink_message_t& msg, std::int64_t timeNs) {
  if (!fromKnownSender(msg)) return;  // line noise that looked like a frame
  // As it came (mavlink_msg_to_send_buffer would trim an untrimmed payload and break
  // its checksum).
  std::array<std::uint8_t, MAVLINK_MAX_PACKET_LEN> buf{};
  const std::size_t n = wireBytes(msg, buf);
  outputs_.mavlink(timeNs, msg.sysid, msg.compid, msg.msgid,
                   std::span<const std::uint8_t>(buf.data(), n));
  vehicle(msg, timeNs);
}

void MavlinkRecord::packet(const TimedPacket& p) {
  // Bytes that hold no whole, checked packet (a record cut short) are left out.
  const auto record = [&](const mavlink_message_t& msg) {
    if (!fromKnownSender(msg)) return;
    outputs_.mavlink(p.timeNs, msg.sysid, msg.compid, msg.msgid, p.bytes);
    vehicle(msg, p.timeNs);
  };
  parser_.feed(p.bytes.data(), p.bytes.size(), record, record);
}

void MavlinkRecord::vehicle(const mavlink_message_t& msg, std::int64_t timeNs) {
  if (msg.sysid != decoder_.autopilotSystem() || msg.compid != decoder_.autopilotComponent() ||
      timeNs < decoder_.autopilotSinceNs())
    return;
  constexpr std::int64_t kQuaternionHoldNs = 2'000'000'000;
  switch (msg.msgid) {
    case MAVLINK_MSG_ID_GLOBAL_POSITION_INT: {
      mavlink_global_position_int_t p;
      mavlink_msg_global_position_int_decode(&msg, &p);
      if (!plausiblePosition(p)) return;
      outputs_.vehicleLocation(timeNs, p.lat * 1e-7, p.lon * 1e-7, p.alt * 1e-3);
      break;
    }
    case MAVLINK_MSG_ID_ATTITUDE_QUATERNION: {
      mavlink_attitude_quaternion_t a;
      mavlink_msg_attitude_quaternion_decode(&msg, &a);
      // As telemetry reads them: an unset (zero) or NaN quaternion is no attitude.
      const Quaternion q{a.q1, a.q2, a.q3, a.q4};
      if (!usableRotation(q)) return;
      lastQuaternionNs_ = timeNs;
      outputs_.vehicleAttitude(timeNs, normalized(q));
      break;
    }
    case MAVLINK_MSG_ID_ATTITUDE: {
      // Both streams describe the same estimate, as telemetry decodes them.
      if (lastQuaternionNs_ >= 0 && timeNs - lastQuaternionNs_ < kQuaternionHoldNs) return;
      mavlink_attitude_t a;
      mavlink_msg_attitude_decode(&msg, &a);
      if (!std::isfinite(a.roll) || !std::isfinite(a.pitch) || !std::isfinite(a.yaw)) return;
      outputs_.vehicleAttitude(timeNs, quaternionFromEuler(a.roll, a.pitch, a.yaw));
      break;
    }
    default: break;
  }
}

void recordLiveMavlink(TelemetryService& telemetry, FlightOutputs& outputs) {
  if (telemetry.isReplay()) return;
  auto record = std::make_shared<MavlinkRecord>(outputs, telemetry.decoder());
  // The sink runs on the telemetry thread only: the record needs no lock of its own.
  telemetry.setRawSink([record](const mavlink_message_t& msg, std::int64_t timeNs) {
    record->message(msg, timeNs);
  });
}

}  // namespace keyframed
