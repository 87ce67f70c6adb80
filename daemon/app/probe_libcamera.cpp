#include "app/probe_libcamera.h"

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <set>
#include <string>
#include <vector>

#include "app/probe_util.h"
#include "capture/libcamera_source.h"

namespace keyframed {
namespace {

using probe::emit;
using probe::jsonNumber;
using probe::jsonString;

constexpr const char* kUsage = R"(usage: keyframed probe-libcamera [options]

Lists libcamera's cameras, opens one, captures frames and prints JSON lines.

options:
  --list               list cameras and exit
  --camera ID          camera id (default: the first)
  --frames N           frames to capture (default 30)
  --format FMT         NV12, YUV420 or YUYV (default: the first offered, in that order)
  --size WxH           frame size (default: the pipeline's for the role)
  --fps F              fixed frame rate (default: the camera's)
  --buffers N          buffers (default 4)
  --timeout-ms MS      longest wait for one frame (default 2000)
  --viewfinder         the viewfinder stream role instead of video recording
  --verbose            one line per frame
exit status: 0 ok, 1 camera error, 2 usage
)";

int usage(const std::string& why) {
  std::fprintf(stderr, "keyframed probe-libcamera: %s\n%s", why.c_str(), kUsage);
  return 2;
}

int fail(const std::string& message) {
  emit("{\"event\":\"error\",\"message\":" + jsonString(message) + "}");
  std::fprintf(stderr, "keyframed probe-libcamera: %s\n", message.c_str());
  return 1;
}

}  // namespace

int probeLibcameraMain(const std::vector<std::string>& args) {
  LibcameraOptions opt;
  int frames = 30;
  bool list = false, verbose = false;
  for (std::size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    const auto value = [&](std::string& out) {
      if (i + 1 >= args.size()) return false;
      out = args[++i];
      return true;
    };
    std::string v;
    if (a == "--help" || a == "-h") {
      std::fputs(kUsage, stdout);
      return 0;
    } else if (a == "--list") {
      list = true;
    } else if (a == "--verbose") {
      verbose = true;
    } else if (a == "--viewfinder") {
      opt.videoRole = false;
    } else if (a == "--camera") {
      if (!value(opt.cameraId)) return usage("--camera needs an id");
    } else if (a == "--format") {
      if (!value(v) || (v != "NV12" && v != "YUV420" && v != "YUYV"))
        return usage("--format takes NV12, YUV420 or YUYV");
      opt.format = v;
    } else if (a == "--frames") {
      if (!value(v) || !probe::parseInt(v, 1, 1'000'000, frames))
        return usage("--frames takes 1..1000000");
    } else if (a == "--size") {
      const std::size_t x = value(v) ? v.find('x') : std::string::npos;
      if (x == std::string::npos || !probe::parseInt(v.substr(0, x), 16, 16384, opt.width) ||
          !probe::parseInt(v.substr(x + 1), 16, 16384, opt.height))
        return usage("--size takes WxH, e.g. 1280x720");
    } else if (a == "--fps") {
      if (!value(v) || !probe::parseDouble(v, 0.1, 1000.0, opt.fps))
        return usage("--fps takes 0.1..1000");
    } else if (a == "--buffers") {
      if (!value(v) || !probe::parseInt(v, 2, 32, opt.bufferCount))
        return usage("--buffers takes 2..32");
    } else if (a == "--timeout-ms") {
      if (!value(v) || !probe::parseInt(v, 1, 600'000, opt.timeoutMs))
        return usage("--timeout-ms takes 1..600000");
    } else {
      return usage("unknown option " + a);
    }
  }

  std::string error;
  const std::vector<std::string> ids = LibcameraSource::listCameras(error);
  for (const std::string& id : ids) emit("{\"event\":\"camera\",\"id\":" + jsonString(id) + "}");
  if (!error.empty()) return fail(error);
  if (list && ids.empty()) return fail("no camera found");
  if (list) return 0;

  auto source = LibcameraSource::open(opt, error);
  if (!source) return fail(error);
  const SourceInfo& info = source->info();
  const auto wallStart = std::chrono::steady_clock::now();
  const double cpuStart = probe::cpuSeconds();
  Frame f;
  std::vector<std::int64_t> times;
  std::set<int> means;  // distinct rounded means: the pixels change from frame to frame
  bool monotonic = true, indexed = true;
  std::string stream;
  for (int i = 0; i < frames; ++i) {
    if (source->next(f, error) != ReadStatus::Frame)
      return fail("frame " + std::to_string(i) + ": " + error);
    if (i == 0) {
      // The first frame's luma along its middle row, at 32 evenly spaced columns:
      // enough to recognise a test pattern (e.g. colour bars) and its layout.
      std::string profile = "[";
      const std::uint8_t* row = f.data + static_cast<std::ptrdiff_t>(f.height / 2) * f.stride;
      const int step = f.format == PixelFormat::YUYV ? 2 : 1;
      for (int k = 0; k < 32; ++k) {
        const int x = (2 * k + 1) * f.width / 64;
        if (k > 0) profile += ',';
        profile += std::to_string(row[x * step]);
      }
      emit("{\"event\":\"stream\",\"camera\":" + jsonString(source->cameraId()) + ",\"format\":" +
           jsonString(toString(f.format)) + ",\"width\":" + std::to_string(f.width) +
           ",\"height\":" + std::to_string(f.height) + ",\"stride\":" + std::to_string(f.stride) +
           ",\"info_fps\":" + jsonNumber(info.fps) + ",\"luma_row\":" + profile + "]}");
    }
    const double mean = probe::sampleMean(f);
    means.insert(static_cast<int>(mean * 10));
    if (!times.empty() && f.timestampNs <= times.back()) monotonic = false;
    if (f.index != i) indexed = false;
    times.push_back(f.timestampNs);
    if (verbose) {
      emit("{\"event\":\"frame\",\"index\":" + std::to_string(f.index) +
           ",\"t_ns\":" + std::to_string(f.timestampNs) + ",\"mean\":" + jsonNumber(mean) + "}");
    }
  }
  const double wall =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - wallStart).count();
  std::vector<double> intervals;
  for (std::size_t i = 1; i < times.size(); ++i)
    intervals.push_back(static_cast<double>(times[i] - times[i - 1]) / 1e6);
  std::sort(intervals.begin(), intervals.end());
  const double median = intervals.empty() ? 0.0 : intervals[intervals.size() / 2];
  emit("{\"event\":\"summary\",\"frames\":" + std::to_string(times.size()) + ",\"monotonic\":" +
       (monotonic ? "true" : "false") + ",\"indexed\":" + (indexed ? "true" : "false") +
       ",\"sensor_timestamps\":" + (source->sensorTimestamps() ? "true" : "false") +
       ",\"failed_frames\":" + std::to_string(source->failedFrames()) + ",\"sequence_gaps\":" +
       std::to_string(source->sequenceGaps()) + ",\"interval_ms_median\":" + jsonNumber(median) +
       ",\"distinct_means\":" + std::to_string(means.size()) + ",\"wall_s\":" + jsonNumber(wall) +
       ",\"cpu_s\":" + jsonNumber(probe::cpuSeconds() - cpuStart) + "}");
  source.reset();  // stop and release the camera before the process ends
  emit("{\"event\":\"closed\"}");
  return 0;
}

}  // namespace keyframed
