#pragma once

#include <cmath>
#include <cstdint>
#include <optional>
#include <string>

namespace keyframed {

// Unit quaternion (Hamilton, w first). As an attitude it rotates vectors from the
// body (or camera) frame into the world frame: v_world = q * v_body * q^-1.
struct Quaternion {
  double w = 1.0;
  double x = 0.0;
  double y = 0.0;
  double z = 0.0;
};

// WGS84 position as the autopilot reports it.
struct GeoPosition {
  double latDeg = 0.0;
  double lonDeg = 0.0;
  double altAmslM = 0.0;  // GLOBAL_POSITION_INT.alt (MSL)
  double altRelM = 0.0;   // above home (GLOBAL_POSITION_INT.relative_alt)
  // Ground velocity, NED, m/s (GLOBAL_POSITION_INT.vx/vy/vz); NaN when unknown.
  double velNorthMs = NAN;
  double velEastMs = NAN;
  double velDownMs = NAN;
};

// GPS quality carried with a position (GPS_RAW_INT). NaN where unknown.
struct GpsQuality {
  int fixType = 0;  // GPS_FIX_TYPE: 0/1 no fix, 2 2D, 3 3D, 4 DGPS, 5/6 RTK
  int satellites = -1;
  double hdop = NAN;        // eph / 100
  double vdop = NAN;        // epv / 100
  double hAccuracyM = NAN;  // h_acc (1-sigma, metres)
  double vAccuracyM = NAN;  // v_acc (1-sigma, metres)
};

// The vehicle's state at one instant of the companion's clock, as the PoseStore
// interpolates it. Missing parts are absent, never zero-filled.
struct Pose {
  std::int64_t timeNs = 0;              // companion clock (CLOCK_MONOTONIC or replay time)
  std::optional<Quaternion> attitude;   // body FRD -> local NED
  std::optional<GeoPosition> position;  // absent without a 3D fix or when stale
  GpsQuality gps;                       // latest GPS_RAW_INT before timeNs
  std::optional<std::int64_t> utcUs;    // UTC of timeNs (unix microseconds) when known
  std::string staleReason;              // why attitude or position is absent; "" when fresh
  // A gimbal's attitude (gimbal FRD -> local NED; x is the camera's optical axis), when
  // the autopilot's system reports GIMBAL_DEVICE_ATTITUDE_STATUS; else why not.
  std::optional<Quaternion> gimbal;
  std::string gimbalReason;
};

}  // namespace keyframed
