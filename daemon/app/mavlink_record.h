#pragma once

#include <cstdint>
#include <memory>
#include <set>
#include <span>

#include "output/flight_outputs.h"
#include "telemetry/telemetry_service.h"
#include "telemetry/timed_packet.h"

namespace keyframed {

// The MAVLink stream into the flight record: every packet on /mavlink/raw, and the
// position and attitude of the autopilot that telemetry follows (the one chosen by
// system/component id, not any sender) on /vehicle/location and /vehicle/pose, at the
// stream's own rate (the keyframe channels have them only at keyframes).
class MavlinkRecord {
 public:
  MavlinkRecord(FlightOutputs& outputs, const TelemetryDecoder& decoder)
      : outputs_(outputs), decoder_(decoder) {}

  // A message a live link received at timeNs.
  void message(const mavlink_message_t& msg, std::int64_t timeNs);
  // A packet as a tlog or an earlier record holds it: recorded byte for byte.
  void packet(const TimedPacket& packet);

 private:
  void vehicle(const mavlink_message_t& msg, std::int64_t timeNs);
  // A message of the dialect notes its sender; one of another dialect (unchecked) is
  // taken only from a sender so noted.
  bool fromKnownSender(const mavlink_message_t& msg);

  FlightOutputs& outputs_;
  const TelemetryDecoder& decoder_;
  MavlinkParser parser_;                // packet(): bytes to messages
  std::int64_t lastQuaternionNs_ = -1;  // ATTITUDE_QUATERNION seen: ATTITUDE is not recorded
  std::set<int> senders_;               // sysid << 8 | compid of checked messages
};

// Records every message a live link receives (nothing for a replay: an offline run
// carries its replay's packets on itself, in time order with its frames).
void recordLiveMavlink(TelemetryService& telemetry, FlightOutputs& outputs);

}  // namespace keyframed
