#include "telemetry/clock_mapper.h"

#include <algorithm>
#include <cmath>

namespace keyframed {

namespace {
// The least delayed of N arrivals is late by about the spread of the link's delays over
// N: on a 5-60 ms radio at ~100 messages/s, a 4 ms excess is left after half a second
// in one start in 50, after a second in one in 3000 (and a loaded start-up adds).
constexpr std::int64_t kArrivalSettleNs = 1'000'000'000;
}  // namespace

void ClockMapper::observeArrival(std::uint32_t bootMs, std::int64_t localNs) {
  const std::int64_t offset = localNs - static_cast<std::int64_t>(bootMs) * 1'000'000;
  if (arrivals_.empty()) firstArrivalNs_ = localNs;
  // Sliding-window minimum: drop entries that can never be the minimum again.
  while (!arrivals_.empty() && arrivals_.back().offsetNs >= offset) arrivals_.pop_back();
  arrivals_.push_back({localNs, offset});
  while (arrivals_.size() > 1 && arrivals_.front().localNs < localNs - config_.arrivalWindowNs) {
    arrivals_.pop_front();
  }
  lastArrivalNs_ = localNs;
}

void ClockMapper::observeTimesync(std::int64_t tc1Ns, std::int64_t ts1Ns, std::int64_t nowNs) {
  const std::int64_t rtt = nowNs - ts1Ns;
  if (rtt < 0 || tc1Ns <= 0) return;
  const bool restart =
      answers_.empty() || nowNs - answers_.back().localNs > config_.timesyncTimeoutNs;
  if (restart) timesyncSamples_ = 0;
  answers_.push_back({nowNs, ts1Ns - tc1Ns, nowNs - tc1Ns});
  while (answers_.front().localNs < nowNs - config_.arrivalWindowNs) answers_.pop_front();
  lowerNs_ = answers_.front().lowerNs;
  upperNs_ = answers_.front().upperNs;
  bestRttNs_ = upperNs_ - lowerNs_;
  for (const Answer& a : answers_) {
    lowerNs_ = std::max(lowerNs_, a.lowerNs);
    upperNs_ = std::min(upperNs_, a.upperNs);
    bestRttNs_ = std::min(bestRttNs_, a.upperNs - a.lowerNs);
  }
  ++timesyncSamples_;
}

void ClockMapper::observeSystemTime(std::uint64_t unixUs, std::uint32_t bootMs) {
  // 0: an autopilot without GPS time yet. Outside 2000-2100: not a time at all (and
  // its microseconds times 1000 would overflow).
  constexpr std::uint64_t kYear2000Us = 946'684'800'000'000ULL;
  constexpr std::uint64_t kYear2100Us = 4'102'444'800'000'000ULL;
  if (unixUs < kYear2000Us || unixUs >= kYear2100Us) return;
  utcMinusBootUs_ = static_cast<std::int64_t>(unixUs) - static_cast<std::int64_t>(bootMs) * 1000;
}

ClockMapper::Source ClockMapper::source() const {
  if (localIsUtc_ && utcMinusBootUs_) return Source::SystemTime;
  if (!answers_.empty() && lastArrivalNs_ - answers_.back().localNs <= config_.timesyncTimeoutNs &&
      timesyncAgreesWithArrivals()) {
    return Source::Timesync;
  }
  if (!arrivals_.empty()) return Source::Arrival;
  if (!answers_.empty()) return Source::Timesync;
  return Source::None;
}

bool ClockMapper::settled() const {
  switch (source()) {
    case Source::Timesync: return timesyncSamples_ >= 3;
    case Source::Arrival: return lastArrivalNs_ - firstArrivalNs_ >= kArrivalSettleNs;
    case Source::SystemTime: return true;
    case Source::None: break;
  }
  return false;
}

std::optional<std::int64_t> ClockMapper::offsetNs() const {
  switch (source()) {
    case Source::Timesync: {
      const auto [lower, upper] = *timesyncBounds();
      // Bounds that cross (the two clocks drifting apart over the window, by a few
      // parts per million): their middle is still the best estimate.
      return lower + (upper - lower) / 2;
    }
    case Source::Arrival: return arrivals_.front().offsetNs;
    case Source::SystemTime: return *utcMinusBootUs_ * 1000;
    case Source::None: break;
  }
  return std::nullopt;
}

std::optional<std::int64_t> ClockMapper::arrivalMinusSystemTimeNs() const {
  if (source() != Source::SystemTime || arrivals_.empty()) return std::nullopt;
  return arrivals_.front().offsetNs - *utcMinusBootUs_ * 1000;
}

std::optional<std::int64_t> ClockMapper::arrivalOffsetNs() const {
  if (arrivals_.empty()) return std::nullopt;
  return arrivals_.front().offsetNs;
}

std::optional<std::int64_t> ClockMapper::toLocalNs(std::int64_t bootNs) const {
  const auto offset = offsetNs();
  if (!offset) return std::nullopt;
  return bootNs + *offset;
}

std::optional<std::int64_t> ClockMapper::utcUs(std::int64_t localNs) const {
  const auto offset = offsetNs();
  if (!offset || !utcMinusBootUs_) return std::nullopt;
  const std::int64_t bootNs = localNs - *offset;
  // Round to the nearest microsecond, also for negative values.
  const std::int64_t bootUs = bootNs >= 0 ? (bootNs + 500) / 1000 : -((-bootNs + 500) / 1000);
  return bootUs + *utcMinusBootUs_;
}

bool ClockMapper::timesyncAgreesWithArrivals() const {
  // The bounds cross by a few parts per million of the window as the clocks drift.
  // When they cross by more, or TIMESYNC puts the offset further below the arrivals'
  // bound than any link's least delay over the window, tc1 is not on the boot clock
  // the messages are stamped with (an autopilot that answers from another clock), and
  // the arrivals, stamped with the very clock being mapped, are believed.
  // 20 ms, and 100 ppm of a window longer than 200 s (crystals drift 30-50 ppm: a
  // 600 s window's bounds cross by up to 30 ms).
  const std::int64_t crossingNs =
      std::max<std::int64_t>(20'000'000, config_.arrivalWindowNs / 10'000);
  constexpr std::int64_t kLeastDelayNs = 500'000'000;
  if (arrivals_.empty()) return true;
  const std::int64_t arrivalUpper = arrivals_.front().offsetNs;
  return lowerNs_ <= arrivalUpper + crossingNs && upperNs_ >= arrivalUpper - kLeastDelayNs;
}

std::optional<std::pair<std::int64_t, std::int64_t>> ClockMapper::timesyncBounds() const {
  if (answers_.empty()) return std::nullopt;
  std::int64_t upper = upperNs_;
  if (!arrivals_.empty()) upper = std::min(upper, arrivals_.front().offsetNs);
  return std::pair{lowerNs_, upper};
}

std::optional<std::int64_t> ClockMapper::uncertaintyNs() const {
  if (source() != Source::Timesync) return std::nullopt;
  const auto [lower, upper] = *timesyncBounds();
  return std::max<std::int64_t>(upper - lower, 0) / 2;
}

double ClockMapper::bestRoundTripMs() const {
  return bestRttNs_ < 0 ? NAN : static_cast<double>(bestRttNs_) / 1e6;
}

const char* toString(ClockMapper::Source source) {
  switch (source) {
    case ClockMapper::Source::Timesync: return "timesync";
    case ClockMapper::Source::Arrival: return "arrival";
    case ClockMapper::Source::SystemTime: return "system_time";
    case ClockMapper::Source::None: break;
  }
  return "none";
}

}  // namespace keyframed
