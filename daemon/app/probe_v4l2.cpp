#include "app/probe_v4l2.h"

#include <fcntl.h>
#include <linux/videodev2.h>
#include <sys/ioctl.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <string>
#include <vector>

#include "app/probe_util.h"
#include "capture/v4l2_source.h"

namespace keyframed {
namespace {

using probe::cpuSeconds;
using probe::emit;
using probe::jsonNumber;
using probe::jsonString;
using probe::parseDouble;
using probe::parseInt;
using probe::sampleMean;

constexpr const char* kUsage = R"(usage: keyframed probe-v4l2 [options]

Lists V4L2 devices, opens one, captures frames and prints JSON lines.

options:
  --list               list devices and exit
  --device PATH        device node (default: the first capture device)
  --frames N           frames to capture (default 30)
  --format FMT         NV12, YUV420, YUYV, MJPEG or GREY (default: best offered)
  --size WxH           frame size (default: the driver's current)
  --fps F              frame rate to ask for (default: the driver's current)
  --buffers N          mmap buffers (default 4)
  --timeout-ms MS      longest wait for one frame (default 2000)
  --reopen-wait S      when the device disappears, keep reopening it for up to
                       S seconds (default 0: a lost device is an error)
  --verbose            one line per frame
  --set-ctrl NAME=V    set one control of --device by its name (case ignored; e.g.
                       vivid's "percentage of dropped buffers=100" stalls it) and exit
exit status: 0 ok, 1 device error, 2 usage
)";

std::string deviceJson(const V4l2DeviceInfo& d) {
  std::string formats = "[";
  for (std::size_t i = 0; i < d.formats.size(); ++i) {
    if (i > 0) formats += ',';
    formats += jsonString(d.formats[i]);
  }
  formats += "]";
  return "{\"event\":\"device\",\"path\":" + jsonString(d.path) +
         ",\"driver\":" + jsonString(d.driver) + ",\"card\":" + jsonString(d.card) +
         ",\"bus\":" + jsonString(d.busInfo) + ",\"capture\":" + (d.capture ? "true" : "false") +
         ",\"streaming\":" + (d.streaming ? "true" : "false") + ",\"formats\":" + formats + "}";
}

int usage(const std::string& why) {
  std::fprintf(stderr, "keyframed probe-v4l2: %s\n%s", why.c_str(), kUsage);
  return 2;
}

// Sets the integer/boolean/menu control called `name` (case ignored) on `path`.
// Works while another process streams: controls are not owned by the streamer.
bool setControl(const std::string& path, const std::string& name, int value, std::string& error) {
  const int fd = ::open(path.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) {
    error = "cannot open " + path + ": " + std::strerror(errno);
    return false;
  }
  const auto lower = [](std::string s) {
    for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    return s;
  };
  v4l2_query_ext_ctrl q{};
  q.id = V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND;
  bool found = false;
  while (::ioctl(fd, VIDIOC_QUERY_EXT_CTRL, &q) == 0) {
    if (lower(std::string(q.name, strnlen(q.name, sizeof q.name))) == lower(name)) {
      found = true;
      break;
    }
    q.id |= V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND;
  }
  if (!found) {
    error = path + " has no control named '" + name + "'";
    ::close(fd);
    return false;
  }
  v4l2_ext_control c{};
  c.id = q.id;
  c.value = value;
  v4l2_ext_controls cs{};
  cs.which = V4L2_CTRL_WHICH_CUR_VAL;
  cs.count = 1;
  cs.controls = &c;
  const bool ok = ::ioctl(fd, VIDIOC_S_EXT_CTRLS, &cs) == 0;
  if (!ok) error = path + ": setting '" + name + "': " + std::strerror(errno);
  ::close(fd);
  return ok;
}

struct DeltaStats {
  std::vector<double> ms;  // inter-frame timestamp deltas within one stream segment
  bool monotonic = true;
};

}  // namespace

int probeV4l2Main(const std::vector<std::string>& args) {
  V4l2Options opt;
  opt.device.clear();
  int frames = 30;
  double reopenWait = 0.0;
  bool listOnly = false, verbose = false;
  std::string setCtrl;
  for (std::size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    const auto value = [&](std::string& out) {
      if (i + 1 >= args.size()) return false;
      out = args[++i];
      return true;
    };
    std::string v;
    if (a == "-h" || a == "--help") {
      std::fputs(kUsage, stdout);
      return 0;
    } else if (a == "--list") {
      listOnly = true;
    } else if (a == "--verbose") {
      verbose = true;
    } else if (a == "--device") {
      if (!value(opt.device) || opt.device.empty()) return usage("--device needs a path");
    } else if (a == "--frames") {
      if (!value(v) || !parseInt(v, 1, 10'000'000, frames)) return usage("--frames needs N >= 1");
    } else if (a == "--format") {
      if (!value(opt.format) || V4l2Source::parseFormat(opt.format) == 0) {
        return usage("--format must be NV12, YUV420, YUYV, MJPEG or GREY");
      }
    } else if (a == "--size") {
      const std::size_t x = value(v) ? v.find('x') : std::string::npos;
      if (x == std::string::npos || !parseInt(v.substr(0, x), 1, 16384, opt.width) ||
          !parseInt(v.substr(x + 1), 1, 16384, opt.height)) {
        return usage("--size needs WxH, e.g. 1280x720");
      }
    } else if (a == "--fps") {
      if (!value(v) || !parseDouble(v, 0.01, 1000.0, opt.fps))
        return usage("--fps needs 0.01..1000");
    } else if (a == "--buffers") {
      if (!value(v) || !parseInt(v, 2, 32, opt.bufferCount)) return usage("--buffers needs 2..32");
    } else if (a == "--timeout-ms") {
      if (!value(v) || !parseInt(v, 1, 600'000, opt.timeoutMs)) {
        return usage("--timeout-ms needs 1..600000");
      }
    } else if (a == "--set-ctrl") {
      if (!value(setCtrl) || setCtrl.find('=') == std::string::npos) {
        return usage("--set-ctrl needs NAME=VALUE");
      }
    } else if (a == "--reopen-wait") {
      if (!value(v) || !parseDouble(v, 0.0, 86400.0, reopenWait)) {
        return usage("--reopen-wait needs seconds >= 0");
      }
    } else {
      return usage("unknown option '" + a + "'");
    }
  }

  if (!setCtrl.empty()) {
    const std::size_t eq = setCtrl.rfind('=');
    const std::string name = setCtrl.substr(0, eq);
    int value = 0;
    if (opt.device.empty()) return usage("--set-ctrl needs --device");
    if (!parseInt(setCtrl.substr(eq + 1), -2'000'000'000, 2'000'000'000, value)) {
      return usage("--set-ctrl needs an integer value");
    }
    std::string error;
    if (!setControl(opt.device, name, value, error)) {
      emit("{\"event\":\"error\",\"reason\":" + jsonString(error) + "}");
      return 1;
    }
    emit("{\"event\":\"control\",\"device\":" + jsonString(opt.device) +
         ",\"name\":" + jsonString(name) + ",\"value\":" + std::to_string(value) + "}");
    return 0;
  }

  const std::vector<V4l2DeviceInfo> devices = V4l2Source::listDevices();
  for (const V4l2DeviceInfo& d : devices) emit(deviceJson(d));
  if (listOnly && devices.empty()) {
    emit("{\"event\":\"error\",\"reason\":\"no V4L2 device found under /dev\"}");
    return 1;
  }
  if (listOnly) return 0;
  if (opt.device.empty()) {
    for (const V4l2DeviceInfo& d : devices) {
      if (d.capture) {
        opt.device = d.path;
        break;
      }
    }
    if (opt.device.empty()) {
      emit("{\"event\":\"error\",\"reason\":\"no V4L2 capture device found under /dev\"}");
      return 1;
    }
  }
  opt.autoReopen = reopenWait > 0.0;
  opt.reopenIntervalMs = 200;

  std::string error;
  const double cpu0 = cpuSeconds();
  const auto wall0 = std::chrono::steady_clock::now();
  auto src = V4l2Source::open(opt, error);
  if (!src) {
    emit("{\"event\":\"error\",\"reason\":" + jsonString(error) + "}");
    return 1;
  }
  const SourceInfo& info = src->info();
  emit("{\"event\":\"open\",\"device\":" + jsonString(opt.device) + ",\"driver\":" +
       jsonString(src->device().driver) + ",\"format\":" + jsonString(src->fourcc()) +
       ",\"pixel_format\":" + jsonString(toString(src->pixelFormat())) +
       ",\"width\":" + std::to_string(info.width) + ",\"height\":" + std::to_string(info.height) +
       ",\"fps\":" + jsonNumber(info.fps) + "}");

  DeltaStats stats;
  std::int64_t captured = 0, firstTs = 0, lastTs = 0, segmentFrames = 0;
  double segmentSpanNs = 0.0;
  std::uint64_t errors = 0, lastReopens = 0;
  bool haveLast = false;
  double lastMean = 0.0;
  auto lostSince = std::chrono::steady_clock::time_point{};
  bool lost = false;
  int rc = 0;
  while (captured < frames) {
    Frame f;
    const ReadStatus s = src->next(f, error);
    if (s != ReadStatus::Frame) {
      ++errors;
      const bool nowLost = src->lost();
      if (!lost || !nowLost) {
        emit("{\"event\":\"error\",\"reason\":" + jsonString(error) + ",\"lost\":" +
             (nowLost ? "true" : "false") + ",\"frame\":" + std::to_string(captured) + "}");
      }
      if (!nowLost) {
        rc = 1;  // a timeout without the device going away: report and stop
        break;
      }
      if (!lost) lostSince = std::chrono::steady_clock::now();
      lost = true;
      const double waited =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - lostSince).count();
      if (!opt.autoReopen || waited > reopenWait) {
        emit("{\"event\":\"error\",\"reason\":" + jsonString("device did not come back: " + error) +
             ",\"lost\":true}");
        rc = 1;
        break;
      }
      continue;
    }
    if (src->reopenCount() != lastReopens) {
      lastReopens = src->reopenCount();
      const double waited =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - lostSince).count();
      emit("{\"event\":\"recovered\",\"reopens\":" + std::to_string(lastReopens) +
           ",\"after_s\":" + jsonNumber(waited) + ",\"frame\":" + std::to_string(captured) + "}");
      lost = false;
      haveLast = false;  // no delta across the gap
    }
    if (haveLast) {
      const double d = static_cast<double>(f.timestampNs - lastTs) / 1e6;
      if (f.timestampNs <= lastTs) stats.monotonic = false;
      stats.ms.push_back(d);
      segmentSpanNs += static_cast<double>(f.timestampNs - lastTs);
      ++segmentFrames;
    } else if (captured == 0) {
      firstTs = f.timestampNs;
    }
    lastMean = sampleMean(f);
    if (verbose) {
      emit("{\"event\":\"frame\",\"index\":" + std::to_string(f.index) +
           ",\"ts_ns\":" + std::to_string(f.timestampNs) + ",\"delta_ms\":" +
           (haveLast ? jsonNumber(static_cast<double>(f.timestampNs - lastTs) / 1e6) : "null") +
           ",\"mean\":" + jsonNumber(lastMean) + "}");
    }
    lastTs = f.timestampNs;
    haveLast = true;
    ++captured;
  }
  timespec now{};
  clock_gettime(CLOCK_MONOTONIC, &now);
  const std::int64_t nowNs = static_cast<std::int64_t>(now.tv_sec) * 1'000'000'000 + now.tv_nsec;
  const double wall =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - wall0).count();
  const double cpu = cpuSeconds() - cpu0;

  double mean = 0.0, sd = 0.0, mn = 0.0, mx = 0.0, median = 0.0;
  if (!stats.ms.empty()) {
    for (double d : stats.ms) mean += d;
    mean /= static_cast<double>(stats.ms.size());
    for (double d : stats.ms) sd += (d - mean) * (d - mean);
    sd = std::sqrt(sd / static_cast<double>(stats.ms.size()));
    std::vector<double> sorted = stats.ms;
    std::sort(sorted.begin(), sorted.end());
    mn = sorted.front();
    mx = sorted.back();
    median = sorted[sorted.size() / 2];
  }
  const double measuredFps =
      segmentSpanNs > 0.0 ? static_cast<double>(segmentFrames) * 1e9 / segmentSpanNs : 0.0;
  emit("{\"event\":\"summary\",\"device\":" + jsonString(opt.device) +
       ",\"format\":" + jsonString(src->fourcc()) + ",\"width\":" + std::to_string(info.width) +
       ",\"height\":" + std::to_string(info.height) + ",\"fps\":" + jsonNumber(info.fps) +
       ",\"frames\":" + std::to_string(captured) + ",\"fps_measured\":" + jsonNumber(measuredFps) +
       ",\"delta_ms_mean\":" + jsonNumber(mean) + ",\"delta_ms_median\":" + jsonNumber(median) +
       ",\"delta_ms_std\":" + jsonNumber(sd) + ",\"delta_ms_min\":" + jsonNumber(mn) +
       ",\"delta_ms_max\":" + jsonNumber(mx) +
       ",\"monotonic\":" + (stats.monotonic ? "true" : "false") +
       ",\"driver_timestamps\":" + (src->driverTimestamps() ? "true" : "false") +
       ",\"timestamps\":" + jsonString(describe(src->timestampOrigin())) +
       ",\"first_ts_ns\":" + std::to_string(firstTs) + ",\"last_ts_ns\":" + std::to_string(lastTs) +
       ",\"monotonic_now_ns\":" + std::to_string(nowNs) +
       ",\"sequence_gaps\":" + std::to_string(src->sequenceGaps()) + ",\"corrupt\":" +
       std::to_string(src->corruptFrames()) + ",\"errors\":" + std::to_string(errors) +
       ",\"reopens\":" + std::to_string(src->reopenCount()) + ",\"mean\":" + jsonNumber(lastMean) +
       ",\"wall_s\":" + jsonNumber(wall) + ",\"cpu_s\":" + jsonNumber(cpu) +
       ",\"cpu_percent\":" + jsonNumber(wall > 0 ? 100.0 * cpu / wall : 0.0) +
       ",\"ok\":" + (rc == 0 ? "true" : "false") + "}");
  return rc;
}

}  // namespace keyframed
