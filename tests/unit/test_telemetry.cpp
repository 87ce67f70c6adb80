#include <fcntl.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <random>
#include <tuple>
#include <vector>

#include "mavlink_messages.h"
#include "telemetry/clock_mapper.h"
#include "telemetry/link.h"
#include "telemetry/mavlink_codec.h"
#include "telemetry/pose_store.h"
#include "telemetry/telemetry_decoder.h"
#include "telemetry/tlog.h"
#include "temp_dir.h"

namespace keyframed {
namespace {

using test::heartbeat;
using test::kDeg;
using test::kMs;

std::vector<std::uint8_t> attitudeQ(MavlinkEncoder& enc, std::uint32_t bootMs,
                                    const Quaternion& q) {
  return enc.encode(
      [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
        const float qq[4] = {static_cast<float>(q.w), static_cast<float>(q.x),
                             static_cast<float>(q.y), static_cast<float>(q.z)};
        mavlink_msg_attitude_quaternion_pack_status(s, c, st, m, bootMs, qq[0], qq[1], qq[2], qq[3],
                                                    0, 0, 0, nullptr);
      });
}

std::vector<std::uint8_t> attitudeEuler(MavlinkEncoder& enc, std::uint32_t bootMs, double roll,
                                        double pitch, double yaw) {
  return enc.encode([&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st,
                        mavlink_message_t* m) {
    mavlink_msg_attitude_pack_status(s, c, st, m, bootMs, static_cast<float>(roll),
                                     static_cast<float>(pitch), static_cast<float>(yaw), 0, 0, 0);
  });
}

std::vector<std::uint8_t> position(MavlinkEncoder& enc, std::uint32_t bootMs, double lat,
                                   double lon, double alt) {
  return enc.encode(
      [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_global_position_int_pack_status(
            s, c, st, m, bootMs, static_cast<std::int32_t>(std::lround(lat * 1e7)),
            static_cast<std::int32_t>(std::lround(lon * 1e7)),
            static_cast<std::int32_t>(std::lround(alt * 1e3)), 30000, 0, 0, 0, 0);
      });
}

std::vector<std::uint8_t> gpsRaw(MavlinkEncoder& enc, std::uint8_t fix, std::uint16_t eph = 80,
                                 std::uint16_t epv = 120) {
  return enc.encode(
      [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_gps_raw_int_pack_status(s, c, st, m, 0, fix, 0, 0, 0, eph, epv, 0, 0, 14, 0,
                                            800, 1200, 0, 0, 0);
      });
}

std::vector<std::uint8_t> gimbalStatus(MavlinkEncoder& enc, std::uint32_t bootMs,
                                       const Quaternion& q, std::uint16_t flags,
                                       std::uint8_t deviceId = 0) {
  return enc.encode(
      [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
        const float qq[4] = {static_cast<float>(q.w), static_cast<float>(q.x),
                             static_cast<float>(q.y), static_cast<float>(q.z)};
        mavlink_msg_gimbal_device_attitude_status_pack_status(s, c, st, m, 0, 0, bootMs, flags, qq,
                                                              NAN, NAN, NAN, 0, NAN, NAN, deviceId);
      });
}

TEST(PoseStore, InterpolatesAttitudeBySlerpAndPositionLinearly) {
  PoseStore store;
  const Quaternion a = quaternionFromEuler(0, 0, 10 * kDeg);
  const Quaternion b = quaternionFromEuler(0, 0, 30 * kDeg);
  store.addAttitude(1000 * kMs, a);
  store.addAttitude(1020 * kMs, b);
  GpsQuality fix;
  fix.fixType = 3;
  store.addGps(900 * kMs, fix);
  store.addPosition(900 * kMs, {51.0, 1.0, 100.0, 10.0});
  store.addPosition(1100 * kMs, {51.0002, 1.0004, 102.0, 12.0});

  const Pose p = store.at(1015 * kMs);
  ASSERT_TRUE(p.attitude.has_value()) << p.staleReason;
  ASSERT_TRUE(p.position.has_value()) << p.staleReason;
  EXPECT_NEAR(angleBetween(*p.attitude, quaternionFromEuler(0, 0, 25 * kDeg)), 0.0, 1e-9);
  // 1015 ms lies 57.5 % of the way from 900 to 1100 ms.
  EXPECT_NEAR(p.position->latDeg, 51.000115, 1e-12);
  EXPECT_NEAR(p.position->lonDeg, 1.00023, 1e-12);
  EXPECT_NEAR(p.position->altAmslM, 101.15, 1e-9);
  EXPECT_TRUE(p.staleReason.empty());
}

TEST(PoseStore, PastTheNewestPositionItMovesOnAtTheReportedVelocity) {
  PoseStore::Config cfg;
  PoseStore store(cfg);
  GpsQuality fix;
  fix.fixType = 3;
  store.addGps(0, fix);
  GeoPosition moving{51.0, 1.0, 100.0, 10.0};
  moving.velNorthMs = 10.0;
  moving.velEastMs = -5.0;
  moving.velDownMs = -2.0;  // climbing
  store.addPosition(1000 * kMs, moving);
  const Pose p = store.at(1100 * kMs);  // 100 ms on, within the 150 ms hold
  ASSERT_TRUE(p.position.has_value()) << p.staleReason;
  constexpr double kMPerDegLat = 6378137.0 * 3.14159265358979323846 / 180.0;
  EXPECT_NEAR((p.position->latDeg - 51.0) * kMPerDegLat, 1.0, 1e-6);  // 10 m/s for 0.1 s
  EXPECT_NEAR((p.position->lonDeg - 1.0) * kMPerDegLat * std::cos(51.0 * kDeg), -0.5, 1e-6);
  EXPECT_NEAR(p.position->altAmslM, 100.2, 1e-9);
  EXPECT_NEAR(p.position->altRelM, 10.2, 1e-9);
  // So a keyframe need not wait for a position newer than it, only for an attitude
  // (held, not carried on): a position as old as the hold will do, never older.
  for (std::int64_t t = 1000 * kMs; t <= 1200 * kMs; t += 20 * kMs) {
    store.addAttitude(t, Quaternion{});
  }
  EXPECT_FALSE(store.covers(1100 * kMs));  // no position newer than the frame
  EXPECT_TRUE(store.covers(1100 * kMs, false, cfg.maxHoldNs));
  EXPECT_FALSE(store.covers(1000 * kMs + cfg.maxHoldNs + 1, false, cfg.maxHoldNs));
  EXPECT_FALSE(store.covers(1000 * kMs + cfg.maxHoldNs + 1, false, 10 * cfg.maxHoldNs));
  EXPECT_FALSE(store.covers(1220 * kMs, false, cfg.maxHoldNs));  // no attitude after it
  // Without a velocity it is held where it was; between samples nothing changes.
  PoseStore still(cfg);
  still.addGps(0, fix);
  still.addPosition(1000 * kMs, {51.0, 1.0, 100.0, 10.0});
  EXPECT_EQ(still.at(1100 * kMs).position->latDeg, 51.0);
  store.addPosition(1200 * kMs, moving);
  EXPECT_EQ(store.at(1100 * kMs).position->latDeg, 51.0);
}

TEST(PoseStore, SaysStaleInsteadOfInventingAPose) {
  PoseStore::Config cfg;
  PoseStore store(cfg);
  GpsQuality fix;
  fix.fixType = 3;
  store.addGps(0, fix);
  store.addAttitude(0, Quaternion{});
  store.addPosition(0, {1, 2, 3, 4});
  // Past the newest sample by more than the hold limit.
  Pose p = store.at(cfg.maxHoldNs + 10 * kMs);
  EXPECT_FALSE(p.attitude.has_value());
  EXPECT_FALSE(p.position.has_value());
  EXPECT_NE(p.staleReason.find("stale"), std::string::npos) << p.staleReason;
  // Within the hold limit: the last sample is used.
  p = store.at(cfg.maxHoldNs / 2);
  EXPECT_TRUE(p.attitude.has_value());
  // A hole in the samples wider than the gap limit.
  store.addAttitude(2000 * kMs, Quaternion{});
  p = store.at(1000 * kMs);
  EXPECT_FALSE(p.attitude.has_value());
  EXPECT_NE(p.staleReason.find("gap"), std::string::npos) << p.staleReason;
  // Before the first sample.
  p = store.at(-5 * kMs);
  EXPECT_FALSE(p.attitude.has_value());
}

TEST(PoseStore, AQuaternionThatIsNoRotationIsNotStored) {
  // Normalising a zero or NaN quaternion would make it level and facing north: an
  // attitude made up, not reported.
  PoseStore store;
  store.addAttitude(1000 * kMs, Quaternion{0, 0, 0, 0});
  store.addAttitude(1050 * kMs, Quaternion{NAN, 0, 0, 0});
  // Nor one far from unit length: corrupt, not a rotation (a float's is within 1e-6).
  EXPECT_FALSE(store.addAttitude(1020 * kMs, Quaternion{3e38, 3e38, 3e38, 3e38}));
  EXPECT_FALSE(store.addAttitude(1030 * kMs, Quaternion{2, 0, 0, 0}));
  EXPECT_TRUE(PoseStore().addAttitude(0, Quaternion{1.0001, 0, 0, 0}));  // rounding: taken
  store.addGimbal(1000 * kMs, Quaternion{0, 0, 0, 0}, true);
  Pose p = store.at(1000 * kMs);
  EXPECT_FALSE(p.attitude.has_value());
  EXPECT_FALSE(p.gimbal.has_value());
  EXPECT_NE(p.staleReason.find("no attitude"), std::string::npos) << p.staleReason;
  // Between good samples, a bad one is simply not there.
  store.addAttitude(1100 * kMs, quaternionFromEuler(0, 0, 20 * kDeg));
  store.addAttitude(1150 * kMs, Quaternion{0, 0, 0, 0});
  store.addAttitude(1200 * kMs, quaternionFromEuler(0, 0, 40 * kDeg));
  p = store.at(1150 * kMs);
  ASSERT_TRUE(p.attitude.has_value()) << p.staleReason;
  EXPECT_NEAR(angleBetween(*p.attitude, quaternionFromEuler(0, 0, 30 * kDeg)), 0.0, 1e-9);
}

TEST(PoseStore, NoFixMeansNoPosition) {
  PoseStore store;
  GpsQuality nofix;
  nofix.fixType = 1;
  store.addGps(0, nofix);
  store.addAttitude(0, Quaternion{});
  store.addAttitude(100 * kMs, Quaternion{});
  store.addPosition(0, {1, 2, 3, 4});
  store.addPosition(100 * kMs, {1, 2, 3, 4});
  const Pose p = store.at(50 * kMs);
  EXPECT_TRUE(p.attitude.has_value());
  EXPECT_FALSE(p.position.has_value());
  EXPECT_NE(p.staleReason.find("no GPS fix"), std::string::npos) << p.staleReason;
}

TEST(PoseStore, AFixNotReportedForLongGoesStale) {
  PoseStore::Config cfg;
  PoseStore store(cfg);
  GpsQuality fix;
  fix.fixType = 3;
  store.addGps(0, fix);  // then the receiver falls silent
  const std::int64_t late = cfg.maxGpsAgeNs + 1000 * kMs;
  for (std::int64_t t = 0; t <= late + 200 * kMs; t += 100 * kMs) {
    store.addAttitude(t, Quaternion{});
    store.addPosition(t, {1, 2, 3, 4});
  }
  Pose p = store.at(cfg.maxGpsAgeNs / 2);
  EXPECT_TRUE(p.position.has_value()) << p.staleReason;
  p = store.at(late);
  EXPECT_TRUE(p.attitude.has_value());
  EXPECT_FALSE(p.position.has_value());
  EXPECT_NE(p.staleReason.find("GPS status stale"), std::string::npos) << p.staleReason;
  // A new report of the fix brings the position back.
  store.addGps(late - 10 * kMs, fix);
  p = store.at(late);
  EXPECT_TRUE(p.position.has_value()) << p.staleReason;
}

TEST(PoseStore, BeforeTheFirstGpsReportOnlyAReportRightAfterCounts) {
  PoseStore::Config cfg;
  PoseStore store(cfg);
  for (std::int64_t t = 0; t <= 2000 * kMs; t += 100 * kMs) {
    store.addAttitude(t, Quaternion{});
    store.addPosition(t, {1, 2, 3, 4});
  }
  GpsQuality fix;
  fix.fixType = 3;
  store.addGps(1000 * kMs, fix);  // the first report of a fix
  Pose p = store.at(200 * kMs);   // long before it: the fix then is unknown
  EXPECT_FALSE(p.position.has_value());
  EXPECT_NE(p.staleReason.find("no GPS status yet"), std::string::npos) << p.staleReason;
  p = store.at(1000 * kMs - cfg.maxHoldNs / 2);  // just before: it holds
  EXPECT_TRUE(p.position.has_value()) << p.staleReason;
}

// Encoded packets into a decoder, arriving at `now` (CLOCK_MONOTONIC ns).
struct Feeder {
  explicit Feeder(TelemetryDecoder& d) : dec(d) {}
  TelemetryDecoder& dec;
  MavlinkParser parser;
  std::int64_t now = 10'000 * kMs;
  void operator()(const std::vector<std::uint8_t>& pkt) {
    parser.feed(pkt.data(), pkt.size(), [&](const mavlink_message_t& m) { dec.handle(m, now); });
  }
};

TEST(TelemetryDecoder, RejectsPositionsAtZeroZeroAndOutOfRange) {
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1);
  Feeder push{dec};
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  for (int i = 0; i <= 10; ++i) {
    push.now = (10'000 + i * 100) * kMs;
    const auto boot = static_cast<std::uint32_t>(i * 100);
    push(gpsRaw(ap, 3));
    push(attitudeQ(ap, boot, Quaternion{}));
    // An EKF without an origin yet reports 0,0; then garbage; then the real place.
    if (i < 4) push(position(ap, boot, 0.0, 0.0, 0.0));
    if (i == 4) push(position(ap, boot, 91.0, 20.0, 50.0));
    if (i == 5) push(position(ap, boot, 10.0, -180.5, 50.0));
    if (i >= 6) push(position(ap, boot, 10.0, 20.0, 50.0));
  }
  EXPECT_EQ(dec.stats().badPositions, 6U);
  EXPECT_EQ(dec.stats().position, 5U);
  Pose p = dec.poseAt(10'000 * kMs + 200 * kMs);
  EXPECT_TRUE(p.attitude.has_value());
  EXPECT_FALSE(p.position.has_value()) << "0,0 is not a position";
  p = dec.poseAt(10'000 * kMs + 750 * kMs);
  ASSERT_TRUE(p.position.has_value()) << p.staleReason;
  EXPECT_NEAR(p.position->latDeg, 10.0, 1e-9);
  // A lone 0 on one axis is a real place (the equator, the prime meridian).
  push(position(ap, 1100, 0.0, 20.0, 50.0));
  EXPECT_EQ(dec.stats().badPositions, 6U);
  // An altitude no aircraft flies at (an unset field: INT32_MAX mm) is no place either;
  // the Dead Sea's shore and a balloon's 40 km are.
  push(position(ap, 1200, 10.0, 20.0, 2147483.647));
  push(position(ap, 1300, 10.0, 20.0, -2000.0));
  EXPECT_EQ(dec.stats().badPositions, 8U);
  push(position(ap, 1400, 10.0, 20.0, -430.0));
  push(position(ap, 1500, 10.0, 20.0, 40000.0));
  EXPECT_EQ(dec.stats().badPositions, 8U);
}

TEST(TelemetryDecoder, ADopOfZeroIsUnknownNotPerfect) {
  // eph/epv: UINT16_MAX is "unknown", and so is 0 (a driver that never fills it in):
  // tagged as a DOP of 0 it would claim a perfect fix.
  for (const auto& [eph, epv, hdop, vdop] :
       {std::tuple<std::uint16_t, std::uint16_t, double, double>{80, 120, 0.8, 1.2},
        {0, 0, NAN, NAN},
        {UINT16_MAX, UINT16_MAX, NAN, NAN}}) {
    TelemetryDecoder dec;
    MavlinkEncoder ap(1, 1);
    Feeder push{dec};
    push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
    for (int i = 0; i <= 5; ++i) {
      push.now = (10'000 + i * 100) * kMs;
      const auto boot = static_cast<std::uint32_t>(i * 100);
      push(gpsRaw(ap, 3, eph, epv));
      push(attitudeQ(ap, boot, Quaternion{}));
      push(position(ap, boot, 10.0, 20.0, 50.0));
    }
    const Pose p = dec.poseAt(10'000 * kMs + 450 * kMs);
    ASSERT_TRUE(p.position.has_value()) << p.staleReason;
    EXPECT_EQ(p.gps.fixType, 3);
    if (std::isnan(hdop)) {
      EXPECT_TRUE(std::isnan(p.gps.hdop)) << eph << " -> " << p.gps.hdop;
      EXPECT_TRUE(std::isnan(p.gps.vdop)) << epv << " -> " << p.gps.vdop;
    } else {
      EXPECT_DOUBLE_EQ(p.gps.hdop, hdop);
      EXPECT_DOUBLE_EQ(p.gps.vdop, vdop);
    }
  }
}

// The camera starts on hasPose(): the clock estimate must have settled too, or the
// first keyframe (its first frame) waits for it. Arrivals only here: a second.
TEST(TelemetryDecoder, HasAPoseOnceTheClockHasSettled) {
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1);
  Feeder push{dec};
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  std::vector<bool> has;
  for (std::uint32_t i = 0; i <= 11; ++i) {
    push.now = (10'000 + i * 100) * kMs;
    push(gpsRaw(ap, 3));
    push(attitudeQ(ap, 5000 + i * 100, Quaternion{}));
    push(position(ap, 5000 + i * 100, 10.0, 20.0, 50.0));
    has.push_back(dec.hasPose());
  }
  std::vector<bool> expected(12, false);
  expected[10] = expected[11] = true;
  EXPECT_EQ(has, expected);
}

// A radio that reorders datagrams can deliver GPS_RAW_INT (whose time is not the boot
// clock) before any message with a boot time: its report waits for the first boot
// time instead of being stamped at boot 0, 25 minutes before the flight, and found
// stale by every keyframe.
TEST(TelemetryDecoder, AGpsReportBeforeAnyBootTimeIsStampedWithTheFirst) {
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1);
  Feeder push{dec};
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  push(gpsRaw(ap, 3));  // the only one
  constexpr std::uint32_t kBootMs = 1'500'000;
  for (std::uint32_t i = 0; i <= 10; ++i) {
    push.now = (10'000 + i * 100) * kMs;
    push(attitudeQ(ap, kBootMs + i * 100, Quaternion{}));
    push(position(ap, kBootMs + i * 100, 10.0, 20.0, 50.0));
  }
  EXPECT_EQ(dec.stats().gps, 1U);
  const Pose p = dec.poseAt(10'500 * kMs);
  ASSERT_TRUE(p.attitude.has_value()) << p.staleReason;
  EXPECT_TRUE(p.position.has_value()) << p.staleReason;
  // Later reports are stamped with the autopilot's time at their arrival.
  push.now = 11'050 * kMs;
  push(gpsRaw(ap, 1));  // the fix lost, 50 ms after the last boot time
  push.now = 11'100 * kMs;
  push(attitudeQ(ap, kBootMs + 1100, Quaternion{}));
  push(position(ap, kBootMs + 1100, 10.0, 20.0, 50.0));
  EXPECT_TRUE(dec.poseAt(11'040 * kMs).position.has_value());
  const Pose lost = dec.poseAt(11'080 * kMs);
  EXPECT_FALSE(lost.position.has_value());
  EXPECT_NE(lost.staleReason.find("no GPS fix"), std::string::npos) << lost.staleReason;
}

// `seconds` of an autopilot at 10 Hz (GPS_RAW_INT, ATTITUDE_QUATERNION q,
// GLOBAL_POSITION_INT at latitude lat) from localMs on the companion's clock, bootMs
// on the autopilot's.
void fly10Hz(Feeder& push, MavlinkEncoder& ap, std::int64_t localMs, std::uint32_t bootMs,
             int seconds, const Quaternion& q, double lat) {
  for (std::uint32_t i = 0; i <= static_cast<std::uint32_t>(seconds * 10); ++i) {
    push.now = (localMs + i * 100) * kMs;
    push(gpsRaw(ap, 3));
    push(attitudeQ(ap, bootMs + i * 100, q));
    push(position(ap, bootMs + i * 100, lat, 20.0, 50.0));
  }
}

// The autopilot reboots (time_boot_ms from 600 s back to 1 s). A frame from before the
// reboot that is looked up after it (a replay feeds telemetry 2 s ahead of its
// frames; a live keyframe may wait across it) is tagged from the old boot's history
// on the old boot's clock; frames after it from the new boot's.
TEST(TelemetryDecoder, FramesFromBeforeARebootAreTaggedFromTheBootBefore) {
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1);
  Feeder push{dec};
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  const Quaternion before = quaternionFromEuler(0, 0, 30 * kDeg);
  const Quaternion after = quaternionFromEuler(0, 0, 120 * kDeg);
  fly10Hz(push, ap, 10'000, 600'000, 2, before, 10.0);
  fly10Hz(push, ap, 12'500, 1'000, 2, after, 11.0);  // rebooted: the boot clock starts again
  EXPECT_EQ(dec.stats().reboots, 1U);
  const Pose old = dec.poseAt(11'500 * kMs);
  ASSERT_TRUE(old.attitude && old.position) << old.staleReason;
  EXPECT_NEAR(angleBetween(*old.attitude, before), 0.0, 1e-6);
  EXPECT_NEAR(old.position->latDeg, 10.0, 1e-9);
  EXPECT_TRUE(dec.covers(11'500 * kMs));  // nothing more to wait for from that boot
  const Pose now = dec.poseAt(13'500 * kMs);
  ASSERT_TRUE(now.attitude && now.position) << now.staleReason;
  EXPECT_NEAR(angleBetween(*now.attitude, after), 0.0, 1e-6);
  EXPECT_NEAR(now.position->latDeg, 11.0, 1e-9);
}

// The link is down for 20 s while the autopilot restarts (a battery swap on the bench):
// when it is heard again its clock reads 15 s, ahead of the 10 s last heard, so it
// never goes back; but it is 17 s behind the time that passed here. A reboot: frames
// from before the silence keep the old boot's poses, frames from the silence get
// none (the old history is not moved onto it), frames after it the new boot's.
TEST(TelemetryDecoder, AnAutopilotRebootedDuringALongerSilenceIsSeen) {
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1);
  Feeder push{dec};
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  const Quaternion before = quaternionFromEuler(0, 0, 30 * kDeg);
  const Quaternion after = quaternionFromEuler(0, 0, 120 * kDeg);
  fly10Hz(push, ap, 10'000, 8'000, 2, before, 10.0);  // boot 8 .. 10 s
  fly10Hz(push, ap, 32'000, 15'000, 5, after, 11.0);  // boot 15 .. 20 s, from 32 s here
  EXPECT_EQ(dec.stats().reboots, 1U);
  const Pose old = dec.poseAt(11'000 * kMs);
  ASSERT_TRUE(old.attitude && old.position) << old.staleReason;
  EXPECT_NEAR(angleBetween(*old.attitude, before), 0.0, 1e-6);
  EXPECT_NEAR(old.position->latDeg, 10.0, 1e-9);
  for (const std::int64_t silent : {13'000, 25'500, 26'000, 31'000}) {
    const Pose p = dec.poseAt(silent * kMs);
    EXPECT_FALSE(p.attitude || p.position) << silent << " ms: " << p.staleReason;
  }
  const Pose now = dec.poseAt(36'000 * kMs);
  ASSERT_TRUE(now.attitude && now.position) << now.staleReason;
  EXPECT_NEAR(angleBetween(*now.attitude, after), 0.0, 1e-6);
  EXPECT_NEAR(now.position->latDeg, 11.0, 1e-9);
}

// A link that stalls for 6 s and then releases what it held (a TCP stream over a
// cellular link): the backlog lags the time that passed here as a late-heard reboot
// would, but catches up, at once or half again faster than real time. No reboot: the
// history goes on, and poses after it are the stream's.
TEST(TelemetryDecoder, ABacklogAfterAStallIsNoReboot) {
  for (const double drain : {0.0, 1.5}) {  // 0: all at once; else this many times real time
    SCOPED_TRACE(drain);
    TelemetryDecoder dec;
    MavlinkEncoder ap(1, 1);
    Feeder push{dec};
    push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
    const Quaternion q = quaternionFromEuler(0, 0, 30 * kDeg);
    constexpr std::uint32_t kBootMs = 600'000;
    const auto send = [&](std::int64_t i) {  // the sample of 50 * i ms
      push(gpsRaw(ap, 3));
      push(attitudeQ(ap, static_cast<std::uint32_t>(kBootMs + i * 50), q));
      push(position(ap, static_cast<std::uint32_t>(kBootMs + i * 50), 10.0, 20.0, 50.0));
    };
    for (std::int64_t i = 0; i <= 100; ++i) {  // 5 s at 20 Hz, then the stall
      push.now = (10'000 + i * 50) * kMs;
      send(i);
    }
    // at 21 s the link comes back with the 6 s it held (samples 101..220), then live
    std::int64_t t = 21'000;
    std::int64_t i = 101;
    for (; 10'000 + i * 50 < t; ++i) {
      push.now = t * kMs;
      send(i);
      t += drain > 0 ? static_cast<std::int64_t>(50 / drain) : 0;
    }
    for (const std::int64_t end = i + 60; i <= end; ++i) {  // 3 s live
      push.now = (10'000 + i * 50) * kMs;
      send(i);
    }
    EXPECT_EQ(dec.stats().reboots, 0U);
    const Pose p = dec.poseAt((10'000 + (i - 20) * 50) * kMs);
    ASSERT_TRUE(p.attitude && p.position) << p.staleReason;
    EXPECT_NEAR(p.position->latDeg, 10.0, 1e-9);
    const Pose early = dec.poseAt(12'000 * kMs);  // before the stall: still there
    EXPECT_TRUE(early.attitude && early.position) << early.staleReason;
  }
}

// An autopilot rebooted two seconds after it started (a power glitch on the bench, a
// parameter reboot): its boot clock goes back by less than the 5 s that marks a reboot
// on its own, but it lags the time that passed here. Datagrams that overtook each
// other (a boot time 80 ms behind the last one) are no reboot.
TEST(TelemetryDecoder, AnAutopilotRebootedSecondsAfterItStartedIsSeen) {
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1);
  Feeder push{dec};
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  const Quaternion before = quaternionFromEuler(0, 0, 30 * kDeg);
  const Quaternion after = quaternionFromEuler(0, 0, 120 * kDeg);
  const auto fly = [&](std::int64_t localMs, std::uint32_t bootMs, const Quaternion& q) {
    for (std::uint32_t i = 0; i <= 20; ++i) {
      push.now = (localMs + i * 100) * kMs;
      push(attitudeQ(ap, bootMs + i * 100, q));
      if (i == 10) push(attitudeQ(ap, bootMs + i * 100 - 80, q));  // overtaken
    }
  };
  fly(10'000, 1'500, before);  // boot time 1.5 .. 3.5 s
  EXPECT_EQ(dec.stats().reboots, 0U);
  fly(13'000, 400, after);  // back by 3.1 s, 4.1 s behind the 1 s that passed here
  EXPECT_EQ(dec.stats().reboots, 1U);
  const Pose old = dec.poseAt(11'000 * kMs);
  ASSERT_TRUE(old.attitude) << old.staleReason;
  EXPECT_NEAR(angleBetween(*old.attitude, before), 0.0, 1e-6);
  const Pose now = dec.poseAt(14'000 * kMs);
  ASSERT_TRUE(now.attitude) << now.staleReason;
  EXPECT_NEAR(angleBetween(*now.attitude, after), 0.0, 1e-6);
}

// The same autopilot heard over two paths (a radio, and LTE through a router that
// does not drop duplicates), the second seconds behind: its copies go back on the
// boot clock at once, but newer messages follow them; no reboot, and the history
// and clock stay as the fast path makes them. So for a stream that stalled two
// seconds and goes on with a message sampled just before the last.
TEST(TelemetryDecoder, ACopyOverASlowerPathOrAStallIsNoReboot) {
  for (const std::int64_t lagMs : {2'500, 6'000}) {
    SCOPED_TRACE(lagMs);
    TelemetryDecoder dec;
    MavlinkEncoder ap(1, 1);
    Feeder push{dec};
    push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
    const Quaternion q = quaternionFromEuler(0, 0, 30 * kDeg);
    constexpr std::uint32_t kBootMs = 600'000;
    for (std::int64_t i = 0; i <= 200; ++i) {  // 10 s at 20 Hz
      push.now = (10'000 + i * 50) * kMs;
      push(gpsRaw(ap, 3));
      push(attitudeQ(ap, static_cast<std::uint32_t>(kBootMs + i * 50), q));
      push(position(ap, static_cast<std::uint32_t>(kBootMs + i * 50), 10.0, 20.0, 50.0));
      const std::int64_t lagged = i * 50 - lagMs;
      if (lagged >= 0) {  // the slow path's copy
        push(attitudeQ(ap, static_cast<std::uint32_t>(kBootMs + lagged), q));
        push(position(ap, static_cast<std::uint32_t>(kBootMs + lagged), 10.0, 20.0, 50.0));
      }
    }
    EXPECT_EQ(dec.stats().reboots, 0U);
    EXPECT_GT(dec.stats().staleBootTimes, 100U);
    const Pose p = dec.poseAt(19'900 * kMs);
    ASSERT_TRUE(p.attitude && p.position) << p.staleReason;
    // A stall: 2.1 s without a message, then one sampled 4 ms before the last.
    push.now = (10'000 + 200 * 50 + 2'100) * kMs;
    push(position(ap, kBootMs + 200 * 50 - 4, 10.0, 20.0, 50.0));
    push.now += 50 * kMs;
    push(attitudeQ(ap, kBootMs + 200 * 50 + 2'150, q));
    EXPECT_EQ(dec.stats().reboots, 0U);
  }
}

TEST(TelemetryDecoder, ASlowQuaternionStreamDoesNotHideAFastEulerOne) {
  // ATTITUDE at 20 Hz (what the daemon asks for) and ATTITUDE_QUATERNION at 1 Hz
  // (another ground station on a shared router asked for it): the quaternions alone
  // lie too far apart for a pose, so ATTITUDE is used.
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1);
  Feeder push{dec};
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  const Quaternion q = quaternionFromEuler(5 * kDeg, -3 * kDeg, 30 * kDeg);
  for (int i = 0; i <= 60; ++i) {
    const auto boot = static_cast<std::uint32_t>(i * 50);
    push.now = (10'000 + boot) * kMs;
    if (i % 20 == 0) push(attitudeQ(ap, boot, q));
    push(attitudeEuler(ap, boot, 5 * kDeg, -3 * kDeg, 30 * kDeg));
  }
  for (const std::int64_t ms : {525, 1990, 2975}) {
    const Pose p = dec.poseAt((10'000 + ms) * kMs);
    ASSERT_TRUE(p.attitude.has_value()) << ms << " ms: " << p.staleReason;
    EXPECT_NEAR(angleBetween(*p.attitude, q), 0.0, 1e-6);
  }
}

TEST(TelemetryDecoder, QuaternionsAtAGoodRateArePreferredUntilTheyStop) {
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1);
  Feeder push{dec};
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  // Both at 20 Hz, in either order; the Euler angles say 35 degrees less, to tell
  // which one is used. The quaternions stop after 1 s (the ground station that asked
  // for them left).
  const Quaternion q = quaternionFromEuler(0, 0, 45 * kDeg);
  const Quaternion euler = quaternionFromEuler(0, 0, 10 * kDeg);
  for (int i = 0; i <= 40; ++i) {
    const auto boot = static_cast<std::uint32_t>(i * 50);
    push.now = (10'000 + boot) * kMs;
    const auto e = attitudeEuler(ap, boot, 0, 0, 10 * kDeg);
    if (i > 20) {
      push(e);
    } else if (i % 2 == 0) {
      push(attitudeQ(ap, boot, q));
      push(e);
    } else {
      push(e);
      push(attitudeQ(ap, boot, q));
    }
  }
  for (const std::int64_t ms : {0, 25, 525, 975, 1000}) {
    const Pose p = dec.poseAt((10'000 + ms) * kMs);
    ASSERT_TRUE(p.attitude.has_value()) << ms << " ms: " << p.staleReason;
    EXPECT_NEAR(angleBetween(*p.attitude, q), 0.0, 1e-6) << ms << " ms";
  }
  // ATTITUDE takes over at once: no hole in the attitude, and none for seconds after.
  for (const std::int64_t ms : {1075, 1300, 1990}) {
    const Pose p = dec.poseAt((10'000 + ms) * kMs);
    ASSERT_TRUE(p.attitude.has_value()) << ms << " ms: " << p.staleReason;
    if (ms >= 1100) {
      EXPECT_NEAR(angleBetween(*p.attitude, euler), 0.0, 1e-6) << ms << " ms";
    }
  }
}

TEST(TelemetryDecoder, AQuaternionStreamSlowerThanAttitudeLetsAttitudeIn) {
  // ATTITUDE_QUATERNION at 5 Hz (samples 200 ms apart: usable), ATTITUDE at 20 Hz:
  // the faster stream gives the finer attitude, and both are the same estimate.
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1);
  Feeder push{dec};
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  for (int i = 0; i <= 40; ++i) {
    const auto boot = static_cast<std::uint32_t>(i * 50);
    push.now = (10'000 + boot) * kMs;
    const double yaw = i * 2 * kDeg;  // turning at 40 deg/s
    if (i % 4 == 0) push(attitudeQ(ap, boot, quaternionFromEuler(0, 0, yaw)));
    push(attitudeEuler(ap, boot, 0, 0, yaw));
  }
  // Each ATTITUDE that no quaternion of the same instant stands for (30), and the
  // quaternions (11).
  EXPECT_EQ(dec.stats().attitude, 41U);
  const Pose p = dec.poseAt((10'000 + 1075) * kMs);
  ASSERT_TRUE(p.attitude.has_value()) << p.staleReason;
  EXPECT_NEAR(angleBetween(*p.attitude, quaternionFromEuler(0, 0, 43 * kDeg)), 0.0, 1e-6);
}

TEST(TelemetryDecoder, NaNAnglesAndAZeroQuaternionAreNoAttitude) {
  // An estimator not aligned yet, or a sender's bug: not "level, facing north".
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1);
  Feeder push{dec};
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  for (int i = 0; i <= 10; ++i) {
    const auto boot = static_cast<std::uint32_t>(i * 50);
    push.now = (10'000 + boot) * kMs;
    push(attitudeQ(ap, boot, Quaternion{0, 0, 0, 0}));
    push(attitudeEuler(ap, boot + 20, NAN, 0, 0));
    push(attitudeEuler(ap, boot + 30, 0, std::numeric_limits<double>::infinity(), 0));
  }
  Pose p = dec.poseAt((10'000 + 250) * kMs);
  EXPECT_FALSE(p.attitude.has_value());
  EXPECT_EQ(dec.stats().attitude, 0U);
  EXPECT_EQ(dec.stats().badAttitudes, 33U);  // counted, as bad positions are
  // A stream of zero quaternions does not hide good ATTITUDE either.
  for (int i = 11; i <= 20; ++i) {
    const auto boot = static_cast<std::uint32_t>(i * 50);
    push.now = (10'000 + boot) * kMs;
    push(attitudeQ(ap, boot, Quaternion{0, 0, 0, 0}));
    push(attitudeEuler(ap, boot, 0, 0, 20 * kDeg));
  }
  p = dec.poseAt((10'000 + 775) * kMs);
  ASSERT_TRUE(p.attitude.has_value()) << p.staleReason;
  EXPECT_NEAR(angleBetween(*p.attitude, quaternionFromEuler(0, 0, 20 * kDeg)), 0.0, 1e-6);
}

TEST(TelemetryDecoder, ATlogsRecordTimesGiveUtcWithoutSystemTime) {
  MavlinkEncoder ap(1, 1);
  const std::int64_t t0 = 1'790'000'000'000'000'000;  // unix ns, as a tlog's records
  auto feed = [&](TelemetryDecoder& dec, bool systemTime) {
    MavlinkParser parser;
    auto push = [&](const std::vector<std::uint8_t>& pkt, std::int64_t now) {
      parser.feed(pkt.data(), pkt.size(), [&](const mavlink_message_t& m) { dec.handle(m, now); });
    };
    push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4), t0);
    for (int i = 0; i <= 10; ++i) {
      push(attitudeQ(ap, static_cast<std::uint32_t>(1000 + i * 100), Quaternion{}),
           t0 + i * 100 * kMs);
    }
    if (systemTime) {
      // GPS time 2.5 s ahead of the recording station's clock: it wins.
      push(ap.encode(
               [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
                 mavlink_msg_system_time_pack_status(s, c, st, m, t0 / 1000 + 2'500'000, 1000);
               }),
           t0);
    }
  };
  TelemetryDecoder live;  // arrival times on CLOCK_MONOTONIC: no UTC from them
  feed(live, false);
  EXPECT_FALSE(live.poseAt(t0 + 500 * kMs).utcUs.has_value());
  TelemetryDecoder tlog;
  tlog.setLocalClockIsUtc(true);
  feed(tlog, false);
  const Pose p = tlog.poseAt(t0 + 500 * kMs + 1234);
  ASSERT_TRUE(p.utcUs.has_value());
  EXPECT_EQ(*p.utcUs, t0 / 1000 + 500'000 + 1);
  // With SYSTEM_TIME the frames (their local time UTC, from --video-start) are placed
  // on the autopilot's clock by its GPS time, not by the station's record times: the
  // attitude sampled at boot time 1.5 s (GPS 3.0 s after t0) is the one at t0 + 3 s.
  TelemetryDecoder both;
  both.setLocalClockIsUtc(true);
  feed(both, true);
  EXPECT_EQ(both.clockSource(), ClockMapper::Source::SystemTime);
  EXPECT_TRUE(both.clockSettled());
  EXPECT_EQ(*both.clockOffsetNs(), t0 + 1500 * kMs);  // UTC - boot time
  const Pose at = both.poseAt(t0 + 3000 * kMs);
  ASSERT_TRUE(at.utcUs.has_value());
  EXPECT_EQ(*at.utcUs, t0 / 1000 + 3'000'000);
  EXPECT_TRUE(at.attitude.has_value()) << at.staleReason;
  // The station's clock ran 2.5 s behind GPS (the smallest latency is 0 here).
  ASSERT_TRUE(both.recordClockAheadNs().has_value());
  EXPECT_EQ(*both.recordClockAheadNs(), -2500 * kMs);
  // Before the autopilot's boot time 1.0 s (the first sample): nothing to tag with.
  EXPECT_FALSE(both.poseAt(t0 + 2000 * kMs).attitude.has_value());
  // A live link (local clock CLOCK_MONOTONIC) keeps mapping by arrival (TIMESYNC).
  TelemetryDecoder liveSys;
  feed(liveSys, true);
  EXPECT_EQ(liveSys.clockSource(), ClockMapper::Source::Arrival);
  EXPECT_FALSE(liveSys.recordClockAheadNs().has_value());
}

TEST(PoseStore, SlerpTakesTheShortWay) {
  const Quaternion a = quaternionFromEuler(0, 0, 179 * kDeg);
  const Quaternion b = quaternionFromEuler(0, 0, -179 * kDeg);
  const Quaternion m = slerp(a, b, 0.5);
  EXPECT_NEAR(angleBetween(m, quaternionFromEuler(0, 0, 180 * kDeg)), 0.0, 1e-9);
}

TEST(ClockMapper, ArrivalMinimumFindsTheOffsetUnderJitter) {
  ClockMapper clock;
  std::mt19937 rng(3);
  std::exponential_distribution<double> latency(1.0 / 3e6);  // mean 3 ms
  const std::int64_t trueOffset = 5'000'000'000'123;
  for (int i = 0; i < 500; ++i) {
    const std::uint32_t boot = 100'000 + static_cast<std::uint32_t>(i * 20);
    const auto lat = static_cast<std::int64_t>(latency(rng)) + 200'000;  // >= 0.2 ms
    clock.observeArrival(boot, boot * kMs + trueOffset + lat);
  }
  ASSERT_EQ(clock.source(), ClockMapper::Source::Arrival);
  const std::int64_t err = *clock.offsetNs() - trueOffset;
  EXPECT_GE(err, 0);
  EXPECT_LT(err, 1 * kMs);
}

TEST(ClockMapper, SettlesAfterASecondOfArrivalsOrOnTimesync) {
  ClockMapper clock;
  EXPECT_FALSE(clock.settled());
  const std::int64_t offset = 300 * kMs;
  for (int i = 0; i <= 45; ++i) {  // 20 ms apart: 0.9 s
    clock.observeArrival(1000 + static_cast<std::uint32_t>(i * 20), (1000 + i * 20) * kMs + offset);
  }
  EXPECT_EQ(clock.source(), ClockMapper::Source::Arrival);
  EXPECT_FALSE(clock.settled());
  for (int i = 46; i <= 50; ++i) {  // 1 s
    clock.observeArrival(1000 + static_cast<std::uint32_t>(i * 20), (1000 + i * 20) * kMs + offset);
  }
  EXPECT_TRUE(clock.settled());

  // TIMESYNC: the first answer waited 30 ms in a queue on its way back. Its bounds
  // alone put the offset 0.5 ms below to 30.5 ms above the truth; the arrival above
  // (no delay at all) caps it at the truth, so the estimate is 0.25 ms low and can be
  // no more than that off. Two quick answers settle it.
  ClockMapper synced;
  synced.observeArrival(1000, 1000 * kMs + offset);
  EXPECT_FALSE(synced.settled());
  EXPECT_FALSE(synced.uncertaintyNs().has_value());
  auto exchange = [&](std::int64_t sentLocal, std::int64_t there, std::int64_t back) {
    const std::int64_t tc1 = sentLocal + there - offset;  // their clock on receipt
    synced.observeTimesync(tc1, sentLocal, sentLocal + there + back);
  };
  exchange(1000 * kMs + offset, kMs / 2, 30 * kMs);
  EXPECT_EQ(synced.source(), ClockMapper::Source::Timesync);
  EXPECT_EQ(*synced.offsetNs() - offset, -kMs / 4);
  EXPECT_EQ(*synced.uncertaintyNs(), kMs / 4);
  EXPECT_FALSE(synced.settled());
  exchange(1100 * kMs + offset, kMs / 2, kMs / 2);
  exchange(1200 * kMs + offset, kMs / 2, kMs / 2);
  EXPECT_TRUE(synced.settled());
  EXPECT_EQ(*synced.offsetNs() - offset, -kMs / 4);
}

// A telemetry radio: every datagram, TIMESYNC answers included, delayed 5-60 ms, the
// requests going up 0-2 ms. A midpoint of each exchange would be off by a quarter of
// the spread; the tightest bounds of a few seconds of traffic are within a few ms.
// The answers keep the source TIMESYNC however slow they are, and the estimate moves
// little from one answer to the next.
TEST(ClockMapper, TimesyncBoundsHoldUpOnAJitteryRadio) {
  ClockMapper clock;
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> down(5e6, 60e6);
  std::uniform_real_distribution<double> up(0.0, 2e6);
  const std::int64_t trueOffset = 1'234'567 * kMs + 321'000;
  std::int64_t previous = 0;
  std::int64_t worstStep = 0;
  std::int64_t worstError = 0;
  for (int i = 0; i < 3000; ++i) {  // 30 s of 100 Hz telemetry
    const std::int64_t local = 2'000'000 * kMs + i * 10 * kMs;
    const auto boot = static_cast<std::uint32_t>((local - trueOffset) / kMs);
    clock.observeArrival(boot, boot * kMs + trueOffset + static_cast<std::int64_t>(down(rng)));
    if (i % 10 == 0) {  // TIMESYNC at 10 Hz
      const auto there = static_cast<std::int64_t>(up(rng));
      const auto back = static_cast<std::int64_t>(down(rng));
      clock.observeTimesync(local + there - trueOffset, local, local + there + back);
    }
    ASSERT_EQ(clock.source(), ClockMapper::Source::Timesync) << i;
    const std::int64_t estimate = *clock.offsetNs();
    const std::int64_t error = std::abs(estimate - trueOffset);
    // Never off by more than the bounds allow.
    ASSERT_LE(error, *clock.uncertaintyNs() + 1) << i;
    if (clock.settled()) {
      if (previous != 0) worstStep = std::max(worstStep, std::abs(estimate - previous));
      worstError = std::max(worstError, error);
    }
    previous = estimate;
  }
  std::printf("jittery radio: worst error %.2f ms once settled, worst step %.2f ms, last %.2f ms\n",
              static_cast<double>(worstError) / 1e6, static_cast<double>(worstStep) / 1e6,
              static_cast<double>(*clock.offsetNs() - trueOffset) / 1e6);
  EXPECT_LT(worstError, 5 * kMs);
  EXPECT_LT(worstStep, 2 * kMs);
  // After 30 s, the window's bounds: within the least delays (5 ms and 0).
  EXPECT_LT(std::abs(*clock.offsetNs() - trueOffset), 3 * kMs);
  EXPECT_LT(*clock.uncertaintyNs(), 3 * kMs);
}

// An autopilot whose TIMESYNC answers come from another clock than its messages'
// time_boot_ms: its bounds disagree with the arrivals' (above them, or far below),
// and the arrivals, stamped with the clock being mapped, are believed.
TEST(ClockMapper, TimesyncFromAnotherClockIsNotBelieved) {
  const std::int64_t offset = 700 * kMs;
  for (const std::int64_t skew : {-30 * kMs, 2000 * kMs, 0 * kMs}) {
    ClockMapper clock;
    for (int i = 0; i < 20; ++i) {
      const std::int64_t local = (5000 + i * 50) * kMs;
      const auto boot = static_cast<std::uint32_t>((local - offset) / kMs);
      clock.observeArrival(boot, local + 3 * kMs);  // 3 ms on the link
      if (i % 5 == 0) clock.observeTimesync(local - offset + skew + kMs, local, local + 2 * kMs);
    }
    const std::int64_t error = *clock.offsetNs() - offset;
    if (skew == 0) {
      EXPECT_EQ(clock.source(), ClockMapper::Source::Timesync);
      EXPECT_LE(std::abs(error), kMs);
    } else {
      EXPECT_EQ(clock.source(), ClockMapper::Source::Arrival) << skew;
      EXPECT_EQ(error, 3 * kMs) << skew;
      EXPECT_FALSE(clock.uncertaintyNs().has_value());
    }
  }
}

// The longest window (telemetry.clock_window_s = 600) over an autopilot crystal 50 ppm
// fast: the bounds from its two ends cross by 30 ms, which is drift, not another clock.
TEST(ClockMapper, ALongWindowTakesTheClocksDriftForDriftNotAnotherClock) {
  ClockMapper::Config config;
  config.arrivalWindowNs = 600'000'000'000;
  ClockMapper clock(config);
  const std::int64_t offset = 5'000 * kMs;
  const auto autopilotNs = [&](std::int64_t local) {
    return static_cast<std::int64_t>(static_cast<double>(local - offset) * (1.0 + 50e-6));
  };
  for (std::int64_t s = 0; s <= 700; ++s) {
    for (int k = 0; k < 10; ++k) {
      const std::int64_t local = 10'000 * kMs + s * 1000 * kMs + k * 100 * kMs;
      clock.observeArrival(static_cast<std::uint32_t>(autopilotNs(local) / kMs), local + kMs);
      if (k == 0) clock.observeTimesync(autopilotNs(local + kMs / 2), local, local + kMs);
    }
    if (s > 10) {
      ASSERT_EQ(clock.source(), ClockMapper::Source::Timesync) << s << " s";
    }
  }
  // The estimate: the window's middle, some 15 ms from now's offset at most.
  const std::int64_t now = 10'000 * kMs + 700'900 * kMs;
  EXPECT_LT(std::abs(*clock.offsetNs() - (now - autopilotNs(now))), 20 * kMs);
}

// A SYSTEM_TIME that is no time (a corrupt field, a CRC-valid garbage packet) is not
// taken: its microseconds would overflow as nanoseconds and date keyframes anywhere.
TEST(ClockMapper, ASystemTimeOutsideThisCenturyIsIgnored) {
  ClockMapper clock;
  clock.observeArrival(1000, 1000 * kMs);
  clock.observeSystemTime(0xFFFFFFFFFFFFFFFFULL, 1000);
  clock.observeSystemTime(123, 1000);  // 1970
  EXPECT_FALSE(clock.utcUs(1000 * kMs).has_value());
  clock.observeSystemTime(1'780'000'000'000'000ULL, 1000);
  ASSERT_TRUE(clock.utcUs(1000 * kMs).has_value());
  EXPECT_EQ(*clock.utcUs(1000 * kMs), 1'780'000'000'000'000LL);
}

TEST(ClockMapper, TimesyncWinsAndUtcFollows) {
  ClockMapper clock;
  const std::int64_t trueOffset = 777 * kMs;                       // local = autopilot + offset
  clock.observeArrival(1000, 1000 * kMs + trueOffset + 40 * kMs);  // a slow link
  for (int i = 0; i < 10; ++i) {
    const std::int64_t ts1 = (2000 + i * 1000) * kMs;     // our send time
    const std::int64_t tc1 = ts1 + 2 * kMs - trueOffset;  // their clock 2 ms later
    clock.observeTimesync(tc1, ts1, ts1 + 4 * kMs);       // 4 ms round trip
    clock.observeArrival(static_cast<std::uint32_t>((ts1 - trueOffset) / kMs), ts1 + 40 * kMs);
  }
  EXPECT_EQ(clock.source(), ClockMapper::Source::Timesync);
  EXPECT_NEAR(static_cast<double>(*clock.offsetNs() - trueOffset), 0.0, 1e5);
  clock.observeSystemTime(1'780'000'000'000'000ULL, 5000);
  const auto utc = clock.utcUs(5000 * kMs + trueOffset + 250 * kMs);
  ASSERT_TRUE(utc.has_value());
  EXPECT_NEAR(static_cast<double>(*utc), 1'780'000'000'250'000.0, 1.0);
}

TEST(MavlinkParser, SkipsGarbageAndCorruptFramesAndKeepsTheRest) {
  MavlinkEncoder ap(1, 1);
  std::vector<std::uint8_t> stream;
  std::mt19937 rng(7);
  int good = 0;
  int bursts = 0;
  for (int i = 0; i < 200; ++i) {
    auto pkt = attitudeQ(ap, static_cast<std::uint32_t>(i * 20), Quaternion{});
    if (i % 10 == 3) {
      pkt[pkt.size() / 2] ^= 0x5A;  // CRC error
    } else {
      ++good;
    }
    stream.insert(stream.end(), pkt.begin(), pkt.end());
    if (i % 7 == 0) {  // noise between frames, start bytes included
      ++bursts;
      for (int k = 0; k < 30; ++k) stream.push_back(static_cast<std::uint8_t>(rng()));
    }
  }
  MavlinkParser parser;
  int seen = 0;
  parser.feed(stream.data(), stream.size(), [&](const mavlink_message_t& m) {
    if (m.msgid == MAVLINK_MSG_ID_ATTITUDE_QUATERNION) ++seen;
  });
  // A false start byte in the noise can swallow the frame after it, when what it
  // starts comes out as another dialect's frame (not searched again), so at most one
  // good frame is lost per burst.
  EXPECT_GE(seen, good - bursts);
  EXPECT_LE(seen, good);
  EXPECT_GT(parser.stats().rejected, 0U);
  EXPECT_EQ(parser.stats().bytes, stream.size());
}

// A MAVLink 2 frame of message id 0x2AB8, which the common dialect lacks (another
// dialect's), from system 1 component 1, its checksum over CRC_EXTRA 0x5B.
std::vector<std::uint8_t> otherDialectFrame(std::uint8_t seq,
                                            const std::vector<std::uint8_t>& payload) {
  std::vector<std::uint8_t> f = {
      0xFD, static_cast<std::uint8_t>(payload.size()), 0, 0, seq, 1, 1, 0xB8, 0x2A, 0x00};
  f.insert(f.end(), payload.begin(), payload.end());
  std::uint16_t crc = crc_calculate(f.data() + 1, static_cast<std::uint16_t>(f.size() - 1));
  crc_accumulate(0x5B, &crc);
  f.push_back(static_cast<std::uint8_t>(crc & 0xFF));
  f.push_back(static_cast<std::uint8_t>(crc >> 8));
  return f;
}

TEST(MavlinkParser, CountsEachKindOfBadInputExactly) {
  MavlinkEncoder ap(1, 1);
  std::vector<std::uint8_t> s;
  const auto add = [&s](const std::vector<std::uint8_t>& p) {
    s.insert(s.end(), p.begin(), p.end());
  };
  add(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));  // good
  // A well-formed MAVLink 2 frame of an id the common dialect lacks (another
  // dialect's message: its CRC_EXTRA is unknown to us).
  const auto other = otherDialectFrame(7, {1, 2, 3, 4});
  add(other);
  auto corrupt = heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA);
  corrupt[12] ^= 0x21;  // a payload bit flipped in flight
  add(corrupt);
  add(std::vector<std::uint8_t>(10, 0x00));  // noise between frames, no start byte
  add(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));  // good
  // A frame cut short (the link dropped mid-packet), then silence filled by noise:
  // the parser completes it with the noise, the CRC fails, the rest is skipped.
  auto cut = heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA);
  const std::size_t kept = 12;
  const std::size_t missing = cut.size() - kept;
  cut.resize(kept);
  add(cut);
  add(std::vector<std::uint8_t>(missing + 5, 0x00));
  add(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));  // good
  MavlinkParser parser;
  int heartbeats = 0;
  std::vector<std::vector<std::uint8_t>> unknown;
  parser.feed(
      s.data(), s.size(),
      [&](const mavlink_message_t& m) {
        if (m.msgid == MAVLINK_MSG_ID_HEARTBEAT) ++heartbeats;
      },
      [&](const mavlink_message_t& m) {
        std::uint8_t buf[MAVLINK_MAX_PACKET_LEN];
        unknown.emplace_back(buf, buf + mavlink_msg_to_send_buffer(buf, &m));
      });
  EXPECT_EQ(heartbeats, 3);
  // The other dialect's frame is handed on as it came, for the record.
  ASSERT_EQ(unknown.size(), 1U);
  EXPECT_EQ(unknown[0], other);
  const ParserStats st = parser.stats();
  EXPECT_EQ(st.messages, 3U);
  EXPECT_EQ(st.unknownIds, 1U);
  EXPECT_EQ(st.rejected, 2U);
  EXPECT_EQ(st.skippedBytes, 10U + 5U);
  EXPECT_EQ(st.bytes, s.size());
}

// A MAVLink 2 frame that says it is signed: header, payload, checksum (over CRC_EXTRA
// 0x5B, as another dialect's message might have), then the 13-byte signature.
std::vector<std::uint8_t> signedFrame(std::uint32_t id, std::uint8_t seq,
                                      const std::vector<std::uint8_t>& payload) {
  const std::uint8_t header[] = {0xFD,
                                 static_cast<std::uint8_t>(payload.size()),
                                 MAVLINK_IFLAG_SIGNED,
                                 0,
                                 seq,
                                 1,
                                 1,
                                 static_cast<std::uint8_t>(id & 0xFF),
                                 static_cast<std::uint8_t>((id >> 8) & 0xFF),
                                 static_cast<std::uint8_t>(id >> 16)};
  std::vector<std::uint8_t> f;
  f.reserve(MAVLINK_MAX_PACKET_LEN);
  for (const std::uint8_t c : header) f.push_back(c);
  for (const std::uint8_t c : payload) f.push_back(c);
  std::uint16_t crc = crc_calculate(f.data() + 1, static_cast<std::uint16_t>(f.size() - 1));
  crc_accumulate(0x5B, &crc);
  f.push_back(static_cast<std::uint8_t>(crc & 0xFF));
  f.push_back(static_cast<std::uint8_t>(crc >> 8));
  for (int k = 0; k < MAVLINK_SIGNATURE_BLOCK_LEN; ++k)
    f.push_back(static_cast<std::uint8_t>(0x30 + k + seq));
  return f;
}

TEST(MavlinkParser, ASignedFrameOfAnotherDialectIsHandedOnOnce) {
  // The parser reports a signed frame's bad (or uncheckable) checksum twice: at the
  // checksum, with the previous frame still in its message buffer, and once the
  // signature has been read. Only the second is the frame.
  MavlinkEncoder ap(1, 1);
  std::vector<std::uint8_t> s;
  const auto add = [&s](const std::vector<std::uint8_t>& p) {
    s.insert(s.end(), p.begin(), p.end());
  };
  add(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  const auto a = signedFrame(0x2AB8, 7, {1, 2, 3, 4});
  const auto b = signedFrame(0x2AB9, 8, {5, 6, 7, 8, 9});
  add(a);
  add(b);
  // A known message, signed, corrupted in flight: rejected, once.
  auto corrupt = heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA);
  corrupt[2] |= MAVLINK_IFLAG_SIGNED;  // under the checksum: it no longer fits
  add(corrupt);
  add(std::vector<std::uint8_t>(MAVLINK_SIGNATURE_BLOCK_LEN, 0x11));
  add(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  MavlinkParser parser;
  int heartbeats = 0;
  std::vector<std::vector<std::uint8_t>> unknown;
  parser.feed(
      s.data(), s.size(),
      [&](const mavlink_message_t& m) {
        if (m.msgid == MAVLINK_MSG_ID_HEARTBEAT) ++heartbeats;
      },
      [&](const mavlink_message_t& m) {
        std::uint8_t buf[MAVLINK_MAX_PACKET_LEN];
        unknown.emplace_back(buf, buf + mavlink_msg_to_send_buffer(buf, &m));
      });
  EXPECT_EQ(heartbeats, 2);
  ASSERT_EQ(unknown.size(), 2U);
  EXPECT_EQ(unknown[0], a);  // as received, signature and all
  EXPECT_EQ(unknown[1], b);
  const ParserStats st = parser.stats();
  EXPECT_EQ(st.messages, 2U);
  EXPECT_EQ(st.unknownIds, 2U);
  EXPECT_EQ(st.rejected, 1U);
  EXPECT_EQ(st.skippedBytes, 0U);
}

TEST(MavlinkParser, ResetDropsAHalfReadFrame) {
  MavlinkEncoder ap(1, 1);
  auto cut = heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA);
  cut.resize(8);
  const auto good = heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA);
  MavlinkParser parser;
  int n = 0;
  parser.feed(cut.data(), cut.size(), [&](const mavlink_message_t&) { ++n; });
  parser.reset();
  parser.feed(good.data(), good.size(), [&](const mavlink_message_t&) { ++n; });
  EXPECT_EQ(n, 1);
  EXPECT_EQ(parser.stats().rejected, 1U);  // the frame cut short
  parser.reset();                          // between frames: nothing dropped
  parser.feed(good.data(), good.size(), [&](const mavlink_message_t&) { ++n; });
  EXPECT_EQ(n, 2);
  EXPECT_EQ(parser.stats().rejected, 1U);
  EXPECT_EQ(parser.stats().bytes, cut.size() + 2 * good.size());
}

// A frame cut short on a serial link (bytes lost in a UART overrun, a radio
// glitch) runs into the next frame; the next is found there, not lost with it.
TEST(MavlinkParser, AFrameCutShortDoesNotTakeTheNextWithIt) {
  MavlinkEncoder ap(1, 1);
  MavlinkEncoder ap1(1, 1, /*mavlink1=*/true);
  std::vector<std::uint8_t> s;
  int sent = 0;
  int cuts = 0;
  for (int i = 0; i < 60; ++i) {
    auto pkt = i % 3 == 0 ? heartbeat(ap1, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA)
                          : attitudeQ(ap, static_cast<std::uint32_t>(i * 20), Quaternion{});
    if (i % 4 == 1) {
      pkt.resize(pkt.size() - 1 - static_cast<std::size_t>(i % 7));  // the end lost
      ++cuts;
    } else {
      ++sent;
    }
    s.insert(s.end(), pkt.begin(), pkt.end());
  }
  // Fed whole and byte by byte (a serial read returns what has come).
  for (const std::size_t piece : {s.size(), std::size_t{1}, std::size_t{7}}) {
    MavlinkParser parser;
    int seen = 0;
    for (std::size_t at = 0; at < s.size(); at += piece) {
      parser.feed(s.data() + at, std::min(piece, s.size() - at),
                  [&](const mavlink_message_t&) { ++seen; });
    }
    EXPECT_EQ(seen, sent) << "piece " << piece;
    EXPECT_EQ(parser.stats().rejected, static_cast<std::uint64_t>(cuts)) << "piece " << piece;
    EXPECT_EQ(parser.stats().skippedBytes, 0U);
    EXPECT_EQ(parser.stats().bytes, s.size());
  }
}

// Flight-like traffic whose payloads hold start bytes (floats of any value): a
// frame that loses bytes on the line is searched again from its second byte, and the
// false starts in it are searched too, never handed on as another dialect's frame
// that would swallow the good frames after it.
TEST(MavlinkParser, FalseStartsInADamagedFrameSwallowNothing) {
  MavlinkEncoder ap(1, 1);
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> any(-4.0F, 4.0F);
  std::vector<std::uint8_t> s;
  int whole = 0;
  int damaged = 0;
  for (int i = 0; i < 2000; ++i) {
    auto pkt = attitudeEuler(ap, static_cast<std::uint32_t>(i * 4), any(rng), any(rng), any(rng));
    if (i % 10 == 0) {  // 3 bytes lost from its middle
      pkt.erase(pkt.begin() + static_cast<std::ptrdiff_t>(pkt.size() / 2),
                pkt.begin() + static_cast<std::ptrdiff_t>(pkt.size() / 2 + 3));
      ++damaged;
    } else {
      ++whole;
    }
    s.insert(s.end(), pkt.begin(), pkt.end());
  }
  MavlinkParser parser;
  int seen = 0;
  int unknown = 0;
  parser.feed(
      s.data(), s.size(), [&](const mavlink_message_t&) { ++seen; },
      [&](const mavlink_message_t&) { ++unknown; });
  EXPECT_EQ(seen, whole);
  EXPECT_EQ(unknown, 0);
  EXPECT_EQ(parser.stats().rejected, static_cast<std::uint64_t>(damaged));
  EXPECT_EQ(parser.stats().skippedBytes, 0U);
}

// A length byte hit by noise makes a frame claim more bytes than it has: in a UDP
// datagram the frames after it are found all the same; a datagram cut short loses
// only the frame it cuts.
TEST(MavlinkParser, ADatagramsFramesAfterABadLengthAreKept) {
  MavlinkEncoder ap(1, 1);
  std::vector<std::uint8_t> d;
  auto first = attitudeQ(ap, 20, Quaternion{});
  first[1] = 0xF0;  // the payload length
  d.insert(d.end(), first.begin(), first.end());
  for (int i = 0; i < 3; ++i) {
    const auto p = attitudeQ(ap, static_cast<std::uint32_t>(40 + 20 * i), Quaternion{});
    d.insert(d.end(), p.begin(), p.end());
  }
  const auto good = heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA);
  std::vector<std::uint8_t> cut = good;
  cut.resize(good.size() - 3);
  MavlinkParser parser;
  std::vector<std::uint32_t> ids;
  const auto onMessage = [&](const mavlink_message_t& m) { ids.push_back(m.msgid); };
  const auto none = [](const mavlink_message_t&) {};
  parser.feedDatagram(d.data(), d.size(), onMessage, none);
  EXPECT_EQ(ids, std::vector<std::uint32_t>(3, MAVLINK_MSG_ID_ATTITUDE_QUATERNION));
  EXPECT_EQ(parser.stats().rejected, 1U);  // the first, cut short by its datagram's end
  parser.feedDatagram(cut.data(), cut.size(), onMessage, none);
  parser.feedDatagram(good.data(), good.size(), onMessage, none);
  ASSERT_EQ(ids.size(), 4U);
  EXPECT_EQ(ids.back(), static_cast<std::uint32_t>(MAVLINK_MSG_ID_HEARTBEAT));
  EXPECT_EQ(parser.stats().rejected, 2U);
  EXPECT_EQ(parser.stats().bytes, d.size() + cut.size() + good.size());
}

// A frame's bytes are searched again only when it was rejected: another dialect's
// whole frame (ArduPilot's own messages) is handed on and the parser goes on after it,
// whatever its payload holds.
TEST(MavlinkParser, AnotherDialectsFrameIsNotSearchedAgain) {
  MavlinkEncoder ap(1, 1);
  const auto hb = heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA);
  // A payload that holds a whole heartbeat frame, CRC and all.
  const auto other = otherDialectFrame(9, hb);
  MavlinkParser parser;
  int good = 0;
  int unknown = 0;
  parser.feed(
      other.data(), other.size(), [&](const mavlink_message_t&) { ++good; },
      [&](const mavlink_message_t&) { ++unknown; });
  EXPECT_EQ(good, 0);
  EXPECT_EQ(unknown, 1);
  EXPECT_EQ(parser.stats().rejected, 0U);
}

TEST(MavlinkParser, ReadsMavlink1AndMavlink2) {
  MavlinkEncoder v1(1, 1, true);
  MavlinkEncoder v2(1, 1, false);
  auto a = heartbeat(v1, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA);
  auto b = heartbeat(v2, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA);
  EXPECT_EQ(a[0], 0xFE);
  EXPECT_EQ(b[0], 0xFD);
  a.insert(a.end(), b.begin(), b.end());
  MavlinkParser parser;
  int n = 0;
  parser.feed(a.data(), a.size(), [&](const mavlink_message_t&) { ++n; });
  EXPECT_EQ(n, 2);
  EXPECT_EQ(parser.stats().mavlink1, 1U);
}

TEST(MavlinkParser, AFrameIsRecordedAsItCameUntrimmedOrNot) {
  // SYSTEM_TIME early in a flight: time_boot_ms < 2^24, its payload's last byte 0. A
  // sender that does not trim sends all 12 bytes (MAVLink 2 allows it); rebuilt with
  // mavlink_msg_to_send_buffer it would be trimmed to 11 under the old checksum.
  std::vector<std::uint8_t> frame = {MAVLINK_STX, 12, 0, 0, 7, 1, 1, MAVLINK_MSG_ID_SYSTEM_TIME,
                                     0,           0};
  const std::uint64_t unixUs = 1'780'000'000'000'000ULL;
  const std::uint32_t bootMs = 123'456;
  for (int i = 0; i < 8; ++i) frame.push_back(static_cast<std::uint8_t>(unixUs >> (8 * i)));
  for (int i = 0; i < 4; ++i) frame.push_back(static_cast<std::uint8_t>(bootMs >> (8 * i)));
  std::uint16_t crc = 0;
  crc_init(&crc);
  crc_accumulate_buffer(&crc, reinterpret_cast<const char*>(frame.data() + 1), frame.size() - 1);
  crc_accumulate(MAVLINK_MSG_ID_SYSTEM_TIME_CRC, &crc);
  frame.push_back(static_cast<std::uint8_t>(crc & 0xFF));
  frame.push_back(static_cast<std::uint8_t>(crc >> 8));

  MavlinkEncoder v1(1, 1, true);
  const std::vector<std::uint8_t> trimmed = heartbeat(v1, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4);
  MavlinkEncoder v2(1, 1, false);
  const std::vector<std::uint8_t> heartbeat2 = heartbeat(v2, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4);
  for (const std::vector<std::uint8_t>& sent : {frame, trimmed, heartbeat2}) {
    MavlinkParser parser;
    std::vector<std::uint8_t> recorded;
    parser.feed(sent.data(), sent.size(), [&](const mavlink_message_t& m) {
      std::array<std::uint8_t, MAVLINK_MAX_PACKET_LEN> buf{};
      recorded.assign(buf.begin(), buf.begin() + static_cast<std::ptrdiff_t>(wireBytes(m, buf)));
    });
    EXPECT_EQ(recorded, sent);
    // ... and reads back as the message it was.
    MavlinkParser again;
    int n = 0;
    again.feed(recorded.data(), recorded.size(), [&](const mavlink_message_t&) { ++n; });
    EXPECT_EQ(n, 1);
  }
}

TEST(MavlinkParser, RandomBytesNeverCrash) {
  std::mt19937 rng(11);
  std::vector<std::uint8_t> junk(200'000);
  for (auto& b : junk) b = static_cast<std::uint8_t>(rng() % 4 == 0 ? 0xFD : rng());
  MavlinkParser parser;
  std::uint64_t n = 0;
  parser.feed(junk.data(), junk.size(), [&](const mavlink_message_t&) { ++n; });
  EXPECT_EQ(parser.stats().bytes, junk.size());
  EXPECT_LT(n, 5U);
}

TEST(TelemetryDecoder, FollowsTheChosenAutopilotOnly) {
  TelemetryDecoder dec;
  MavlinkEncoder gcs(255, 190), ap(1, 1), other(2, 1);
  Feeder push{dec};
  push(heartbeat(gcs, MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID));
  // ArduPilot's antenna tracker and a companion computer run "an autopilot" too, but
  // fly nothing: not followed.
  MavlinkEncoder tracker(3, 1), companion(1, 191);
  push(heartbeat(tracker, MAV_TYPE_ANTENNA_TRACKER, MAV_AUTOPILOT_ARDUPILOTMEGA));
  push(heartbeat(companion, MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_ARDUPILOTMEGA));
  EXPECT_EQ(dec.autopilotSinceNs(), std::numeric_limits<std::int64_t>::max());  // none yet
  push.now += 7 * kMs;
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4));
  EXPECT_EQ(dec.autopilotSinceNs(), 10'007 * kMs);  // named by this heartbeat
  push(heartbeat(other, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4));
  for (int i = 0; i <= 10; ++i) {
    push.now = (10'000 + i * 100) * kMs + 5 * kMs;
    const auto boot = static_cast<std::uint32_t>(i * 100);
    push(gpsRaw(ap, 3));
    push(attitudeQ(ap, boot, quaternionFromEuler(0, 0, 45 * kDeg)));
    push(position(ap, boot, 10.0 + i * 1e-5, 20.0, 50.0));
    push(attitudeQ(other, boot, quaternionFromEuler(0, 0, 90 * kDeg)));
    push(position(other, boot, -10.0, -20.0, 0.0));
  }
  EXPECT_EQ(dec.autopilotSystem(), 1);
  EXPECT_GT(dec.stats().otherSources, 10U);
  const Pose p = dec.poseAt(10'000 * kMs + 5 * kMs + 550 * kMs);
  ASSERT_TRUE(p.position.has_value()) << p.staleReason;
  ASSERT_TRUE(p.attitude.has_value()) << p.staleReason;
  EXPECT_NEAR(p.position->latDeg, 10.0 + 5.5e-5, 1e-9);
  EXPECT_NEAR(angleBetween(*p.attitude, quaternionFromEuler(0, 0, 45 * kDeg)), 0.0, 1e-6);
}

TEST(TelemetryDecoder, AChosenAutopilotThatIsNotTheFirstHeard) {
  TelemetryConfig cfg;
  cfg.autopilotSystem = 2;  // --autopilot 2:1
  cfg.autopilotComponent = 1;
  TelemetryDecoder dec(cfg);
  MavlinkEncoder first(1, 1), chosen(2, 1);
  Feeder push{dec};
  push(heartbeat(first, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4));
  push(heartbeat(chosen, MAV_TYPE_FIXED_WING, MAV_AUTOPILOT_ARDUPILOTMEGA));
  for (int i = 0; i <= 10; ++i) {
    push.now = (10'000 + i * 100) * kMs;
    const auto boot = static_cast<std::uint32_t>(i * 100);
    push(gpsRaw(first, 3));
    push(attitudeQ(first, boot, quaternionFromEuler(0, 0, 90 * kDeg)));
    push(position(first, boot, -10.0, -20.0, 0.0));
    push(gpsRaw(chosen, 3));
    push(attitudeQ(chosen, boot, quaternionFromEuler(0, 0, 45 * kDeg)));
    push(position(chosen, boot, 10.0, 20.0, 50.0));
  }
  EXPECT_EQ(dec.autopilotSystem(), 2);
  EXPECT_EQ(dec.autopilotComponent(), 1);
  // Both ids configured: its messages are its own from the first.
  EXPECT_EQ(dec.autopilotSinceNs(), std::numeric_limits<std::int64_t>::min());
  const Pose p = dec.poseAt(10'000 * kMs + 500 * kMs);
  ASSERT_TRUE(p.position.has_value()) << p.staleReason;
  EXPECT_NEAR(p.position->latDeg, 10.0, 1e-9);
  EXPECT_NEAR(angleBetween(*p.attitude, quaternionFromEuler(0, 0, 45 * kDeg)), 0.0, 1e-6);
}

TEST(PoseStore, GimbalInTheVehicleFrameTurnsWithTheHeading) {
  PoseStore store;
  // The vehicle heads 60 deg and banks 10 deg; the gimbal looks 30 deg right of the
  // nose, pitched 45 deg down, level to the horizon.
  store.addAttitude(1000 * kMs, quaternionFromEuler(10 * kDeg, 0, 60 * kDeg));
  store.addAttitude(1020 * kMs, quaternionFromEuler(10 * kDeg, 0, 60 * kDeg));
  store.addGimbal(990 * kMs, quaternionFromEuler(0, -45 * kDeg, 20 * kDeg), false);
  store.addGimbal(1030 * kMs, quaternionFromEuler(0, -45 * kDeg, 40 * kDeg), false);
  Pose p = store.at(1010 * kMs);
  ASSERT_TRUE(p.gimbal.has_value()) << p.gimbalReason;
  EXPECT_NEAR(angleBetween(*p.gimbal, quaternionFromEuler(0, -45 * kDeg, 90 * kDeg)), 0.0, 1e-9);

  // In the earth frame the heading does not matter.
  PoseStore earth;
  earth.addAttitude(1000 * kMs, quaternionFromEuler(0, 0, 60 * kDeg));
  earth.addGimbal(1000 * kMs, quaternionFromEuler(0, -90 * kDeg, 0), true);
  p = earth.at(1000 * kMs);
  ASSERT_TRUE(p.gimbal.has_value()) << p.gimbalReason;
  EXPECT_NEAR(angleBetween(*p.gimbal, quaternionFromEuler(0, -90 * kDeg, 0)), 0.0, 1e-9);
}

TEST(PoseStore, CoversWaitsForAGimbalOnceOneReports) {
  PoseStore store;
  GpsQuality fix;
  fix.fixType = 3;
  store.addGps(0, fix);
  store.addAttitude(1000 * kMs, quaternionFromEuler(0, 0, 0));
  store.addPosition(1000 * kMs, {51.0, 1.0, 100.0, 10.0});
  EXPECT_TRUE(store.covers(990 * kMs, true));  // no gimbal on the link: not waited for
  store.addGimbal(900 * kMs, quaternionFromEuler(0, -45 * kDeg, 0), true);
  EXPECT_FALSE(store.covers(990 * kMs, true));  // 5 Hz gimbal: its next report is due
  EXPECT_TRUE(store.covers(990 * kMs));         // a fixed mount does not wait for it
  store.addGimbal(1100 * kMs, quaternionFromEuler(0, -45 * kDeg, 0), true);
  EXPECT_TRUE(store.covers(990 * kMs, true));
  const Pose p = store.at(990 * kMs);
  EXPECT_TRUE(p.gimbal.has_value()) << p.gimbalReason;
}

TEST(PoseStore, AGimbalMayReportLessOftenThanTheAirframe) {
  // A stabilised gimbal holds its attitude while the airframe turns under it: its
  // reports (ArduPilot's EXTRA3 stream, 1-2 Hz unless asked for more) may lie further
  // apart than the airframe's attitude samples, up to their own limit.
  PoseStore::Config cfg;
  PoseStore store(cfg);
  ASSERT_EQ(store.maxGimbalGapNs(), 1000 * kMs);
  for (std::int64_t t = 1000; t <= 4000; t += 50) {
    store.addAttitude(t * kMs, quaternionFromEuler(0, 0, 60 * kDeg));
  }
  store.addGimbal(1000 * kMs, quaternionFromEuler(0, -80 * kDeg, 0), true);
  store.addGimbal(1500 * kMs, quaternionFromEuler(0, -90 * kDeg, 0), true);
  Pose p = store.at(1250 * kMs);
  ASSERT_TRUE(p.gimbal.has_value()) << p.gimbalReason;
  EXPECT_NEAR(angleBetween(*p.gimbal, quaternionFromEuler(0, -85 * kDeg, 0)), 0.0, 1e-9);
  // The airframe's own limit still holds for the airframe.
  EXPECT_TRUE(p.attitude.has_value()) << p.staleReason;
  // Further apart than the gimbal's limit: said, not interpolated.
  store.addGimbal(1500 * kMs + store.maxGimbalGapNs() + 1 * kMs,
                  quaternionFromEuler(0, -90 * kDeg, 0), true);
  p = store.at(2000 * kMs);
  EXPECT_FALSE(p.gimbal.has_value());
  EXPECT_NE(p.gimbalReason.find("gimbal attitude gap"), std::string::npos) << p.gimbalReason;
  EXPECT_TRUE(p.attitude.has_value());
  // An attitude gap limit set wider than that applies to the gimbal too.
  cfg.maxAttitudeGapNs = 3000 * kMs;
  EXPECT_EQ(PoseStore(cfg).maxGimbalGapNs(), 3000 * kMs);
}

TEST(PoseStore, HasAttitudeSinceLooksOnlyAtTheNewestSample) {
  // A link that has just started: one attitude sample, nothing before it. It counts
  // as delivering at once (the output thread then waits for the samples after a frame).
  PoseStore store;
  EXPECT_FALSE(store.hasAttitudeSince(0));
  store.addAttitude(1000 * kMs, quaternionFromEuler(0, 0, 0));
  EXPECT_TRUE(store.hasAttitudeSince(600 * kMs));
  EXPECT_TRUE(store.hasAttitudeSince(1000 * kMs));
  EXPECT_FALSE(store.hasAttitudeSince(1001 * kMs));
  store.addPosition(2000 * kMs, {51.0, 1.0, 100.0, 10.0});  // position is not attitude
  EXPECT_FALSE(store.hasAttitudeSince(1500 * kMs));
}

TEST(PoseStore, GimbalGapsAreSaidNotInvented) {
  PoseStore store;
  store.addAttitude(1000 * kMs, quaternionFromEuler(0, 0, 0));
  Pose p = store.at(1000 * kMs);
  EXPECT_FALSE(p.gimbal.has_value());
  EXPECT_EQ(p.gimbalReason, "no gimbal attitude");
  store.addGimbal(1000 * kMs, quaternionFromEuler(0, -45 * kDeg, 0), true);
  store.addGimbal(1000 * kMs + store.maxGimbalGapNs() + 10 * kMs,
                  quaternionFromEuler(0, -45 * kDeg, 0), true);
  p = store.at(1500 * kMs);
  EXPECT_FALSE(p.gimbal.has_value());
  EXPECT_NE(p.gimbalReason.find("gap"), std::string::npos) << p.gimbalReason;
  // Relative to a heading that is not known: no attitude.
  PoseStore noHeading;
  noHeading.addGimbal(1000 * kMs, quaternionFromEuler(0, -45 * kDeg, 0), false);
  p = noHeading.at(1000 * kMs);
  EXPECT_FALSE(p.gimbal.has_value());
  EXPECT_NE(p.gimbalReason.find("heading"), std::string::npos) << p.gimbalReason;
}

TEST(TelemetryDecoder, ReadsTheVehiclesGimbalInItsFrame) {
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1), gimbal(1, MAV_COMP_ID_GIMBAL), second(1, MAV_COMP_ID_GIMBAL2),
      otherVehicle(2, MAV_COMP_ID_GIMBAL);
  Feeder push{dec};
  // Before the autopilot is known, gimbal messages are not used.
  push(gimbalStatus(gimbal, 5, quaternionFromEuler(0, -30 * kDeg, 0),
                    GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME));
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  EXPECT_EQ(dec.stats().gimbal, 0U);
  for (int i = 0; i <= 10; ++i) {
    push.now = (10'000 + i * 100) * kMs;
    const auto boot = static_cast<std::uint32_t>(i * 100);
    push(gpsRaw(ap, 3));
    push(attitudeQ(ap, boot, quaternionFromEuler(0, 0, 90 * kDeg)));
    push(position(ap, boot, 10.0, 20.0, 50.0));
    // The gimbal's own clock is unrelated: 777 s since its boot.
    push(gimbalStatus(gimbal, 777'000 + boot, quaternionFromEuler(0, -30 * kDeg, 0),
                      GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME));
    push(gimbalStatus(second, boot, quaternionFromEuler(0, 0, 0), 0));
    push(gimbalStatus(otherVehicle, boot, quaternionFromEuler(0, 0, 0), 0));
  }
  EXPECT_EQ(dec.stats().gimbal, 11U);
  // A report that is no rotation is counted, not used.
  push(gimbalStatus(gimbal, 778'100, Quaternion{0, 0, 0, 0},
                    GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME));
  EXPECT_EQ(dec.stats().gimbal, 11U);
  EXPECT_EQ(dec.stats().badAttitudes, 1U);
  const Pose p = dec.poseAt(10'550 * kMs);
  ASSERT_TRUE(p.gimbal.has_value()) << p.gimbalReason;
  // 30 deg down, looking east (the vehicle's heading).
  EXPECT_NEAR(angleBetween(*p.gimbal, quaternionFromEuler(0, -30 * kDeg, 90 * kDeg)), 0.0, 1e-6);
}

// A tlog recorded by a station whose clock ran 3 s ahead of GPS time: the frames are
// placed by SYSTEM_TIME, and a separate gimbal component's reports (stamped with
// their arrival, the station's clock) must land at the same boot times as the
// autopilot's samples that came with them, not 3 s later.
TEST(TelemetryDecoder, ASeparateGimbalInATlogOnAWrongClockIsPlacedByTheAutopilotsArrivals) {
  TelemetryDecoder dec;
  dec.setLocalClockIsUtc(true);
  MavlinkEncoder ap(1, 1), gimbal(1, MAV_COMP_ID_GIMBAL);
  MavlinkParser parser;
  const std::int64_t utc0 = 1'790'000'000'000'000'000;  // UTC at the autopilot's boot
  const std::int64_t ahead = 3'000 * kMs;               // the station's clock error
  auto push = [&](const std::vector<std::uint8_t>& pkt, std::int64_t recordNs) {
    parser.feed(pkt.data(), pkt.size(),
                [&](const mavlink_message_t& m) { dec.handle(m, recordNs); });
  };
  // The gimbal pitches down by 1 degree every 100 ms of boot time, from -10 at 1.0 s.
  const auto pitchAt = [](std::int64_t bootMs) {
    return -10.0 - static_cast<double>(bootMs - 1000) / 100.0;
  };
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4), utc0 + ahead + 900 * kMs);
  for (std::int64_t ms = 1000; ms <= 2500; ms += 100) {
    const std::int64_t record = utc0 + ahead + ms * kMs;
    const auto boot = static_cast<std::uint32_t>(ms);
    push(attitudeQ(ap, boot, Quaternion{}), record);
    push(ap.encode([&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
      mavlink_msg_system_time_pack_status(
          s, c, st, m, static_cast<std::uint64_t>((utc0 + ms * kMs) / 1000), boot);
    }),
         record);
    // Its own clock: 777 s since the gimbal's boot.
    push(gimbalStatus(gimbal, static_cast<std::uint32_t>(777'000 + ms),
                      quaternionFromEuler(0, pitchAt(ms) * kDeg, 0),
                      GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME),
         record);
  }
  ASSERT_EQ(dec.clockSource(), ClockMapper::Source::SystemTime);
  EXPECT_EQ(dec.stats().gimbal, 16U);
  // A frame at boot time 1.55 s (its local time UTC, from --video-start).
  const Pose p = dec.poseAt(utc0 + 1550 * kMs);
  ASSERT_TRUE(p.attitude.has_value()) << p.staleReason;
  ASSERT_TRUE(p.gimbal.has_value()) << p.gimbalReason;
  EXPECT_NEAR(angleBetween(*p.gimbal, quaternionFromEuler(0, pitchAt(1550) * kDeg, 0)) / kDeg, 0.0,
              0.01);
}

TEST(TelemetryDecoder, LegacyYawLockMeansEarthFrame) {
  TelemetryDecoder dec;
  MavlinkEncoder ap(1, 1);
  Feeder push{dec};
  push(heartbeat(ap, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA));
  for (int i = 0; i <= 5; ++i) {
    push.now = (10'000 + i * 100) * kMs;
    const auto boot = static_cast<std::uint32_t>(i * 100);
    push(attitudeQ(ap, boot, quaternionFromEuler(0, 0, 90 * kDeg)));
    // ArduPilot sends it from the autopilot component, device id 1, on its boot clock.
    push(gimbalStatus(ap, boot, quaternionFromEuler(0, -60 * kDeg, 10 * kDeg),
                      GIMBAL_DEVICE_FLAGS_YAW_LOCK | GIMBAL_DEVICE_FLAGS_ROLL_LOCK, 1));
  }
  const Pose p = dec.poseAt(10'250 * kMs);
  ASSERT_TRUE(p.gimbal.has_value()) << p.gimbalReason;
  EXPECT_NEAR(angleBetween(*p.gimbal, quaternionFromEuler(0, -60 * kDeg, 10 * kDeg)), 0.0, 1e-6);
}

TEST(Tlog, RecordTimesOutOfLineAreMendedAndAStepIsKept) {
  constexpr std::int64_t s = 1'000'000'000;
  const auto packets = [](const std::vector<std::int64_t>& times) {
    std::vector<TimedPacket> out;
    for (std::int64_t t : times) out.push_back({t, {}});
    return out;
  };
  const auto times = [](const std::vector<TimedPacket>& ps) {
    std::vector<std::int64_t> out;
    for (const TimedPacket& p : ps) out.push_back(p.timeNs);
    return out;
  };
  const std::int64_t t0 = 1'780'000'000 * s;
  const std::int64_t ms = s / 1000;
  // One record 3 s early, two 30 s late, and a jitter of a few ms that stays.
  auto ps = packets({t0, t0 + 20 * ms, t0 - 3 * s, t0 + 60 * ms, t0 + 30 * s, t0 + 30 * s,
                     t0 + 120 * ms, t0 + 110 * ms, t0 + 160 * ms});
  EXPECT_EQ(mendRecordTimes(ps), 3U);
  EXPECT_EQ(times(ps),
            (std::vector<std::int64_t>{t0, t0 + 20 * ms, t0 + 20 * ms, t0 + 60 * ms, t0 + 60 * ms,
                                       t0 + 60 * ms, t0 + 120 * ms, t0 + 110 * ms, t0 + 160 * ms}));
  // The station's clock set back 30 s for good, and the first record out of line.
  ps = packets({t0 + 5 * s, t0, t0 + 20 * ms, t0 + 40 * ms, t0 - 30 * s, t0 - 30 * s + 20 * ms,
                t0 - 30 * s + 40 * ms, t0 - 30 * s + 60 * ms});
  EXPECT_EQ(mendRecordTimes(ps), 1U);
  EXPECT_EQ(times(ps), (std::vector<std::int64_t>{t0, t0, t0 + 20 * ms, t0 + 40 * ms, t0 - 30 * s,
                                                  t0 - 30 * s + 20 * ms, t0 - 30 * s + 40 * ms,
                                                  t0 - 30 * s + 60 * ms}));
  // Too short to tell, and empty: left as they are.
  ps = packets({t0, t0 + 9 * s});
  EXPECT_EQ(mendRecordTimes(ps), 0U);
  std::vector<TimedPacket> none;
  EXPECT_EQ(mendRecordTimes(none), 0U);
}

TEST(Tlog, ReadsRecordsSkipsGarbageAndReportsATruncatedEnd) {
  MavlinkEncoder ap(1, 1);
  const auto path = test::processTempDir("keyframed-unit") / "keyframed_test.tlog";
  std::vector<std::uint8_t> bytes;
  const std::uint64_t t0 = 1'780'000'000'000'000ULL;
  for (int i = 0; i < 20; ++i) {
    const std::uint64_t us = t0 + static_cast<std::uint64_t>(i) * 20'000;
    for (int k = 7; k >= 0; --k) bytes.push_back(static_cast<std::uint8_t>(us >> (8 * k)));
    const auto pkt = attitudeQ(ap, static_cast<std::uint32_t>(i * 20), Quaternion{});
    bytes.insert(bytes.end(), pkt.begin(), pkt.end());
    if (i == 5) bytes.insert(bytes.end(), 37, std::uint8_t{0x55});  // garbage between records
  }
  bytes.resize(bytes.size() - 7);  // cut the last packet short
  std::ofstream(path, std::ios::binary)
      .write(reinterpret_cast<const char*>(bytes.data()),
             static_cast<std::streamsize>(bytes.size()));

  TlogReader reader;
  std::string error;
  ASSERT_TRUE(reader.open(path.string(), error)) << error;
  std::int64_t t = 0;
  std::vector<std::uint8_t> pkt;
  int n = 0;
  while (reader.next(t, pkt)) {
    EXPECT_EQ(t, static_cast<std::int64_t>(t0 + static_cast<std::uint64_t>(n) * 20'000) * 1000);
    ++n;
  }
  EXPECT_EQ(n, 19);
  EXPECT_TRUE(reader.truncated());
  EXPECT_EQ(reader.resyncedBytes(), 37U);

  // Not a tlog at all.
  std::ofstream(path, std::ios::binary) << "this is not a tlog, just text\n";
  TlogReader bad;
  EXPECT_FALSE(bad.open(path.string(), error));
  EXPECT_NE(error.find("not a MAVLink tlog"), std::string::npos) << error;
  std::filesystem::remove(path);
}

TEST(MavlinkLink, ASerialWriteCutShortIsFinishedBeforeTheNextFrame) {
  // A pseudo-terminal stands for the serial port. Nobody reads its other end, so its
  // buffer fills, and a write then takes only the start of a frame: every frame the
  // link took must still arrive whole, in order (a cut one would also take the next
  // frame down with it at the receiver).
  const int master = ::posix_openpt(O_RDWR | O_NOCTTY);
  char name[128] = {};
  if (master < 0 || ::grantpt(master) != 0 || ::unlockpt(master) != 0 ||
      ::ptsname_r(master, name, sizeof name) != 0) {
    GTEST_SKIP() << "no pseudo-terminal";
  }
  ::fcntl(master, F_SETFL, ::fcntl(master, F_GETFL) | O_NONBLOCK);
  std::string error;
  auto link = openMavlinkLink(std::string("serial:") + name + ":115200", error);
  ASSERT_TRUE(link) << error;
  MavlinkEncoder cam(1, 100);
  const auto frame = [&](int i) {
    // file_url is a fixed 205-byte field that the packer copies whole.
    char url[205] = {};
    std::snprintf(url, sizeof url, "file:///k/%d.jpg", i);
    const float q[4] = {1, 0, 0, 0};
    return cam.encode(
        [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
          mavlink_msg_camera_image_captured_pack_status(s, c, st, m, 1000, 0, 0, 1, 2, 3, 4, q, i,
                                                        1, url);
        });
  };
  std::vector<std::uint8_t> sent;  // the frames the link took
  std::vector<std::uint8_t> refused;
  int taken = 0;
  for (; taken < 100'000; ++taken) {
    const auto f = frame(taken);
    if (!link->write(f.data(), f.size(), error)) {
      refused = f;
      break;
    }
    sent.insert(sent.end(), f.begin(), f.end());
  }
  ASSERT_FALSE(refused.empty()) << "the buffer never filled";
  ASSERT_TRUE(error.empty()) << error;  // a full buffer, not a broken link
  // Read the other end; the refused frame goes once the link has room again.
  std::vector<std::uint8_t> got;
  bool refusedTaken = false;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (std::chrono::steady_clock::now() < deadline) {
    std::uint8_t buf[4096];
    const ssize_t n = ::read(master, buf, sizeof buf);
    if (n > 0) got.insert(got.end(), buf, buf + n);
    if (!refusedTaken && link->write(refused.data(), refused.size(), error)) {
      refusedTaken = true;
      sent.insert(sent.end(), refused.begin(), refused.end());
    }
    if (refusedTaken && got.size() >= sent.size()) break;
    if (n <= 0) ::poll(nullptr, 0, 1);
  }
  EXPECT_TRUE(refusedTaken);
  EXPECT_TRUE(error.empty()) << error;
  EXPECT_EQ(got.size(), sent.size());
  EXPECT_TRUE(got == sent) << "the bytes that arrived are not the frames taken";
  MavlinkParser parser;
  int frames = 0;
  parser.feed(got.data(), got.size(), [&](const mavlink_message_t&) { ++frames; });
  EXPECT_EQ(frames, taken + 1);
  EXPECT_EQ(parser.stats().rejected, 0U);
  link.reset();
  ::close(master);
}

TEST(MavlinkLink, RejectsBadUrls) {
  std::string error;
  EXPECT_TRUE(parseMavlinkUrl("udpin:0.0.0.0:14550", error));
  EXPECT_TRUE(parseMavlinkUrl("udpout:127.0.0.1:14550", error));
  EXPECT_TRUE(parseMavlinkUrl("serial:/dev/ttyAMA0:921600", error));
  EXPECT_TRUE(parseMavlinkUrl("/dev/ttyUSB0", error));
  EXPECT_TRUE(parseMavlinkUrl("flight.tlog", error));
  EXPECT_FALSE(parseMavlinkUrl("udpin:0.0.0.0", error));
  EXPECT_FALSE(parseMavlinkUrl("serial:/dev/ttyS0:12345", error));
  EXPECT_NE(error.find("baud"), std::string::npos);
  EXPECT_FALSE(parseMavlinkUrl("tcp:1.2.3.4:5760", error));
  EXPECT_FALSE(openMavlinkLink("serial:/dev/does-not-exist:57600", error));
  EXPECT_NE(error.find("does-not-exist"), std::string::npos);
  // A stable serial name has colons of its own: the whole of it is the device.
  const std::string byPath = "/dev/serial/by-path/platform-xhci-usb-0:1.3:1.0-port0";
  EXPECT_TRUE(parseMavlinkUrl(byPath, error)) << error;
  EXPECT_FALSE(openMavlinkLink(byPath, error));
  EXPECT_NE(error.find(byPath), std::string::npos) << error;
  EXPECT_EQ(error.find("baud"), std::string::npos) << error;
  EXPECT_FALSE(openMavlinkLink("serial:" + byPath + ":921600", error));
  EXPECT_NE(error.find(byPath), std::string::npos) << error;
  EXPECT_FALSE(parseMavlinkUrl("serial:/dev/ttyS0:99999999999", error));
  EXPECT_NE(error.find("baud"), std::string::npos) << error;
}

}  // namespace
}  // namespace keyframed
