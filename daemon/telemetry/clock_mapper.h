#pragma once

#include <cstdint>
#include <deque>
#include <optional>
#include <utility>

namespace keyframed {

// Maps the autopilot's clock (time_boot_ms) onto the companion's clock (the one
// frames are stamped with) and onto UTC.
//
// offset = local - autopilot is bounded from both sides, and the estimate is the
// middle of the tightest bounds seen over a sliding window (an NTP-style filter that
// needs no model of the link's delays):
//  - arrival: every timestamped message arrives after it was stamped, so
//    offset <= arrival - time_boot_ms, for each of them;
//  - TIMESYNC: the companion sends ts1 = local time and the autopilot answers with its
//    own time tc1, read between our send and the answer's arrival (now), so
//    ts1 - tc1 <= offset <= now - tc1.
// The least delayed datagrams give the tightest bounds, so a jittery radio that
// delays most of them by tens of ms costs nothing once a few got through quickly;
// half the width of the bounds is the most the estimate can be off. With TIMESYNC
// unanswered there is no lower bound, and the estimate is the upper one (the offset
// plus the smallest latency seen).
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
    std::int64_t arrivalWindowNs = 10'000'000'000;   // sliding window of both bounds
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
  // over a second. One answer, or the first few arrivals, can be late by a
  // scheduler's hiccup (tens of ms at start-up) that only more of them expose.
  [[nodiscard]] bool settled() const;
  [[nodiscard]] double bestRoundTripMs() const;  // in the window; NaN without TIMESYNC
  // Half the width of the bounds (the most the TIMESYNC estimate can be off); empty
  // when the source is not TIMESYNC.
  [[nodiscard]] std::optional<std::int64_t> uncertaintyNs() const;
  // With the local clock UTC and SYSTEM_TIME known: how far the arrival (record)
  // times run ahead of the autopilot's UTC, the smallest latency included.
  [[nodiscard]] std::optional<std::int64_t> arrivalMinusSystemTimeNs() const;
  // Local minus autopilot time as the arrivals measure it (the smallest latency
  // included), on the clock the arrivals are stamped with, whatever the source: what
  // places a sample stamped only with its arrival. Empty before any arrival.
  [[nodiscard]] std::optional<std::int64_t> arrivalOffsetNs() const;

 private:
  struct Arrival {
    std::int64_t localNs;
    std::int64_t offsetNs;
  };
  struct Answer {          // one TIMESYNC exchange
    std::int64_t localNs;  // when the answer arrived
    std::int64_t lowerNs;  // ts1 - tc1
    std::int64_t upperNs;  // now - tc1
  };
  // The TIMESYNC bounds when answers are current: {lower, upper}, the upper one
  // tightened by the arrivals'.
  [[nodiscard]] std::optional<std::pair<std::int64_t, std::int64_t>> timesyncBounds() const;
  // False when TIMESYNC's bounds are far from the arrivals' (see the .cpp).
  [[nodiscard]] bool timesyncAgreesWithArrivals() const;

  Config config_;
  std::deque<Arrival> arrivals_;  // monotonic deque: offsets increasing from front
  std::int64_t firstArrivalNs_ = 0;
  std::int64_t lastArrivalNs_ = 0;
  std::deque<Answer> answers_;  // within the window, oldest first
  std::int64_t lowerNs_ = 0;    // max lowerNs over answers_
  std::int64_t upperNs_ = 0;    // min upperNs over answers_
  std::int64_t bestRttNs_ = -1;
  int timesyncSamples_ = 0;  // answers since the estimate (re)started
  std::optional<std::int64_t> utcMinusBootUs_;
  bool localIsUtc_ = false;
};

const char* toString(ClockMapper::Source source);

}  // namespace keyframed
