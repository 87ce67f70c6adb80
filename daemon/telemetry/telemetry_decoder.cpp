#include "telemetry/telemetry_decoder.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace keyframed {

namespace {
constexpr std::int64_t kMs = 1'000'000;
}

TelemetryDecoder::TelemetryDecoder(TelemetryConfig config)
    : config_(config),
      clock_(config.clock),
      store_(std::make_shared<PoseStore>(config.store)),
      system_(config.autopilotSystem),
      component_(config.autopilotComponent) {}

bool plausiblePosition(const mavlink_global_position_int_t& p) {
  // Altitudes from the Dead Sea's shore to a stratospheric balloon's (-1 km .. 50 km
  // above the sea, and as far from home): past them a field is garbage or unset
  // (INT32_MAX), not a place to tag.
  const auto altitude = [](std::int32_t mm) { return mm >= -1'000'000 && mm <= 50'000'000; };
  return !(p.lat == 0 && p.lon == 0) && p.lat >= -900'000'000 && p.lat <= 900'000'000 &&
         p.lon >= -1'800'000'000 && p.lon <= 1'800'000'000 && altitude(p.alt) &&
         p.relative_alt >= -51'000'000 && p.relative_alt <= 51'000'000;
}

namespace {

// Components that say they run an autopilot but fly nothing: ArduPilot's antenna
// tracker, and the peripherals a vehicle carries (a companion computer, ADS-B, a
// gimbal, ...). The autopilot followed is the first of the others.
bool peripheralType(std::uint8_t type) {
  switch (type) {
    case MAV_TYPE_ANTENNA_TRACKER:
    case MAV_TYPE_GCS:
    case MAV_TYPE_ONBOARD_CONTROLLER:
    case MAV_TYPE_GIMBAL:
    case MAV_TYPE_ADSB:
    case MAV_TYPE_CAMERA:
    case MAV_TYPE_CHARGING_STATION:
    case MAV_TYPE_FLARM:
    case MAV_TYPE_SERVO:
    case MAV_TYPE_ODID:
    case MAV_TYPE_BATTERY:
    case MAV_TYPE_PARACHUTE:
    case MAV_TYPE_LOG:
    case MAV_TYPE_OSD:
    case MAV_TYPE_IMU:
    case MAV_TYPE_GPS:
    case MAV_TYPE_WINCH: return true;
    default: return false;
  }
}

}  // namespace

bool TelemetryDecoder::accept(const mavlink_message_t& msg) {
  if (system_ == 0 || component_ == 0) {
    // Lock onto the first autopilot that says so in its HEARTBEAT.
    if (msg.msgid != MAVLINK_MSG_ID_HEARTBEAT) return false;
    mavlink_heartbeat_t hb;
    mavlink_msg_heartbeat_decode(&msg, &hb);
    if (hb.autopilot == MAV_AUTOPILOT_INVALID || peripheralType(hb.type)) return false;
    if (system_ != 0 && msg.sysid != system_) return false;
    if (component_ != 0 && msg.compid != component_) return false;
    system_ = msg.sysid;
    component_ = msg.compid;
    return true;
  }
  return msg.sysid == system_ && msg.compid == component_;
}

bool TelemetryDecoder::observeBootTime(std::uint32_t bootMs, std::int64_t localNs) {
  // A boot clock that goes back means the autopilot rebooted when it goes back by more
  // than a few seconds, or when it lags the time that passed here by more than two
  // (an autopilot that reboots seconds after it started: a reboot takes a second or
  // more). A datagram that overtook another goes back by no more than the jitter. So
  // may a copy of the stream over a slower path (a radio and LTE merged by a router)
  // or a stream that stalled: those are followed by newer messages at once, so a
  // reboot is believed only once the clock has stayed behind, and gone on consistently
  // from where it went back, for kRebootConfirmNs with at least three messages.
  // A reboot first heard after a silence longer than the old boot had run (the link
  // down while the autopilot restarted) finds its clock ahead of the last time heard,
  // yet seconds behind the time that passed here: the same lag, and the same test.
  // (Kept on the old boot's clock, its history would be moved onto the silence.) A
  // backlog that a stalled link releases lags too, but catches up: such a clock is
  // believed only once it has kept the pace of ours closely for kRebootAheadConfirmNs.
  const auto boot = static_cast<std::int64_t>(bootMs);
  // A reboot's messages come after the silence of the reboot: a candidate from before
  // a silence (the link, or this thread, stalled) starts afresh.
  if (localNs - lastMessageLocalNs_ > 1'000'000'000) reboot_.reset();
  lastMessageLocalNs_ = localNs;
  const std::int64_t back = lastBootMs_ - boot;
  const std::int64_t expected = lastBootMs_ + (localNs - lastBootLocalNs_) / kMs;
  if (lastBootMs_ >= 0 && (back > 5000 || (back != 0 && expected - boot > 2000))) {
    const bool ahead = back < 0;
    const bool goesOn = reboot_ && boot >= reboot_->bootMs - 100 &&
                        std::llabs((boot - reboot_->bootMs) - (localNs - reboot_->localNs) / kMs) <=
                            (ahead ? 250 : 1000);
    if (!goesOn) reboot_ = RebootCandidate{boot, localNs, 0};
    if (++reboot_->count < 3 ||
        localNs - reboot_->localNs < (ahead ? kRebootAheadConfirmNs : kRebootConfirmNs)) {
      ++stats_.staleBootTimes;
      return false;
    }
    previous_ = PreviousBoot{store_, clock_, reboot_->localNs};
    store_ = std::make_shared<PoseStore>(config_.store);
    clock_ = ClockMapper(config_.clock);
    clock_.setLocalIsUtc(localClockIsUtc_);
    quaternions_ = {};
    euler_ = {};
    ++stats_.reboots;
    lastBootMs_ = -1;  // the new boot's clock from here
    reboot_.reset();
  }
  if (back <= 100) reboot_.reset();  // on time (or a reordered datagram): no reboot
  if (boot > lastBootMs_) {
    lastBootMs_ = boot;
    lastBootLocalNs_ = localNs;
  }
  clock_.observeArrival(bootMs, localNs);
  if (pendingGps_) {
    store_->addGps(boot * kMs, *pendingGps_);
    pendingGps_.reset();
  }
  return true;
}

void TelemetryDecoder::StreamTiming::observe(std::int64_t ms) {
  if (ms <= lastMs) return;  // a repeat, or a reordered datagram
  if (lastMs >= 0) spacingMs = ms - lastMs;
  lastMs = ms;
}

// ATTITUDE and ATTITUDE_QUATERNION describe the same estimate, and the quaternion has
// no gimbal lock: an ATTITUDE is left out while the quaternions stand for it, that is
// while they come about as often as ATTITUDE (at most half again as far apart), close
// enough together for the pose store (within the attitude gap limit), and the next
// one is due. A slow quaternion stream (another ground station on a shared router
// asked for 1 Hz, a low-bandwidth stream profile) then never blanks out a fast
// ATTITUDE one, and ATTITUDE takes over at once when the quaternions stop.
bool TelemetryDecoder::quaternionsStandFor(std::int64_t attitudeMs) const {
  const StreamTiming& q = quaternions_;
  if (q.lastMs < 0) return false;
  if (attitudeMs == q.lastMs) return true;  // the same instant, in both streams
  if (q.spacingMs <= 0 || q.spacingMs > config_.store.maxAttitudeGapNs / kMs) return false;
  if (euler_.spacingMs > 0 && 2 * q.spacingMs > 3 * euler_.spacingMs) return false;
  // The quaternion of this instant may come right after it: due within 1.5 spacings.
  return attitudeMs - q.lastMs <= q.spacingMs * 3 / 2;
}

void TelemetryDecoder::handleGimbal(const mavlink_message_t& msg, std::int64_t localNs) {
  mavlink_gimbal_device_attitude_status_t g;
  mavlink_msg_gimbal_device_attitude_status_decode(&msg, &g);
  if (gimbalComponent_ < 0) {
    gimbalComponent_ = msg.compid;
    gimbalDevice_ = g.gimbal_device_id;
  }
  if (msg.compid != gimbalComponent_ || g.gimbal_device_id != gimbalDevice_) {
    ++stats_.otherSources;
    return;
  }
  const Quaternion q{g.q[0], g.q[1], g.q[2], g.q[3]};
  if (!usableRotation(q)) {
    ++stats_.badAttitudes;  // NaN or no rotation: nothing to use
    return;
  }
  // The frame of yaw: the explicit flags, else (older gimbals) YAW_LOCK means earth.
  bool earth = (g.flags & GIMBAL_DEVICE_FLAGS_YAW_LOCK) != 0;
  if (g.flags & GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME)
    earth = true;
  else if (g.flags & GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME)
    earth = false;
  std::int64_t t = 0;
  if (msg.compid == component_) {
    t = static_cast<std::int64_t>(g.time_boot_ms) * kMs;  // the autopilot's own clock
  } else {
    // A separate gimbal component counts time from its own boot: stamp the sample with
    // its arrival instead, mapped onto the autopilot's timeline by the arrivals of the
    // autopilot's own samples (the same link, the same latency). Not by offsetNs():
    // replaying a tlog that is GPS time (UTC - boot), and the arrivals are the record
    // station's clock, seconds off it may be.
    const auto offset = clock_.arrivalOffsetNs();
    if (!offset) return;
    t = localNs - *offset;
  }
  store_->addGimbal(t, q, earth);
  ++stats_.accepted;
  ++stats_.gimbal;
}

void TelemetryDecoder::handle(const mavlink_message_t& msg, std::int64_t localNs) {
  std::lock_guard lock(mutex_);
  if (msg.msgid == MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS && system_ != 0 &&
      component_ != 0 && msg.sysid == system_) {
    // From the autopilot itself (ArduPilot) or the vehicle's gimbal component.
    handleGimbal(msg, localNs);
    return;
  }
  const bool known = system_ != 0 && component_ != 0;
  if (!accept(msg)) {
    ++stats_.otherSources;
    return;
  }
  if (!known) autopilotSinceNs_ = localNs;
  ++stats_.accepted;
  switch (msg.msgid) {
    case MAVLINK_MSG_ID_ATTITUDE_QUATERNION: {
      mavlink_attitude_quaternion_t a;
      mavlink_msg_attitude_quaternion_decode(&msg, &a);
      if (!observeBootTime(a.time_boot_ms, localNs)) break;
      // Normalising a zero or NaN quaternion would make it level, facing north.
      if (!store_->addAttitude(a.time_boot_ms * kMs, {a.q1, a.q2, a.q3, a.q4})) {
        ++stats_.badAttitudes;
        break;
      }
      quaternions_.observe(a.time_boot_ms);
      ++stats_.attitude;
      break;
    }
    case MAVLINK_MSG_ID_ATTITUDE: {
      mavlink_attitude_t a;
      mavlink_msg_attitude_decode(&msg, &a);
      if (!observeBootTime(a.time_boot_ms, localNs)) break;
      if (!std::isfinite(a.roll) || !std::isfinite(a.pitch) || !std::isfinite(a.yaw)) {
        ++stats_.badAttitudes;
        break;
      }
      euler_.observe(a.time_boot_ms);
      if (quaternionsStandFor(a.time_boot_ms)) break;
      store_->addAttitude(a.time_boot_ms * kMs, quaternionFromEuler(a.roll, a.pitch, a.yaw));
      ++stats_.attitude;
      break;
    }
    case MAVLINK_MSG_ID_GLOBAL_POSITION_INT: {
      mavlink_global_position_int_t p;
      mavlink_msg_global_position_int_decode(&msg, &p);
      if (!observeBootTime(p.time_boot_ms, localNs)) break;
      if (!plausiblePosition(p)) {
        ++stats_.badPositions;
        break;
      }
      GeoPosition g;
      g.latDeg = p.lat * 1e-7;
      g.lonDeg = p.lon * 1e-7;
      g.altAmslM = p.alt * 1e-3;
      g.altRelM = p.relative_alt * 1e-3;
      g.velNorthMs = p.vx * 1e-2;
      g.velEastMs = p.vy * 1e-2;
      g.velDownMs = p.vz * 1e-2;
      store_->addPosition(p.time_boot_ms * kMs, g);
      ++stats_.position;
      break;
    }
    case MAVLINK_MSG_ID_GPS_RAW_INT: {
      mavlink_gps_raw_int_t r;
      mavlink_msg_gps_raw_int_decode(&msg, &r);
      GpsQuality q;
      q.fixType = r.fix_type;
      q.satellites = r.satellites_visible == 255 ? -1 : r.satellites_visible;
      // UINT16_MAX is "unknown"; so is 0 (drivers that never fill it in): a DOP of 0,
      // a perfect fix, would tag an accuracy of 0 m that bundle adjustment believes.
      q.hdop = r.eph == UINT16_MAX || r.eph == 0 ? NAN : r.eph / 100.0;
      q.vdop = r.epv == UINT16_MAX || r.epv == 0 ? NAN : r.epv / 100.0;
      // h_acc/v_acc are MAVLink 2 extensions (mm); 0 in MAVLink 1 frames = unknown.
      q.hAccuracyM = r.h_acc == 0 ? NAN : r.h_acc / 1000.0;
      q.vAccuracyM = r.v_acc == 0 ? NAN : r.v_acc / 1000.0;
      // time_usec is UTC or boot time depending on the autopilot: stamp GPS state
      // with the autopilot's time now instead (the newest boot time, plus the time
      // since it came), it changes slowly. Before any boot time has come (the first
      // datagrams of a radio that reorders them) it waits for the first one.
      if (lastBootMs_ >= 0) {
        store_->addGps(lastBootMs_ * kMs + std::max<std::int64_t>(localNs - lastBootLocalNs_, 0),
                       q);
      } else {
        pendingGps_ = q;
      }
      ++stats_.gps;
      break;
    }
    case MAVLINK_MSG_ID_SYSTEM_TIME: {
      mavlink_system_time_t s;
      mavlink_msg_system_time_decode(&msg, &s);
      if (!observeBootTime(s.time_boot_ms, localNs)) break;
      clock_.observeSystemTime(s.time_unix_usec, s.time_boot_ms);
      break;
    }
    default: break;
  }
}

void TelemetryDecoder::setLocalClockIsUtc(bool utc) {
  std::lock_guard lock(mutex_);
  localClockIsUtc_ = utc;
  clock_.setLocalIsUtc(utc);
}

void TelemetryDecoder::handleTimesync(std::int64_t tc1Ns, std::int64_t ts1Ns, std::int64_t nowNs) {
  std::lock_guard lock(mutex_);
  clock_.observeTimesync(tc1Ns, ts1Ns, nowNs);
}

TelemetryDecoder::Lookup TelemetryDecoder::lookup(std::int64_t localNs) const {
  std::lock_guard lock(mutex_);
  Lookup l;
  const bool before = previous_ && localNs < previous_->rebootLocalNs;
  const ClockMapper& clock = before ? previous_->clock : clock_;
  l.store = before ? previous_->store : store_;
  l.previousBoot = before;
  l.offset = clock.offsetNs();
  l.utcUs = clock.utcUs(localNs);
  if (!l.utcUs && localClockIsUtc_) {
    // The tlog's record times: the recording station's clock, not the autopilot's
    // GPS time, hence only without SYSTEM_TIME.
    l.utcUs = localNs >= 0 ? (localNs + 500) / 1000 : -((-localNs + 500) / 1000);
  }
  return l;
}

Pose TelemetryDecoder::poseAt(std::int64_t localNs) const {
  const Lookup l = lookup(localNs);
  if (!l.offset) {
    Pose p;
    p.timeNs = localNs;
    p.utcUs = l.utcUs;
    p.staleReason = "no telemetry";
    return p;
  }
  Pose p = l.store->at(localNs - *l.offset);
  p.timeNs = localNs;
  p.utcUs = l.utcUs;
  return p;
}

bool TelemetryDecoder::covers(std::int64_t localNs, bool gimbal, std::int64_t positionLagNs) const {
  const Lookup l = lookup(localNs);
  // The boot before a reboot has said all it will: nothing newer is worth waiting for.
  if (l.previousBoot) return true;
  return l.offset && l.store->covers(localNs - *l.offset, gimbal, positionLagNs);
}

bool TelemetryDecoder::hasAttitudeSince(std::int64_t localNs) const {
  const Lookup l = lookup(localNs);
  return l.offset && l.store->hasAttitudeSince(localNs - *l.offset);
}

bool TelemetryDecoder::hasPose() const {
  bool mapped = false;
  std::shared_ptr<const PoseStore> store;
  {
    std::lock_guard lock(mutex_);
    // Settled (so mapped), not only mapped: the first keyframe, the camera's first
    // frame, would otherwise wait for it.
    mapped = clock_.settled();
    store = store_;
  }
  // The receiver's status too: a camera started on attitude and position alone takes
  // its first keyframe before the GPS status arrives (a slower stream, a jittery
  // radio), and tags it with no position.
  return mapped && store->covers(std::numeric_limits<std::int64_t>::min()) && store->hasGpsStatus();
}

TelemetryStats TelemetryDecoder::stats() const {
  std::lock_guard lock(mutex_);
  return stats_;
}

ClockMapper::Source TelemetryDecoder::clockSource() const {
  std::lock_guard lock(mutex_);
  return clock_.source();
}

std::optional<std::int64_t> TelemetryDecoder::clockOffsetNs() const {
  std::lock_guard lock(mutex_);
  return clock_.offsetNs();
}

bool TelemetryDecoder::clockSettled() const {
  std::lock_guard lock(mutex_);
  return clock_.settled();
}

std::optional<std::int64_t> TelemetryDecoder::recordClockAheadNs() const {
  std::lock_guard lock(mutex_);
  return clock_.arrivalMinusSystemTimeNs();
}

double TelemetryDecoder::clockUncertaintyMs() const {
  std::lock_guard lock(mutex_);
  const auto u = clock_.uncertaintyNs();
  return u ? static_cast<double>(*u) / 1e6 : NAN;
}

double TelemetryDecoder::clockRoundTripMs() const {
  std::lock_guard lock(mutex_);
  return clock_.bestRoundTripMs();
}

std::int64_t TelemetryDecoder::autopilotSinceNs() const {
  std::lock_guard lock(mutex_);
  return system_ != 0 && component_ != 0 &&
                 autopilotSinceNs_ == std::numeric_limits<std::int64_t>::max()
             ? std::numeric_limits<std::int64_t>::min()  // configured
             : autopilotSinceNs_;
}

int TelemetryDecoder::autopilotSystem() const {
  std::lock_guard lock(mutex_);
  return system_;
}

int TelemetryDecoder::autopilotComponent() const {
  std::lock_guard lock(mutex_);
  return component_;
}

}  // namespace keyframed
