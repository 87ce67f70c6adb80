#include "app/video_sync.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <vector>

#include "capture/file_source.h"
#include "core/overlap.h"
#include "core/resize.h"

namespace keyframed {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
// Longest tlog searched: a day at 20 ms is 4.3 million samples.
constexpr std::int64_t kMaxSpanNs = 24LL * 3600 * 1'000'000'000;

// The turn from attitude a to attitude b (camera -> NED) about the camera's own
// optical axis (z), radians: the z part of the rotation vector of conj(a) * b.
double turnAboutOpticalAxis(const Quaternion& a, const Quaternion& b) {
  Quaternion d = multiply(Quaternion{a.w, -a.x, -a.y, -a.z}, b);
  if (d.w < 0) d = Quaternion{-d.w, -d.x, -d.y, -d.z};
  const double s = std::sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
  if (s < 1e-12) return 0.0;
  return 2.0 * std::atan2(s, d.w) * d.z / s;
}

// The camera's turn rate seen in the video: times (container seconds, midway between
// two frames) and rates (rad/s about the optical axis, as a right-handed turn about
// the axis pointing into the scene).
struct VideoTurns {
  std::vector<double> timesS;
  std::vector<double> rates;
  std::int64_t frames = 0;
  std::int64_t known = 0;
  std::string error;
};

VideoTurns measureVideoTurns(const VideoSyncRequest& req, const std::atomic<bool>* stop) {
  VideoTurns out;
  std::string error;
  auto source = FileSource::open(req.video, error);
  if (!source) {
    out.error = error;
    return out;
  }
  OverlapConfig oc;
  oc.mode = OverlapMode::Geometric;
  if (req.camera) oc.lens = req.camera->lensModel();
  auto estimator = OverlapEstimator::create(oc);
  LumaExtractor luma;
  DownScaler scaler;
  std::int64_t prevNs = 0;
  bool havePrev = false;
  Frame frame;
  while (stop == nullptr || !stop->load()) {
    const ReadStatus st = source->next(frame, error);
    if (st == ReadStatus::End) break;
    if (st == ReadStatus::Error) {
      if (source->failed()) break;  // what came before still counts
      continue;
    }
    ++out.frames;
    const OverlapResult r =
        estimator->observe(scaler.scaleToWidth(luma.luma(frame), req.analysisWidth));
    const std::int64_t dtNs = frame.timestampNs - prevNs;
    if (havePrev) {
      const bool turned = dtNs > 0 && std::isfinite(r.stepRotationRad);
      out.timesS.push_back((static_cast<double>(prevNs) + 0.5 * static_cast<double>(dtNs)) / 1e9);
      // A camera turning by +a about its optical axis turns the scene on its image by -a.
      out.rates.push_back(turned ? -r.stepRotationRad / (static_cast<double>(dtNs) / 1e9) : kNaN);
      if (turned) ++out.known;
    }
    prevNs = frame.timestampNs;
    havePrev = true;
  }
  if (out.frames < 2 && (stop == nullptr || !stop->load()))
    out.error = req.video + ": too few frames to measure the camera's turns";
  return out;
}

}  // namespace

VideoSync syncVideoWithTlog(const VideoSyncRequest& req, const std::atomic<bool>* stop) {
  VideoSync out;
  const auto started = std::chrono::steady_clock::now();
  const auto finish = [&]() -> VideoSync& {
    out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
    return out;
  };

  // The tlog: once through to learn how far its record times run ahead of the
  // autopilot's GPS time (the frames follow GPS time), then again, sampled on the grid.
  TelemetryServiceConfig tc = req.link;
  tc.camera = false;
  tc.timesync = false;
  std::int64_t firstNs = 0, lastNs = 0, aheadNs = 0;
  std::vector<TimedPacket> packets;  // read once, replayed twice
  {
    TelemetryService probe(tc, CameraDescription{});
    std::string error;
    if (!probe.start(error)) {
      out.error = error;
      return finish();
    }
    if (!probe.isReplay()) {
      out.error =
          "--video-start auto needs a tlog: a live link's frames are stamped as they arrive";
      return finish();
    }
    packets = probe.replayPackets();
    if (packets.empty()) {
      out.error = req.link.url + ": no MAVLink packets";
      return finish();
    }
    // The span of the record times (a station's clock may step: not front and back).
    firstNs = packets.front().timeNs;
    lastNs = firstNs;
    for (const TimedPacket& p : packets) {
      firstNs = std::min(firstNs, p.timeNs);
      lastNs = std::max(lastNs, p.timeNs);
    }
    if (lastNs - firstNs > kMaxSpanNs) {
      out.error = req.link.url +
                  ": its record times span more than a day (a clock that stepped?): too long "
                  "to search";
      return finish();
    }
    probe.stop();  // feeds the rest
    aheadNs = probe.decoder().recordClockAheadNs().value_or(0);
  }

  const auto stopped = [stop] { return stop != nullptr && stop->load(); };
  VideoTurns turns = measureVideoTurns(req, stop);
  out.frames = turns.frames;
  out.turnsKnown = turns.known;
  if (stopped()) {
    out.error = "interrupted";
    return finish();
  }
  if (!turns.error.empty()) {
    out.error = turns.error;
    return finish();
  }

  TelemetryService svc(tc, CameraDescription{});
  svc.startFromPackets(std::move(packets), true);  // unix record times, as start() reads them
  const auto stepNs = static_cast<std::int64_t>(std::llround(req.stepS * 1e9));
  const std::int64_t t0 = firstNs - aheadNs;
  const std::int64_t t1 = lastNs - aheadNs;
  std::vector<double> times;
  std::vector<double> rates;
  std::optional<Quaternion> prev;
  for (std::int64_t t = t0; t <= t1; t += stepNs) {
    if ((t - t0) % (1000 * stepNs) == 0 && stopped()) {
      out.error = "interrupted";
      return finish();
    }
    svc.advanceReplay(t);
    const Pose p = svc.decoder().poseAt(t);
    std::optional<Quaternion> cam;
    if (req.mount.gimbal) {
      if (p.gimbal) cam = cameraToNed(*p.gimbal, CameraMount{0, 0, 0, false});
    } else if (p.attitude) {
      cam = cameraToNed(*p.attitude, req.mount);
    }
    if (prev && cam) {
      times.push_back(static_cast<double>(t - t0 - stepNs / 2) / 1e9);
      rates.push_back(turnAboutOpticalAxis(*prev, *cam) / req.stepS);
    } else if (t > t0) {
      times.push_back(static_cast<double>(t - t0 - stepNs / 2) / 1e9);
      rates.push_back(kNaN);
    }
    prev = cam;
  }
  svc.stop();
  if (times.size() < 2) {
    out.error = req.link.url + ": too short to place the video in";
    return finish();
  }
  // Video rates are a frame interval apart: across a lost frame or two they are joined.
  const RateSeries video = resampleRates(turns.timesS, turns.rates, req.stepS, 0.2);
  const RateSeries tel = resampleRates(times, rates, req.stepS, 2.5 * req.stepS);
  out.match = findMotionLag(video, tel, req.match);
  if (!out.match.ok) {
    out.error =
        "cannot place the video in the tlog by its motion: " + out.match.error + "; " + req.hint;
    return finish();
  }
  // Telemetry time t0 + lag is video (container) time 0.
  out.videoStartUnixNs = t0 + static_cast<std::int64_t>(std::llround(out.match.lagS * 1e9));
  out.ok = true;
  return finish();
}

}  // namespace keyframed
