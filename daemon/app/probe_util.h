#pragma once
// Helpers shared by the capture probes (probe-v4l2, probe-libcamera): JSON lines on
// stdout, argument parsing, a pixel sample. Header-only: the static V4L2 probe and the
// libcamera probe built against another libcamera link nothing else.

#include <sys/resource.h>

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "core/frame.h"

namespace keyframed::probe {

inline std::string jsonString(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    switch (c) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\t': out += "\\t"; break;
      default:
        if (static_cast<unsigned char>(c) < 0x20) {
          char buf[8];
          std::snprintf(buf, sizeof(buf), "\\u%04x", static_cast<unsigned>(c));
          out += buf;
        } else {
          out += c;
        }
    }
  }
  return out + "\"";
}

inline std::string jsonNumber(double v) {
  if (!std::isfinite(v)) return "null";
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%.6g", v);
  return buf;
}

inline void emit(const std::string& line) {
  std::fputs(line.c_str(), stdout);
  std::fputc('\n', stdout);
  std::fflush(stdout);  // the VM test reads these off a serial console as they come
}

inline double cpuSeconds() {
  rusage ru{};
  getrusage(RUSAGE_SELF, &ru);
  const auto tv = [](const timeval& t) {
    return static_cast<double>(t.tv_sec) + static_cast<double>(t.tv_usec) * 1e-6;
  };
  return tv(ru.ru_utime) + tv(ru.ru_stime);
}

// Mean of a sparse sample of the first plane (or of BGR bytes): shows the
// pixels are real without costing much.
inline double sampleMean(const Frame& f) {
  if (f.data == nullptr || f.width <= 0 || f.height <= 0) return 0.0;
  const int bpp = f.format == PixelFormat::BGR24 ? 3 : f.format == PixelFormat::YUYV ? 2 : 1;
  double sum = 0.0;
  int n = 0;
  for (int y = 0; y < f.height; y += std::max(1, f.height / 16)) {
    const std::uint8_t* row = f.data + static_cast<std::ptrdiff_t>(y) * f.stride;
    for (int x = 0; x < f.width; x += std::max(1, f.width / 16)) {
      sum += row[x * bpp];
      ++n;
    }
  }
  return n > 0 ? sum / n : 0.0;
}

inline bool parseInt(const std::string& s, int lo, int hi, int& out) {
  char* end = nullptr;
  const long v = std::strtol(s.c_str(), &end, 10);
  if (s.empty() || *end != '\0' || v < lo || v > hi) return false;
  out = static_cast<int>(v);
  return true;
}

inline bool parseDouble(const std::string& s, double lo, double hi, double& out) {
  char* end = nullptr;
  const double v = std::strtod(s.c_str(), &end);
  if (s.empty() || *end != '\0' || !(v >= lo && v <= hi)) return false;
  out = v;
  return true;
}

}  // namespace keyframed::probe
