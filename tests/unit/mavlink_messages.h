#pragma once

#include <cmath>
#include <cstdint>
#include <vector>

#include "telemetry/mavlink_codec.h"

// What the telemetry tests share: time and angle units and the messages they all
// send (the sanitizer build compiles several test files as one: one definition).
namespace keyframed::test {

inline constexpr std::int64_t kMs = 1'000'000;  // ns
inline constexpr double kDeg = M_PI / 180.0;

inline std::vector<std::uint8_t> heartbeat(MavlinkEncoder& enc, std::uint8_t type,
                                           std::uint8_t autopilot) {
  return enc.encode(
      [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_heartbeat_pack_status(s, c, st, m, type, autopilot, 0, 0, MAV_STATE_ACTIVE);
      });
}

}  // namespace keyframed::test
