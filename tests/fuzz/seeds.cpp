#include "seeds.h"

#include "telemetry/mavlink_codec.h"

namespace keyframed::fuzz {

namespace {

using Packet = std::vector<std::uint8_t>;

void addFlight(MavlinkEncoder& enc, std::vector<Packet>& out) {
  using St = mavlink_status_t;
  using Msg = mavlink_message_t;
  out.push_back(enc.encode([](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
    mavlink_msg_heartbeat_pack_status(s, c, st, m, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA,
                                      0, 0, MAV_STATE_ACTIVE);
  }));
  out.push_back(enc.encode([](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
    mavlink_msg_system_time_pack_status(s, c, st, m, 1'790'000'000'000'000ULL, 5000);
  }));
  for (std::uint32_t t = 5000; t < 5100; t += 20) {
    out.push_back(enc.encode([t](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
      mavlink_msg_attitude_pack_status(s, c, st, m, t, 0.01F, -0.02F, 1.5F, 0, 0, 0);
    }));
    out.push_back(enc.encode([t](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
      mavlink_msg_attitude_quaternion_pack_status(s, c, st, m, t, 0.7F, 0.0F, 0.0F, 0.7F, 0, 0, 0,
                                                  nullptr);
    }));
    out.push_back(enc.encode([t](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
      mavlink_msg_global_position_int_pack_status(s, c, st, m, t, 515'000'000, -1'000'000, 120'000,
                                                  30'000, 100, 0, 0, 9000);
    }));
  }
  out.push_back(enc.encode([](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
    mavlink_msg_gps_raw_int_pack_status(s, c, st, m, 5'080'000, 3, 515'000'000, -1'000'000, 120'000,
                                        80, 120, 0, 0, 14, 0, 800, 1200, 0, 0, 0);
  }));
  out.push_back(enc.encode([](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
    mavlink_msg_timesync_pack_status(s, c, st, m, 0, 5'100'000'000LL);
  }));
  // What a ground station asks the camera, and TIMESYNC answers (ours to no request).
  for (const float p2 : {0.0F, 1.0F, -1.0F, 2.0F}) {
    out.push_back(enc.encode([p2](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
      mavlink_msg_command_long_pack_status(s, c, st, m, 1, 100, MAV_CMD_REQUEST_MESSAGE, 0,
                                           MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED, p2,
                                           p2 == 1.0F ? -1.0F : 0.0F, 0, 0, 0, 0);
    }));
  }
  out.push_back(enc.encode([](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
    mavlink_msg_command_long_pack_status(s, c, st, m, 0, 0, MAV_CMD_REQUEST_MESSAGE, 0,
                                         MAVLINK_MSG_ID_CAMERA_INFORMATION, 0, 0, 0, 0, 0, 0);
  }));
  out.push_back(enc.encode([](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
    mavlink_msg_command_long_pack_status(s, c, st, m, 1, 100, MAV_CMD_REQUEST_CAMERA_INFORMATION, 0,
                                         1, 0, 0, 0, 0, 0, 0);
  }));
  out.push_back(enc.encode([](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
    mavlink_msg_timesync_pack_status(s, c, st, m, 5'100'000'000LL, 9'000'000'000LL);
  }));
  out.push_back(enc.encode([](std::uint8_t s, std::uint8_t c, St* st, Msg* m) {
    mavlink_msg_sys_status_pack_status(s, c, st, m, 0, 0, 0, 500, 12000, 100, 80, 0, 0, 0, 0, 0, 0,
                                       0, 0, 0);
  }));
}

}  // namespace

std::vector<std::vector<std::uint8_t>> mavlinkSeeds() {
  std::vector<Packet> out;
  MavlinkEncoder v2(1, 1);
  MavlinkEncoder v1(1, 1, /*mavlink1=*/true);
  MavlinkEncoder other(2, 1);
  addFlight(v2, out);
  addFlight(v1, out);
  addFlight(other, out);
  // Also whole streams: all packets of one encoder back to back.
  Packet stream;
  for (const auto& p : out) stream.insert(stream.end(), p.begin(), p.end());
  // And a tlog: each packet after its 8-byte big-endian unix time in microseconds.
  Packet tlog;
  std::uint64_t us = 1'790'000'000'000'000ULL;
  for (const auto& p : out) {
    for (int shift = 56; shift >= 0; shift -= 8)
      tlog.push_back(static_cast<std::uint8_t>(us >> shift));
    tlog.insert(tlog.end(), p.begin(), p.end());
    us += 20'000;
  }
  out.push_back(stream);
  out.push_back(tlog);
  return out;
}

}  // namespace keyframed::fuzz
