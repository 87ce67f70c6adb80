#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

namespace keyframed {

// Says a recurring problem without flooding the log: the first line at once, a
// different kind of problem after at least `newKindGapNs`, the same kind again
// after `repeatGapNs`; the lines in between are counted, not written. Not
// thread-safe (one per loop). Times on any monotonic clock.
class LogThrottle {
 public:
  explicit LogThrottle(std::int64_t repeatGapNs = 10'000'000'000, std::int64_t newKindGapNs = 0)
      : repeatGapNs_(repeatGapNs), newKindGapNs_(newKindGapNs) {}

  // The number of lines held back since the last one written when a line about
  // `kind` is to be written now; nothing when it is held back.
  std::optional<std::uint64_t> pass(std::string_view kind, std::int64_t nowNs) {
    const std::int64_t since = nowNs - lastNs_;
    const bool write =
        !logged_ || (kind != lastKind_ && since >= newKindGapNs_) || since >= repeatGapNs_;
    if (!write) {
      ++heldBack_;
      return std::nullopt;
    }
    const std::uint64_t held = heldBack_;
    logged_ = true;
    lastNs_ = nowNs;
    lastKind_ = kind;
    heldBack_ = 0;
    return held;
  }

  // Lines held back since the last one written.
  [[nodiscard]] std::uint64_t heldBack() const { return heldBack_; }

  // The problem is over: the next line is written at once.
  void reset() {
    logged_ = false;
    heldBack_ = 0;
    lastKind_.clear();
  }

 private:
  std::int64_t repeatGapNs_;
  std::int64_t newKindGapNs_;
  bool logged_ = false;
  std::int64_t lastNs_ = 0;
  std::uint64_t heldBack_ = 0;
  std::string lastKind_;
};

}  // namespace keyframed
