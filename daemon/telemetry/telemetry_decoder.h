#pragma once

#include <cstdint>
#include <limits>
#include <memory>
#include <mutex>
#include <optional>
#include <string>

#include "telemetry/clock_mapper.h"
#include "telemetry/mavlink_codec.h"
#include "telemetry/pose_store.h"

namespace keyframed {

struct TelemetryConfig {
  int autopilotSystem = 0;     // 0: the first system whose HEARTBEAT names an autopilot
  int autopilotComponent = 0;  // 0: that system's first autopilot component
  PoseStore::Config store;
  ClockMapper::Config clock;
};

struct TelemetryStats {
  std::uint64_t accepted = 0;      // messages from the chosen autopilot
  std::uint64_t otherSources = 0;  // messages from other systems/components
  std::uint64_t attitude = 0;
  std::uint64_t position = 0;
  std::uint64_t gps = 0;
  std::uint64_t gimbal = 0;   // GIMBAL_DEVICE_ATTITUDE_STATUS used
  std::uint64_t reboots = 0;  // time_boot_ms went backwards: history cleared
  // Messages seconds behind the boot clock (a slower path's copy, a stalled stream)
  // or the first of a reboot not yet believed: not used.
  std::uint64_t staleBootTimes = 0;
  std::uint64_t badPositions = 0;  // GLOBAL_POSITION_INT at 0,0 or out of range: not used
  // ATTITUDE with a NaN or infinite angle, ATTITUDE_QUATERNION or the gimbal's with a
  // NaN or zero quaternion: no rotation, not used
  std::uint64_t badAttitudes = 0;
};

// A GLOBAL_POSITION_INT that names a place: not 0,0 (what an estimator without an
// origin yet sends, and what an unset field reads) and within range (else corrupt).
bool plausiblePosition(const mavlink_global_position_int_t& p);

// Turns the autopilot's messages into pose history and clock mapping. Thread-safe:
// the telemetry thread calls handle(); any thread calls poseAt().
class TelemetryDecoder {
 public:
  explicit TelemetryDecoder(TelemetryConfig config = {});

  // msg arrived at localNs (the companion clock, or the tlog's record time).
  void handle(const mavlink_message_t& msg, std::int64_t localNs);
  // A replayed tlog (or a flight record made from one): the local clock (its record
  // times) is UTC. The autopilot's clock is then mapped by SYSTEM_TIME once it comes
  // (the record times are the recording station's clock), and a frame's UTC without
  // SYSTEM_TIME is its local time.
  void setLocalClockIsUtc(bool utc);
  // Our TIMESYNC request's answer (handled by the camera component).
  void handleTimesync(std::int64_t tc1Ns, std::int64_t ts1Ns, std::int64_t nowNs);

  // The pose at a frame time on the companion clock, with UTC when known. Empty
  // attitude/position with staleReason when telemetry cannot tell.
  [[nodiscard]] Pose poseAt(std::int64_t localNs) const;
  // True when telemetry newer than localNs has arrived (no need to wait more);
  // gimbal: the gimbal's too, once one has reported; positionLagNs as PoseStore::covers.
  [[nodiscard]] bool covers(std::int64_t localNs, bool gimbal = false,
                            std::int64_t positionLagNs = 0) const;
  // An attitude sample at or after localNs has arrived (false before the clock is mapped).
  [[nodiscard]] bool hasAttitudeSince(std::int64_t localNs) const;
  // True once the clock estimate has settled and attitude, position and (when a fix is
  // required) the GPS status have arrived.
  [[nodiscard]] bool hasPose() const;

  [[nodiscard]] TelemetryStats stats() const;
  [[nodiscard]] ClockMapper::Source clockSource() const;
  [[nodiscard]] std::optional<std::int64_t> clockOffsetNs() const;
  [[nodiscard]] bool clockSettled() const;        // ClockMapper::settled()
  [[nodiscard]] double clockRoundTripMs() const;  // best TIMESYNC round trip; NaN without
  // ClockMapper::uncertaintyNs() in ms; NaN when the clock is not mapped by TIMESYNC.
  [[nodiscard]] double clockUncertaintyMs() const;
  // Local clock UTC, mapped by SYSTEM_TIME: how far the record times run ahead of the
  // autopilot's UTC (ClockMapper::arrivalMinusSystemTimeNs).
  [[nodiscard]] std::optional<std::int64_t> recordClockAheadNs() const;
  [[nodiscard]] int autopilotSystem() const;
  [[nodiscard]] int autopilotComponent() const;
  // The local time of the HEARTBEAT that named the autopilot (INT64_MIN when both ids
  // are configured; INT64_MAX while none is known): what came before it was not
  // taken as the autopilot's, as it arrived. A replay, fed ahead of its frames, asks
  // this to record the vehicle's track as the live run did.
  [[nodiscard]] std::int64_t autopilotSinceNs() const;

 private:
  // When an attitude stream's samples come, on the autopilot's clock.
  struct StreamTiming {
    std::int64_t lastMs = -1;
    std::int64_t spacingMs = -1;  // between the last two; -1 until there are two
    void observe(std::int64_t ms);
  };

  bool accept(const mavlink_message_t& msg);
  void handleGimbal(const mavlink_message_t& msg, std::int64_t localNs);
  // False when the message's samples are not to be used: it lies seconds behind the
  // boot clock (a copy over a slower path, a stalled stream) and may be the first of a
  // reboot, which is believed once such messages have gone on for kRebootConfirmNs
  // with nothing newer in between; or, after a silence, it is ahead of the last boot
  // time but seconds behind the time that passed (a reboot heard late, or a backlog),
  // believed a reboot once it has kept our clock's pace for kRebootAheadConfirmNs.
  [[nodiscard]] bool observeBootTime(std::uint32_t bootMs, std::int64_t localNs);
  static constexpr std::int64_t kRebootConfirmNs = 500'000'000;
  static constexpr std::int64_t kRebootAheadConfirmNs = 2'000'000'000;
  [[nodiscard]] bool quaternionsStandFor(std::int64_t attitudeMs) const;
  // The boot whose history answers for localNs (the previous one before a reboot),
  // its clock's offset and UTC there. Takes mutex_.
  struct Lookup {
    std::shared_ptr<const PoseStore> store;
    std::optional<std::int64_t> offset;
    std::optional<std::int64_t> utcUs;
    bool previousBoot = false;
  };
  [[nodiscard]] Lookup lookup(std::int64_t localNs) const;

  TelemetryConfig config_;
  mutable std::mutex mutex_;  // guards everything but *store_ (which has its own lock)
  ClockMapper clock_;
  std::shared_ptr<PoseStore> store_;  // this boot's history (replaced at a reboot)
  // The boot before the last reboot: frames from before it (a replay feeds telemetry
  // ahead of its frames; a live keyframe may wait across it) are tagged from its
  // history on its clock, not left untagged.
  struct PreviousBoot {
    std::shared_ptr<const PoseStore> store;
    ClockMapper clock;
    std::int64_t rebootLocalNs = 0;  // the local time the new boot was first heard
  };
  std::optional<PreviousBoot> previous_;
  TelemetryStats stats_;
  int system_ = 0;
  int component_ = 0;
  std::int64_t autopilotSinceNs_ = std::numeric_limits<std::int64_t>::max();
  int gimbalComponent_ = -1;  // the first gimbal heard (component, device id) is used
  int gimbalDevice_ = -1;
  std::int64_t lastBootMs_ = -1;      // the newest boot time of this boot
  std::int64_t lastBootLocalNs_ = 0;  // when lastBootMs_ arrived
  // Messages seconds behind lastBootMs_, consistent with one another: a reboot, once
  // they have gone on long enough with nothing newer in between.
  struct RebootCandidate {
    std::int64_t bootMs = 0;
    std::int64_t localNs = 0;  // when the first of them came
    int count = 0;
  };
  std::optional<RebootCandidate> reboot_;
  std::int64_t lastMessageLocalNs_ = 0;   // when the last message with a boot time came
  std::optional<GpsQuality> pendingGps_;  // a GPS_RAW_INT before any boot time
  StreamTiming quaternions_;              // ATTITUDE_QUATERNION
  StreamTiming euler_;                    // ATTITUDE
  bool localClockIsUtc_ = false;
};

}  // namespace keyframed
