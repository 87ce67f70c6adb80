#include "telemetry/pose_store.h"

#include <algorithm>
#include <cmath>
#include <vector>

namespace keyframed {

Quaternion normalized(const Quaternion& q) {
  const double n = std::sqrt(q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z);
  if (!(n > 0.0)) return Quaternion{};
  return {q.w / n, q.x / n, q.y / n, q.z / n};
}

bool usableRotation(const Quaternion& q) {
  const double n2 = q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z;
  // A NaN or infinite part makes n2 one too; one far from unit length is corrupt (a
  // float quaternion from an autopilot is unit to 1e-6), not a rotation to normalise.
  return std::isfinite(n2) && n2 >= 0.5 && n2 <= 2.0;
}

Quaternion slerp(const Quaternion& a, const Quaternion& b0, double t) {
  Quaternion b = b0;
  double d = a.w * b.w + a.x * b.x + a.y * b.y + a.z * b.z;
  if (d < 0.0) {  // q and -q are the same rotation: take the short way
    b = {-b.w, -b.x, -b.y, -b.z};
    d = -d;
  }
  double wa = 1.0 - t;
  double wb = t;
  if (d < 0.9995) {
    const double theta = std::acos(std::min(d, 1.0));
    const double s = std::sin(theta);
    wa = std::sin((1.0 - t) * theta) / s;
    wb = std::sin(t * theta) / s;
  }
  return normalized(
      {wa * a.w + wb * b.w, wa * a.x + wb * b.x, wa * a.y + wb * b.y, wa * a.z + wb * b.z});
}

Quaternion quaternionFromEuler(double roll, double pitch, double yaw) {
  const double cr = std::cos(roll / 2), sr = std::sin(roll / 2);
  const double cp = std::cos(pitch / 2), sp = std::sin(pitch / 2);
  const double cy = std::cos(yaw / 2), sy = std::sin(yaw / 2);
  return {cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
          cr * cp * sy - sr * sp * cy};
}

Quaternion multiply(const Quaternion& a, const Quaternion& b) {
  return {
      a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z, a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
      a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x, a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w};
}

double yawOf(const Quaternion& q0) {
  const Quaternion q = normalized(q0);
  return std::atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z));
}

double angleBetween(const Quaternion& a, const Quaternion& b) {
  const double d = std::fabs(a.w * b.w + a.x * b.x + a.y * b.y + a.z * b.z);
  return 2.0 * std::acos(std::min(d, 1.0));
}

template <typename T>
void PoseStore::append(std::deque<Sample<T>>& q, std::int64_t timeNs, const T& value,
                       std::int64_t historyNs) {
  if (!q.empty() && timeNs <= q.back().timeNs) {
    if (timeNs == q.back().timeNs) {
      q.back().value = value;
      return;
    }
    // Out of order (a reordered UDP datagram): insert in place.
    auto it = std::upper_bound(q.begin(), q.end(), timeNs,
                               [](std::int64_t t, const Sample<T>& s) { return t < s.timeNs; });
    q.insert(it, Sample<T>{timeNs, value});
    return;
  }
  q.push_back(Sample<T>{timeNs, value});
  while (q.size() > 2 && q.front().timeNs < timeNs - historyNs) q.pop_front();
}

bool PoseStore::addAttitude(std::int64_t timeNs, const Quaternion& bodyToNed) {
  if (!usableRotation(bodyToNed)) return false;
  std::lock_guard lock(mutex_);
  append(attitude_, timeNs, normalized(bodyToNed), config_.historyNs);
  return true;
}

void PoseStore::addPosition(std::int64_t timeNs, const GeoPosition& position) {
  std::lock_guard lock(mutex_);
  append(position_, timeNs, position, config_.historyNs);
}

void PoseStore::addGps(std::int64_t timeNs, const GpsQuality& gps) {
  std::lock_guard lock(mutex_);
  append(gps_, timeNs, gps, config_.historyNs);
}

bool PoseStore::addGimbal(std::int64_t timeNs, const Quaternion& q, bool earthFrame) {
  if (!usableRotation(q)) return false;
  std::lock_guard lock(mutex_);
  append(gimbal_, timeNs, GimbalSample{normalized(q), earthFrame}, config_.historyNs);
  return true;
}

void PoseStore::clear() {
  std::lock_guard lock(mutex_);
  gimbal_.clear();
  attitude_.clear();
  position_.clear();
  gps_.clear();
}

namespace {

// Finds the samples around t. Returns false with a reason when they are too far.
template <typename Q>
bool bracket(const Q& q, std::int64_t t, std::int64_t maxGap, std::int64_t maxHold, std::size_t& i0,
             std::size_t& i1, std::string& why, const char* what) {
  if (q.empty()) {
    why = std::string("no ") + what;
    return false;
  }
  auto it = std::lower_bound(q.begin(), q.end(), t,
                             [](const auto& s, std::int64_t v) { return s.timeNs < v; });
  if (it == q.end()) {
    const std::int64_t age = t - q.back().timeNs;
    if (age > maxHold) {
      why = std::string(what) + " stale (" + std::to_string(age / 1'000'000) + " ms old)";
      return false;
    }
    i0 = i1 = q.size() - 1;
    return true;
  }
  i1 = static_cast<std::size_t>(it - q.begin());
  if (it->timeNs == t) {
    i0 = i1;
    return true;
  }
  if (i1 == 0) {
    why = std::string(what) + " starts after the frame";
    return false;
  }
  i0 = i1 - 1;
  const std::int64_t gap = q[i1].timeNs - q[i0].timeNs;
  if (gap > maxGap) {
    why = std::string(what) + " gap of " + std::to_string(gap / 1'000'000) + " ms";
    return false;
  }
  return true;
}

double lerp(double a, double b, double t) {
  return a + (b - a) * t;
}

// Past the newest position (up to the hold, 150 ms): carried on at the velocity the
// autopilot reported with it, rather than left where it was (2 m behind at 15 m/s).
void extrapolate(GeoPosition& p, std::int64_t aheadNs) {
  if (!std::isfinite(p.velNorthMs) || !std::isfinite(p.velEastMs) || !std::isfinite(p.velDownMs)) {
    return;
  }
  constexpr double kEarthRadiusM = 6378137.0;  // WGS84 equatorial; metres over 150 ms
  constexpr double kDeg = 180.0 / 3.14159265358979323846;
  const double dt = static_cast<double>(aheadNs) / 1e9;
  const double cosLat = std::cos(p.latDeg / kDeg);
  p.latDeg += p.velNorthMs * dt / kEarthRadiusM * kDeg;
  if (cosLat > 1e-6) {
    p.lonDeg += p.velEastMs * dt / (kEarthRadiusM * cosLat) * kDeg;
    if (p.lonDeg > 180.0) p.lonDeg -= 360.0;
    if (p.lonDeg < -180.0) p.lonDeg += 360.0;
  }
  p.altAmslM -= p.velDownMs * dt;
  p.altRelM -= p.velDownMs * dt;
}

}  // namespace

Pose PoseStore::at(std::int64_t timeNs) const {
  std::lock_guard lock(mutex_);
  Pose pose;
  pose.timeNs = timeNs;
  std::vector<std::string> reasons;
  std::size_t i0 = 0, i1 = 0;
  std::string why;

  std::int64_t gpsAgeNs = 0;
  bool gpsKnown = false;
  if (!gps_.empty()) {
    auto it = std::upper_bound(gps_.begin(), gps_.end(), timeNs,
                               [](std::int64_t v, const auto& s) { return v < s.timeNs; });
    const auto& g = it == gps_.begin() ? gps_.front() : *std::prev(it);
    pose.gps = g.value;
    gpsAgeNs = timeNs - g.timeNs;
    // Before the first report, that report speaks for the moment only when it came
    // right after it (within the hold): the receiver may have had no fix earlier.
    gpsKnown = gpsAgeNs >= -config_.maxHoldNs;
  }

  if (bracket(attitude_, timeNs, config_.maxAttitudeGapNs, config_.maxHoldNs, i0, i1, why,
              "attitude")) {
    const auto& a = attitude_[i0];
    const auto& b = attitude_[i1];
    const double t = i0 == i1 ? 0.0
                              : static_cast<double>(timeNs - a.timeNs) /
                                    static_cast<double>(b.timeNs - a.timeNs);
    pose.attitude = slerp(a.value, b.value, t);
  } else {
    reasons.push_back(why);
  }

  if (!gpsKnown && config_.minFixType > 0) {
    reasons.emplace_back(gps_.empty() ? "no GPS status" : "no GPS status yet");
  } else if (pose.gps.fixType < config_.minFixType) {
    reasons.push_back("no GPS fix (fix type " + std::to_string(pose.gps.fixType) + ")");
  } else if (config_.minFixType > 0 && gpsAgeNs > config_.maxGpsAgeNs) {
    // The receiver stopped reporting: its last fix says nothing about now.
    reasons.push_back("GPS status stale (" + std::to_string(gpsAgeNs / 1'000'000) + " ms old)");
  } else if (bracket(position_, timeNs, config_.maxPositionGapNs, config_.maxHoldNs, i0, i1, why,
                     "position")) {
    const auto& a = position_[i0];
    const auto& b = position_[i1];
    const double t = i0 == i1 ? 0.0
                              : static_cast<double>(timeNs - a.timeNs) /
                                    static_cast<double>(b.timeNs - a.timeNs);
    GeoPosition p;
    p.latDeg = lerp(a.value.latDeg, b.value.latDeg, t);
    double dLon = b.value.lonDeg - a.value.lonDeg;  // across the antimeridian
    if (dLon > 180.0) dLon -= 360.0;
    if (dLon < -180.0) dLon += 360.0;
    p.lonDeg = a.value.lonDeg + dLon * t;
    if (p.lonDeg > 180.0) p.lonDeg -= 360.0;
    if (p.lonDeg < -180.0) p.lonDeg += 360.0;
    p.altAmslM = lerp(a.value.altAmslM, b.value.altAmslM, t);
    p.altRelM = lerp(a.value.altRelM, b.value.altRelM, t);
    p.velNorthMs = lerp(a.value.velNorthMs, b.value.velNorthMs, t);
    p.velEastMs = lerp(a.value.velEastMs, b.value.velEastMs, t);
    p.velDownMs = lerp(a.value.velDownMs, b.value.velDownMs, t);
    if (i0 == i1 && timeNs > a.timeNs) extrapolate(p, timeNs - a.timeNs);
    pose.position = p;
  } else {
    reasons.push_back(why);
  }

  if (bracket(gimbal_, timeNs, maxGimbalGapNs(), config_.maxHoldNs, i0, i1, why,
              "gimbal attitude")) {
    const auto& a = gimbal_[i0];
    const auto& b = gimbal_[i1];
    Quaternion q = a.value.q;
    bool earth = a.value.earthFrame;
    if (i0 != i1) {
      const double t =
          static_cast<double>(timeNs - a.timeNs) / static_cast<double>(b.timeNs - a.timeNs);
      if (a.value.earthFrame == b.value.earthFrame) {
        q = slerp(a.value.q, b.value.q, t);
      } else if (t >= 0.5) {  // the gimbal switched frames: no blend across the switch
        q = b.value.q;
        earth = b.value.earthFrame;
      }
    }
    if (earth) {
      pose.gimbal = q;
    } else if (pose.attitude) {
      // Vehicle frame: NED turned by the heading. q_earth = q_yaw * q_vehicle.
      const double yaw = yawOf(*pose.attitude);
      pose.gimbal = normalized(multiply({std::cos(yaw / 2), 0.0, 0.0, std::sin(yaw / 2)}, q));
    } else {
      pose.gimbalReason = "gimbal attitude is relative to the heading, and attitude is missing";
    }
  } else {
    pose.gimbalReason = why;
  }

  for (const auto& r : reasons) {
    if (!pose.staleReason.empty()) pose.staleReason += "; ";
    pose.staleReason += r;
  }
  return pose;
}

bool PoseStore::hasGpsStatus() const {
  std::lock_guard lock(mutex_);
  return config_.minFixType <= 0 || !gps_.empty();
}

bool PoseStore::covers(std::int64_t timeNs, bool gimbal, std::int64_t positionLagNs) const {
  std::lock_guard lock(mutex_);
  const bool att = !attitude_.empty() && attitude_.back().timeNs >= timeNs;
  const std::int64_t lag = std::clamp<std::int64_t>(positionLagNs, 0, config_.maxHoldNs);
  const bool pos = !position_.empty() && position_.back().timeNs >= timeNs - lag;
  const bool gim = !gimbal || gimbal_.empty() || gimbal_.back().timeNs >= timeNs;
  return att && pos && gim;
}

std::optional<std::int64_t> PoseStore::newestNs() const {
  std::lock_guard lock(mutex_);
  std::optional<std::int64_t> t;
  if (!attitude_.empty()) t = attitude_.back().timeNs;
  if (!position_.empty())
    t = std::max(t.value_or(position_.back().timeNs), position_.back().timeNs);
  return t;
}

bool PoseStore::hasAttitudeSince(std::int64_t timeNs) const {
  std::lock_guard lock(mutex_);
  return !attitude_.empty() && attitude_.back().timeNs >= timeNs;
}

std::size_t PoseStore::size() const {
  std::lock_guard lock(mutex_);
  return attitude_.size() + position_.size() + gps_.size();
}

}  // namespace keyframed
