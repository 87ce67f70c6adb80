#include "app/settings.h"

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>

namespace keyframed {
namespace {

std::string number(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.10g", v);
  return buf;
}

bool parseId(std::string_view text, int& out) {
  int v = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
  if (ec != std::errc() || end != text.data() + text.size() || text.empty()) return false;
  if (!limits::kMavlinkId.contains(v)) return false;
  out = v;
  return true;
}

}  // namespace

bool parseDouble(const std::string& s, double& out) {
  if (s.empty()) return false;
  char* end = nullptr;
  errno = 0;
  out = std::strtod(s.c_str(), &end);
  return errno == 0 && end == s.c_str() + s.size() && std::isfinite(out);
}

void relaxDependentDefaults(SelectorConfig& config, bool minTracksSet, bool warmupSet) {
  OverlapConfig& o = config.overlap;
  // Lowered with max_tracks, but never under min_inliers (as far as max_tracks allows):
  // tracks are replenished below min_tracks, and fewer than min_inliers lose the track.
  if (!minTracksSet && o.minTracks > o.maxTracks) {
    o.minTracks = std::max({8, o.maxTracks * 2 / 5, std::min(o.minInliers, o.maxTracks)});
  }
  SharpnessConfig& b = config.blur;
  if (!warmupSet && b.warmup > b.window) b.warmup = b.window;
}

std::string rangeError(SettingRange<double> range, double value) {
  return "must be between " + number(range.lo) + " and " + number(range.hi) + " (got " +
         number(value) + ")";
}

std::string rangeError(SettingRange<std::int64_t> range, std::int64_t value) {
  return "must be between " + std::to_string(range.lo) + " and " + std::to_string(range.hi) +
         " (got " + std::to_string(value) + ")";
}

bool parseOverlapMode(std::string_view text, OverlapMode& mode) {
  if (text == "geometric")
    mode = OverlapMode::Geometric;
  else if (text == "paper")
    mode = OverlapMode::Paper;
  else
    return false;
  return true;
}

const char* blurModeName(BlurMode mode) {
  return mode == BlurMode::Absolute ? "absolute" : "adaptive";
}

bool parseBlurMode(std::string_view text, BlurMode& mode) {
  if (text == "adaptive")
    mode = BlurMode::Adaptive;
  else if (text == "absolute")
    mode = BlurMode::Absolute;
  else
    return false;
  return true;
}

std::string parseAutopilot(std::string_view text, int& system, int& component) {
  const auto colon = text.find(':');
  int sys = 0;
  int comp = 0;
  if (!parseId(text.substr(0, colon), sys) ||
      (colon != std::string_view::npos && !parseId(text.substr(colon + 1), comp)))
    return "expected SYS[:COMP] with ids 1..255";
  system = sys;
  component = comp;
  return {};
}

bool parseUtcTime(const std::string& text, std::int64_t& unixNs) {
  double seconds = 0;
  if (parseDouble(text, seconds)) {
    if (seconds < 0 || seconds > 4.1e9) return false;
    unixNs = std::llround(seconds * 1e9);
    return true;
  }
  std::tm tm{};
  int consumed = 0;
  if (std::sscanf(text.c_str(), "%4d-%2d-%2dT%2d:%2d:%2d%n", &tm.tm_year, &tm.tm_mon, &tm.tm_mday,
                  &tm.tm_hour, &tm.tm_min, &tm.tm_sec, &consumed) != 6) {
    return false;
  }
  // 1970-2099, as the numeric form (nanoseconds past 2262 would not fit an int64).
  if (tm.tm_year < 1970 || tm.tm_year > 2099 || tm.tm_mon < 1 || tm.tm_mon > 12 || tm.tm_mday < 1 ||
      tm.tm_mday > 31 || tm.tm_hour < 0 || tm.tm_hour > 23 || tm.tm_min < 0 || tm.tm_min > 59 ||
      tm.tm_sec < 0 || tm.tm_sec > 60) {
    return false;
  }
  // A day the month has (timegm would roll 2026-02-30 over into March).
  const int y = tm.tm_year;
  const bool leap = (y % 4 == 0 && y % 100 != 0) || y % 400 == 0;
  constexpr int kDays[] = {31, 28, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31};
  if (tm.tm_mday > kDays[tm.tm_mon - 1] + (tm.tm_mon == 2 && leap ? 1 : 0)) return false;
  std::string rest = text.substr(static_cast<std::size_t>(consumed));
  std::int64_t fracNs = 0;
  if (!rest.empty() && rest[0] == '.') {
    std::size_t i = 1;
    std::int64_t scale = 100'000'000;
    while (i < rest.size() && rest[i] >= '0' && rest[i] <= '9') {
      fracNs += (rest[i] - '0') * scale;
      scale /= 10;
      ++i;
    }
    if (i == 1) return false;
    rest = rest.substr(i);
  }
  if (rest != "Z" && rest != "+00:00" && !rest.empty()) return false;  // UTC only
  tm.tm_year -= 1900;
  tm.tm_mon -= 1;
  const std::time_t t = timegm(&tm);
  unixNs = static_cast<std::int64_t>(t) * 1'000'000'000 + fracNs;
  return true;
}

std::string tooLargeToAnalyse(int w, int h) {
  constexpr long kMaxSide = 16384;
  constexpr long kMaxPixels = 64L * 1024 * 1024;
  if (w <= kMaxSide && h <= kMaxSide && static_cast<long>(w) * h <= kMaxPixels) return {};
  return "frames of " + std::to_string(w) + "x" + std::to_string(h) +
         " are too large to analyse (at most 16384 pixels a side and 64 megapixels)";
}

std::string vehicleNameError(const std::string& s) {
  const bool ok = !s.empty() && s.size() <= 64 && s != "." && s != ".." &&
                  std::all_of(s.begin(), s.end(), [](char ch) {
                    return (ch >= 'a' && ch <= 'z') || (ch >= 'A' && ch <= 'Z') ||
                           (ch >= '0' && ch <= '9') || ch == '-' || ch == '_' || ch == '.';
                  });
  return ok ? "" : "may hold only letters, digits, '-', '_' and '.', 1 to 64 of them";
}

std::string tooSmallToAnalyse(int w, int h, int analysisWidth) {
  constexpr int kMinSide = 32;
  const int aw = analysisWidth > 0 ? std::min(analysisWidth, w) : w;
  const long ah = w > 0 ? std::lround(static_cast<double>(h) * aw / w) : 0;
  if (w <= 0 || (aw >= kMinSide && ah >= kMinSide)) return {};
  return "frames of " + std::to_string(w) + "x" + std::to_string(h) +
         " are too small to analyse (at least " + std::to_string(kMinSide) +
         " pixels each way at the analysis width)";
}

}  // namespace keyframed
