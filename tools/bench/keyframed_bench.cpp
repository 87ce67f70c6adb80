// Per-stage cost of the selector on real decoded frames, one thread.
//
//   keyframed-bench VIDEO [--frames N] [--width W] [--gray] [--geometric-only]
//                   [--max-tracks N] [--lk-window N] [--fast-threshold N] [--analysis-width W]
//                   [--calibration FILE]
//
// Decodes N frames into memory first (decoding is not timed), then runs the
// geometric and the paper mode over them and prints median and p99 per stage,
// heap allocations per frame in steady state, CPU time and peak RSS. With
// --calibration, the geometric mode measures overlap through that lens (a fisheye, or
// a pinhole with distortion), as `keyframed select --calibration` does.
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>

#include "alloc_counter.h"
#include "core/frame.h"
#include "core/selector.h"
#include "tagging/camera_model.h"
#include "tagging/camera_mount.h"
#include "tagging/exif_writer.h"
#include "tagging/jpeg_encoder.h"
#include "telemetry/pose_store.h"

using namespace keyframed;

namespace {

// The selector reads this clock at each stage boundary (luma, blur, resize,
// overlap); recording the allocation count there too attributes allocations to
// stages.
class SteadyClock final : public Clock {
 public:
  [[nodiscard]] std::int64_t nowNs() const override {
    marks_[next_++ % 5] = bench::allocations();
    return std::chrono::duration_cast<std::chrono::nanoseconds>(
               std::chrono::steady_clock::now().time_since_epoch())
        .count();
  }
  void beginFrame() const { next_ = 0; }
  [[nodiscard]] std::uint64_t stageAllocs(int stage) const {
    return marks_[stage + 1] - marks_[stage];
  }

 private:
  mutable std::uint64_t marks_[5] = {};
  mutable int next_ = 0;
};

struct Stat {
  double median = 0;
  double p99 = 0;
};

Stat stat(std::vector<double> v) {
  if (v.empty()) return {};
  std::sort(v.begin(), v.end());
  const auto at = [&](double q) {
    return v[std::min(v.size() - 1,
                      static_cast<std::size_t>(q * static_cast<double>(v.size() - 1) + 0.5))];
  };
  return {at(0.5), at(0.99)};
}

double cpuSeconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_utime.tv_sec + u.ru_stime.tv_sec) +
         static_cast<double>(u.ru_utime.tv_usec + u.ru_stime.tv_usec) / 1e6;
}

long maxRssKb() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_maxrss;
}

struct ModeResult {
  std::string name;
  Stat luma, blur, resize, overlap, total;
  double allocsPerFrame = 0;
  double stageAllocs[4] = {};  // luma, blur, resize, overlap
  double fps = 0;
  double cpuPerFrameMs = 0;
  long kept = 0;
};

ModeResult run(const std::string& name, const SelectorConfig& cfg,
               const std::vector<cv::Mat>& frames) {
  SteadyClock clock;
  KeyframeSelector sel(cfg, &clock);
  std::vector<double> luma, blur, resize, overlap, total;
  // Reserved: the timing vectors must not show up in the allocation count.
  for (auto* v : {&luma, &blur, &resize, &overlap, &total}) v->reserve(frames.size());
  const std::size_t warm = std::min<std::size_t>(30, frames.size() / 4);
  std::uint64_t allocStart = 0;
  ModeResult r;
  r.name = name;
  const double cpu0 = cpuSeconds();
  const auto t0 = std::chrono::steady_clock::now();
  for (std::size_t i = 0; i < frames.size(); ++i) {
    if (i == warm) {
      allocStart = bench::allocations();
      bench::setCounting(true);
    }
    const auto index = static_cast<std::int64_t>(i);
    const Frame frame = frames[i].channels() == 1
                            ? Frame::ofGray(frames[i], index, index * 33'333'333)
                            : Frame::ofBgr(frames[i], index, index * 33'333'333);
    clock.beginFrame();
    const Decision d = sel.process(frame);
    if (i >= warm)
      for (int st = 0; st < 4; ++st)
        r.stageAllocs[st] += static_cast<double>(clock.stageAllocs(st));
    if (d.kept) ++r.kept;
    if (d.promotedIndex >= 0) ++r.kept;
    if (i >= warm) {
      luma.push_back(static_cast<double>(d.times.lumaNs) / 1e6);
      blur.push_back(static_cast<double>(d.times.blurNs) / 1e6);
      resize.push_back(static_cast<double>(d.times.resizeNs) / 1e6);
      overlap.push_back(static_cast<double>(d.times.overlapNs) / 1e6);
      total.push_back(static_cast<double>(d.times.totalNs) / 1e6);
    }
  }
  bench::setCounting(false);
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const double cpu = cpuSeconds() - cpu0;
  const double n = static_cast<double>(frames.size() - warm);
  r.allocsPerFrame = static_cast<double>(bench::allocations() - allocStart) / n;
  for (double& a : r.stageAllocs) a /= n;
  r.luma = stat(luma);
  r.blur = stat(blur);
  r.resize = stat(resize);
  r.overlap = stat(overlap);
  r.total = stat(total);
  r.fps = static_cast<double>(frames.size()) / wall;
  r.cpuPerFrameMs = cpu / static_cast<double>(frames.size()) * 1e3;
  return r;
}

}  // namespace

// What one keyframe costs after the decision: JPEG encoding (from BGR as a file
// gives it, and from the Y plane + chroma as a YUV camera gives it) and the
// EXIF/XMP tags, on the first frames of the video. Median / p99 ms.
void benchTagging(const std::vector<cv::Mat>& frames) {
  const int n = std::min<int>(40, static_cast<int>(frames.size()));
  CameraModel cam;
  cam.width = frames[0].cols;
  cam.height = frames[0].rows;
  cam.fx = cam.fy = 0.9 * cam.width;
  cam.cx = cam.width / 2.0 - 0.5;
  cam.cy = cam.height / 2.0 - 0.5;
  cam.distortion = {-0.1, 0.02, 0.001, -0.001, 0.0};
  cam.sensorWidthMm = 6.17;
  cam.sensorHeightMm = 6.17 * cam.height / cam.width;
  cam.focalLengthMm = cam.fx * cam.sensorWidthMm / cam.width;
  // The same camera with a fisheye lens: its tags carry Pix4D's model, fitted per call.
  CameraModel fisheye = cam;
  fisheye.lens = CameraModel::Lens::Fisheye;
  fisheye.fx = fisheye.fy = 0.3 * cam.width;
  fisheye.distortion = {0.032, -0.0081, 0.0017, -0.0003};
  TagSet tags;
  tags.camera = &cam;
  tags.position = GeoPosition{51.889, 0.94, 70.0, 50.0};
  tags.gps.fixType = 3;
  tags.gps.hdop = 0.8;
  tags.cameraToNed = quaternionFromEuler(0.01, -0.02, 1.2);
  tags.utcUs = 1'780'308'000'000'000;
  JpegEncoder encoder;
  std::vector<std::uint8_t> jpeg;
  std::string error;
  std::vector<double> bgrMs, yuvMs, tagMs, fisheyeMs;
  std::vector<std::uint8_t> untagged;
  std::size_t bytes = 0;
  cv::Mat bgr, yuv;
  for (int i = 0; i < n; ++i) {
    if (frames[i].channels() == 1) {
      cv::cvtColor(frames[i], bgr, cv::COLOR_GRAY2BGR);
    } else {
      bgr = frames[i];
    }
    cv::cvtColor(bgr, yuv, cv::COLOR_BGR2YUV_I420);
    const Frame yuvFrame{PixelFormat::YUV420, yuv.data, bgr.cols, bgr.rows, bgr.cols, 0, i};
    auto t0 = std::chrono::steady_clock::now();
    if (!encoder.encode(yuvFrame, 92, jpeg, error)) break;
    auto t1 = std::chrono::steady_clock::now();
    if (!encoder.encode(bgr, 92, jpeg, error)) break;
    auto t2 = std::chrono::steady_clock::now();
    untagged = jpeg;
    const auto t2b = std::chrono::steady_clock::now();  // the copy not counted
    if (!writeTags(jpeg, tags, error)) break;
    auto t3 = std::chrono::steady_clock::now();
    TagSet fisheyeTags = tags;
    fisheyeTags.camera = &fisheye;
    const auto t4 = std::chrono::steady_clock::now();
    if (!writeTags(untagged, fisheyeTags, error)) break;
    fisheyeMs.push_back(
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t4).count());
    yuvMs.push_back(std::chrono::duration<double, std::milli>(t1 - t0).count());
    bgrMs.push_back(std::chrono::duration<double, std::milli>(t2 - t1).count());
    tagMs.push_back(std::chrono::duration<double, std::milli>(t3 - t2b).count());
    bytes += jpeg.size();
  }
  if (!error.empty() || tagMs.empty()) {
    std::fprintf(stderr, "keyframed-bench: tagging: %s\n", error.c_str());
    return;
  }
  auto pct = [](std::vector<double> v, double q) {
    std::sort(v.begin(), v.end());
    return v[static_cast<std::size_t>(q * static_cast<double>(v.size() - 1))];
  };
  std::printf("\nper keyframe, ms (median / p99), %zu keyframes of %dx%d, JPEG quality 92\n",
              tagMs.size(), frames[0].cols, frames[0].rows);
  std::printf("  %-28s%.2f / %.2f\n", "JPEG from YUV420 (camera)", pct(yuvMs, 0.5),
              pct(yuvMs, 0.99));
  std::printf("  %-28s%.2f / %.2f\n", "JPEG from BGR (file)", pct(bgrMs, 0.5), pct(bgrMs, 0.99));
  std::printf("  %-28s%.2f / %.2f\n", "EXIF + XMP tags (exiv2)", pct(tagMs, 0.5), pct(tagMs, 0.99));
  std::printf("  %-28s%.2f / %.2f\n", "the same, a fisheye lens", pct(fisheyeMs, 0.5),
              pct(fisheyeMs, 0.99));
  std::printf("  %-28s%.0f KB\n", "mean JPEG size",
              static_cast<double>(bytes) / static_cast<double>(tagMs.size()) / 1024.0);
}

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr, "usage: keyframed-bench VIDEO [--frames N] [--width W]\n");
    return 2;
  }
  const std::string video = argv[1];
  int maxFrames = 300;
  int width = 1920;
  bool grayInput = false;  // feed the Y plane, as a YUV camera would (no conversion)
  bool geometricOnly = false;
  SelectorConfig geometric;
  for (int i = 2; i < argc; ++i) {
    const std::string a = argv[i];
    const bool hasValue = i + 1 < argc;
    if (a == "--gray") {
      grayInput = true;
    } else if (a == "--geometric-only") {
      geometricOnly = true;
    } else if (a == "--frames" && hasValue) {
      maxFrames = std::atoi(argv[++i]);
    } else if (a == "--width" && hasValue) {
      width = std::atoi(argv[++i]);
    } else if (a == "--max-tracks" && hasValue) {
      geometric.overlap.maxTracks = std::atoi(argv[++i]);
      // As the daemon lowers it: never under min_inliers (see relaxDependentDefaults).
      geometric.overlap.minTracks =
          std::max({8, geometric.overlap.maxTracks * 2 / 5,
                    std::min(geometric.overlap.minInliers, geometric.overlap.maxTracks)});
    } else if (a == "--lk-window" && hasValue) {
      geometric.overlap.lkWindow = std::atoi(argv[++i]);
    } else if (a == "--fast-threshold" && hasValue) {
      geometric.overlap.fastThreshold = std::atoi(argv[++i]);
    } else if (a == "--analysis-width" && hasValue) {
      geometric.analysisWidth = std::atoi(argv[++i]);
    } else if (a == "--calibration" && hasValue) {
      CameraModel camera;
      std::string error;
      if (!loadCameraModel(argv[++i], camera, error)) {
        std::fprintf(stderr, "keyframed-bench: %s\n", error.c_str());
        return 2;
      }
      geometric.overlap.lens = camera.lensModel();
    } else {
      std::fprintf(stderr, "keyframed-bench: unknown option %s\n", a.c_str());
      return 2;
    }
  }
  cv::setNumThreads(1);  // one core, as on the companion's analysis thread
  cv::VideoCapture cap(video, cv::CAP_FFMPEG);
  if (!cap.isOpened()) {
    std::fprintf(stderr, "keyframed-bench: cannot open %s\n", video.c_str());
    return 3;
  }
  std::vector<cv::Mat> frames;
  cv::Mat f;
  while (static_cast<int>(frames.size()) < maxFrames && cap.read(f)) {
    cv::Mat g;
    if (f.cols != width) {
      cv::resize(f, g, cv::Size(width, f.rows * width / f.cols), 0, 0, cv::INTER_LINEAR);
    } else {
      g = f.clone();
    }
    if (grayInput) cv::cvtColor(g, g, cv::COLOR_BGR2GRAY);
    frames.push_back(g);
  }
  if (frames.size() < 40) {
    std::fprintf(stderr, "keyframed-bench: need at least 40 frames, got %zu\n", frames.size());
    return 3;
  }
  std::printf(
      "keyframed-bench: %zu frames of %dx%d %s from %s, one thread (cv::setNumThreads(1))\n",
      frames.size(), frames[0].cols, frames[0].rows,
      grayInput ? "grey (camera Y plane)" : "BGR (decoded file)", video.c_str());

  if (std::string e = geometric.validate(); !e.empty()) {
    std::fprintf(stderr, "keyframed-bench: %s\n", e.c_str());
    return 2;
  }
  SelectorConfig paper;
  paper.overlap.mode = OverlapMode::Paper;
  SelectorConfig paperFull = paper;
  paperFull.analysisWidth = 0;
  std::vector<ModeResult> results = {run("geometric", geometric, frames)};
  if (!geometricOnly) {
    results.push_back(run("paper@640", paper, frames));
    results.push_back(run("paper@full", paperFull, frames));
  }

  std::printf("\nper frame, ms (median / p99)   ");
  for (const auto& r : results) std::printf("%-22s", r.name.c_str());
  std::printf("paper's figures (i7)\n");
  auto row = [&](const char* label, Stat ModeResult::*m, const char* paperFig) {
    std::printf("  %-28s", label);
    for (const auto& r : results) {
      const Stat& s = r.*m;
      char cell[32];
      std::snprintf(cell, sizeof cell, "%.2f / %.2f", s.median, s.p99);
      std::printf("%-22s", cell);
    }
    std::printf("%s\n", paperFig);
  };
  row("grey (luma)", &ModeResult::luma, "");
  row("blur score (S9 Laplacian)", &ModeResult::blur, "13.5 Laplacian, 16.3 blur total");
  row("resize to analysis width", &ModeResult::resize, "");
  row("overlap (track/ORB+match)", &ModeResult::overlap, "16.8 ORB + up to 550 matching");
  row("total decision", &ModeResult::total, "70-126 (14 Hz)");
  std::printf("  %-28s", "frames/s (single thread)");
  for (const auto& r : results) std::printf("%-22.1f", r.fps);
  std::printf("\n  %-28s", "CPU ms/frame");
  for (const auto& r : results) std::printf("%-22.2f", r.cpuPerFrameMs);
  std::printf("\n  %-28s", "heap allocations/frame");
  for (const auto& r : results) std::printf("%-22.2f", r.allocsPerFrame);
  std::printf("\n  %-28s", "  of which overlap stage");
  for (const auto& r : results) std::printf("%-22.2f", r.stageAllocs[3]);
  std::printf("\n  %-28s", "  of which luma+blur+resize");
  for (const auto& r : results)
    std::printf("%-22.2f", r.stageAllocs[0] + r.stageAllocs[1] + r.stageAllocs[2]);
  std::printf("\n  %-28s", "keyframes");
  for (const auto& r : results) std::printf("%-22ld", r.kept);
  std::printf("\n\npeak RSS %.1f MB (includes the %zu decoded frames held in memory)\n",
              static_cast<double>(maxRssKb()) / 1024.0, frames.size());
  benchTagging(frames);
  return 0;
}
