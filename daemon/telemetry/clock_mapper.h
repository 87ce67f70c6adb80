#pragma once

#include <cstdint>
#include <deque>
#include <optional>

namespace keyframed {

// Maps the autopilot's clock (time_boot_ms) onto the companion's clock (the one
// frames are stamped with) and onto UTC.
//
// Two estimates of offset = local - autopilot:
//  - TIMESYNC: the companion sends ts1 = local time, the autopilot answers with its
//    own time tc1; offset = (ts1 + now) / 2 - tc1, good to half the round trip.
//    Samples with a round trip above 1.5x the best recent one are ignored; one with
//    the best round trip yet replaces the estimate, the others are averaged in.
//  - arrival: every timestamped message arrives after it was stamped, so
//    min(arrival - time_boot_ms) over a sliding window is the offset plus the
//    smallest latency seen. Used while TIMESYNC is not answered.
// SYSTEM_TIME gives UTC for the autopilot's clock.
//
// When the local clock is UTC (a tlog replayed: its record times, frames stamped
// from --video-start), SYSTEM_TIME is the offset itself (UTC - boot time, from the
// autopilot's GPS) and is preferred to the record times, which are the recording
// station's clock and may be seconds off.
class ClockMapper {
 public:
  enum class Source { None, Arrival, Timesync, SystemTime };

  struct Config {
    std::int64_t arrivalWindowNs = 10'000'000'000;   // sliding window of the min filter
    std::int64_t timesyncTimeoutNs = 5'000'000'000;  // fall back to arrival after this
  };

  ClockMapper() = default;
  explicit ClockMapper(Config config) : config_(config) {}

  void observeArrival(std::uint32_t bootMs, std::int64_t localNs);
  // tc1: autopilot time (ns), ts1: our time echoed (ns), nowNs: local arrival.
  void observeTimesync(std::int64_t tc1Ns, std::int64_t ts1Ns, std::int64_t nowNs);
  void observeSystemTime(std::uint64_t unixUs, std::uint32_t bootMs);
  // The local clock is UTC (see above).
  void setLocalIsUtc(bool utc) { localIsUtc_ = utc; }

  // Autopilot time (ns since its boot) -> local ns; empty until an estimate exists.
  [[nodiscard]] std::optional<std::int64_t> toLocalNs(std::int64_t bootNs) const;
  // Local ns -> UTC unix microseconds; empty until SYSTEM_TIME and an offset are known.
  [[nodiscard]] std::optional<std::int64_t> utcUs(std::int64_t localNs) const;

  [[nodiscard]] Source source() const;
  [[nodiscard]] std::optional<std::int64_t> offsetNs() const;  // local - autopilot
  // True once the estimate is worth tagging with: three TIMESYNC answers, or arrivals
  // over half a second. One answer, or the first few arrivals, can be late by a
  // scheduler's hiccup (tens of ms at start-up) that only more of them expose.
  [[nodiscard]] bool settled() const;
  [[nodiscard]] double bestRoundTripMs() const;  // NaN without TIMESYNC
  // With the local clock UTC and SYSTEM_TIME known: how far the arrival (record)
  // times run ahead of the autopilot's UTC, the smallest latency included.
  [[nodiscard]] std::optional<std::int64_t> arrivalMinusSystemTimeNs() const;

 private:
  struct Arrival {
    std::int64_t localNs;
    std::int64_t offsetNs;
  };

  Config config_;
  std::deque<Arrival> arrivals_;  // monotonic deque: offsets increasing from front
  std::int64_t firstArrivalNs_ = 0;
  std::int64_t lastArrivalNs_ = 0;
  std::optional<std::int64_t> timesyncOffsetNs_;
  std::int64_t timesyncAtNs_ = 0;
  std::int64_t bestRttNs_ = -1;
  int timesyncSamples_ = 0;  // used since the estimate (re)started
  std::optional<std::int64_t> utcMinusBootUs_;
  bool localIsUtc_ = false;
};

const char* toString(ClockMapper::Source source);

}  // namespace keyframed
