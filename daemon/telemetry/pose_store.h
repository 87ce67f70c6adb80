#pragma once

#include <cstdint>
#include <deque>
#include <mutex>
#include <optional>
#include <string>

#include "telemetry/pose.h"

namespace keyframed {

// Thread-safe, time-indexed history of the vehicle's attitude, position and GPS
// state on one timeline (the autopilot's clock, in ns). The telemetry thread adds
// samples; the output thread asks for the pose at a frame's time: attitude by
// slerp, position linearly, between the two samples around that time. A pose part
// is only given when samples lie close enough on both sides (or, past the newest
// sample, when that sample is recent enough); otherwise it is absent and the
// reason is said: a keyframe is never tagged with a fabricated position.
class PoseStore {
 public:
  struct Config {
    std::int64_t historyNs = 120'000'000'000;     // keep this much history
    std::int64_t maxAttitudeGapNs = 250'000'000;  // max spacing of the samples used
    std::int64_t maxPositionGapNs = 1'500'000'000;
    std::int64_t maxHoldNs = 150'000'000;  // past the newest sample: hold this long
    int minFixType = 3;                    // GPS_FIX_TYPE_3D_FIX
    // The GPS fix state (GPS_RAW_INT, 1-10 Hz) is trusted this long after its last report.
    std::int64_t maxGpsAgeNs = 3'000'000'000;
  };

  PoseStore() = default;
  explicit PoseStore(Config config) : config_(config) {}

  // The max spacing of the gimbal's samples used: maxAttitudeGapNs, and at least this.
  // A stabilised gimbal holds the attitude it is set to while the airframe turns under
  // it, so its reports may lie further apart than the airframe's (a gimbal reporting
  // at 1-2 Hz, with one report lost).
  static constexpr std::int64_t kMinGimbalGapNs = 1'000'000'000;
  [[nodiscard]] std::int64_t maxGimbalGapNs() const {
    return config_.maxAttitudeGapNs > kMinGimbalGapNs ? config_.maxAttitudeGapNs : kMinGimbalGapNs;
  }

  // False (nothing stored) for a quaternion that is no rotation (usableRotation()).
  bool addAttitude(std::int64_t timeNs, const Quaternion& bodyToNed);
  void addPosition(std::int64_t timeNs, const GeoPosition& position);
  void addGps(std::int64_t timeNs, const GpsQuality& gps);
  // A gimbal's attitude (gimbal FRD -> NED when earthFrame, else relative to the
  // vehicle frame: NED turned by the vehicle's heading, roll and pitch still to the
  // horizon, as GIMBAL_DEVICE_ATTITUDE_STATUS defines them). False as addAttitude.
  bool addGimbal(std::int64_t timeNs, const Quaternion& q, bool earthFrame);
  void clear();

  // The pose at timeNs (same timeline as the samples). Pose::timeNs = timeNs;
  // utcUs is left for the caller, who knows the clocks.
  [[nodiscard]] Pose at(std::int64_t timeNs) const;

  // True when samples newer than timeNs exist for attitude and position (and, with
  // gimbal, for a gimbal that has reported: it reports at a few Hz): the caller may
  // query without waiting for more. positionLagNs: a position up to this much older
  // will do (at() carries it on at its velocity for up to maxHoldNs).
  [[nodiscard]] bool covers(std::int64_t timeNs, bool gimbal = false,
                            std::int64_t positionLagNs = 0) const;
  [[nodiscard]] std::optional<std::int64_t> newestNs() const;
  // True when an attitude sample at or after timeNs has arrived.
  [[nodiscard]] bool hasAttitudeSince(std::int64_t timeNs) const;
  // True when the receiver's status (GPS_RAW_INT) has been heard, or none is needed
  // (minFixType 0): without it no position is tagged.
  [[nodiscard]] bool hasGpsStatus() const;
  [[nodiscard]] std::size_t size() const;

 private:
  template <typename T>
  struct Sample {
    std::int64_t timeNs;
    T value;
  };
  template <typename T>
  static void append(std::deque<Sample<T>>& q, std::int64_t timeNs, const T& value,
                     std::int64_t historyNs);

  Config config_;
  mutable std::mutex mutex_;
  std::deque<Sample<Quaternion>> attitude_;
  std::deque<Sample<GeoPosition>> position_;
  std::deque<Sample<GpsQuality>> gps_;
  struct GimbalSample {
    Quaternion q;
    bool earthFrame = true;
  };
  std::deque<Sample<GimbalSample>> gimbal_;
};

// Spherical linear interpolation between unit quaternions (shortest path).
Quaternion slerp(const Quaternion& a, const Quaternion& b, double t);
// The unit quaternion of q's direction; identity for a zero or NaN q (check those
// with usableRotation() where they may come from outside).
Quaternion normalized(const Quaternion& q);
// True when q, as received, describes a rotation: finite, and not (near) zero. A unit
// quaternion sent as floats has a norm of 1 to within 1e-7; an unset or zeroed one
// (an estimator not aligned yet) is no attitude at all, not "level, facing north".
bool usableRotation(const Quaternion& q);
// ZYX (yaw, pitch, roll) aeronautical Euler angles in radians -> body->NED quaternion.
Quaternion quaternionFromEuler(double roll, double pitch, double yaw);
// Hamilton product a * b (rotate by b, then by a).
Quaternion multiply(const Quaternion& a, const Quaternion& b);
// The heading (ZYX yaw, radians) of a body -> NED attitude.
double yawOf(const Quaternion& bodyToNed);
// Angle between two attitudes in radians.
double angleBetween(const Quaternion& a, const Quaternion& b);

}  // namespace keyframed
