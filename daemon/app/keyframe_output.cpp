#include "app/keyframe_output.h"

#include <time.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <optional>
#include <thread>

namespace keyframed {

KeyframeOutput::KeyframeOutput(KeyframeWriter& writer, DecisionLog& log, FlightOutputs& outputs,
                               TelemetryService* telemetry, int telemetryWaitMs,
                               const PoseStore::Config& limits, double timeOffsetMs)
    : writer_(writer),
      log_(log),
      outputs_(outputs),
      telemetry_(telemetry),
      telemetryWaitMs_(telemetryWaitMs),
      limits_(limits),
      timeOffsetNs_(static_cast<std::int64_t>(std::llround(timeOffsetMs * 1e6))) {}

bool KeyframeOutput::linkDelivers(std::int64_t nowNs, bool gimbal) const {
  const TelemetryDecoder& d = telemetry_->decoder();
  const std::int64_t widest = std::max(limits_.maxAttitudeGapNs, limits_.maxPositionGapNs);
  if (!d.covers(nowNs - widest - limits_.maxHoldNs, gimbal)) return false;
  // Attitude, the fast stream, says sooner that the link went quiet: a sample came
  // within attitude_gap + stale. (Only the newest sample's age counts, so a link that
  // has just started delivers as soon as its first samples are in.)
  return d.hasAttitudeSince(nowNs - limits_.maxAttitudeGapNs - limits_.maxHoldNs);
}

bool KeyframeOutput::writeKeyframe(const Frame& captured, std::int64_t decidedNs, std::string& note,
                                   std::string& error) {
  // The keyframe is tagged for its exposure: the camera's frame time moved by its
  // latency (camera.time_offset_ms). A Frame is a view; the pixels stay where they are.
  Frame frame = captured;
  frame.timestampNs += timeOffsetNs_;
  std::optional<Pose> pose;
  if (telemetry_ != nullptr) {
    if (!telemetry_->isReplay()) {
      // Telemetry for this instant may still be on its way: wait a little, up to
      // wait_ms. Through a silence too, when the link was heard delivering: a radio
      // that stalls or an autopilot busy for half a second sends what it held back in
      // a burst when it moves on (given up at attitude_gap + stale, 0.4 s, such a pause
      // left the keyframe in it untagged). A link silent through a whole wait is lost:
      // the keyframes after it do not wait until it delivers again (waiting on every
      // one would hold each, and so the analysis and the capture, for wait_ms).
      const std::int64_t deadline = monotonicNowNs() + telemetryWaitMs_ * 1'000'000LL;
      // A gimbal only when its attitude is used: a dead gimbal on the link must not
      // hold up a fixed-mount camera's keyframes.
      const bool gimbal = writer_.mount().gimbal;
      // And for a clock estimate that has settled: the first keyframe, taken as the
      // first telemetry arrives, would otherwise be placed by a few messages' latency.
      // Attitude (tens of Hz, and held, not carried on, past its newest sample) must be
      // newer than the frame; a position (often 5-10 Hz) as old as the hold will do:
      // carried on at its velocity over that time it is off by half the acceleration
      // times its square (2 cm at 2 m/s^2 over 150 ms), well inside GPS's own error,
      // where waiting for the next one would hold every keyframe up to 100-200 ms.
      // A link opened less than that long ago counts as delivering: a camera started
      // with it (telemetry.start_wait_ms = 0) takes its first keyframe before the
      // autopilot's first messages, a few ms away.
      const TelemetryDecoder& d = telemetry_->decoder();
      const std::int64_t young = telemetry_->startedNs() + telemetryWaitMs_ * 1'000'000LL;
      if (linkDelivers(monotonicNowNs(), gimbal)) linkLost_ = false;  // heard again
      while (!d.covers(frame.timestampNs, gimbal, limits_.maxHoldNs) || !d.clockSettled()) {
        const std::int64_t now = monotonicNowNs();
        const bool delivers = now < young || linkDelivers(now, gimbal);
        if (now >= deadline) {
          if (!delivers) linkLost_ = true;
          break;
        }
        if (!delivers && linkLost_) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
      }
    }
    telemetry_->advanceReplay(frame.timestampNs);
    pose = telemetry_->decoder().poseAt(frame.timestampNs);
  }
  KeyframeRecord rec;
  const bool saved = writer_.write(frame, pose ? &*pose : nullptr, rec, error);
  if (!rec.encoded) return false;
  rec.decidedNs = decidedNs;
  // Published and recorded even when it could not be saved (disk full): a keyframe
  // the ground station receives is not lost.
  outputs_.keyframe(rec, writer_.lastJpeg());
  // Those a full disk held back, saved now: the publisher's copies can go.
  outputs_.keyframesIndexedLate(writer_.takeIndexedLate());
  note = rec.geotag;
  if (telemetry_ != nullptr && !telemetry_->isReplay()) {
    CaptureReport report;
    report.timeNs = frame.timestampNs;
    report.imageIndex = static_cast<std::int32_t>(rec.sequence);
    report.pose = rec.pose;
    report.cameraAttitude = rec.cameraToNed;
    report.fileUrl = "file://" + rec.file;
    report.saved = !rec.file.empty();  // on disk (untagged, or its row unsynced, too)
    telemetry_->reportCapture(report);
  }
  return saved;
}

bool KeyframeOutput::handle(const KeyframeEvent& ev, std::string& error) {
  // Every part is attempted even when one fails (disk full): the decision is still
  // published and recorded, the keyframe still sent. The first error is returned.
  std::string note;
  bool ok = true;
  auto failed = [&](const std::string& e) {
    if (ok) error = e;
    ok = false;
  };
  auto write = [&](const Frame& f) {
    std::string e;
    try {
      if (!writeKeyframe(f, ev.decidedNs, note, e)) failed(e);
    } catch (const std::exception& x) {  // (out of memory): the other keyframe still goes
      failed("keyframe " + std::to_string(f.index) + ": " + x.what());
    }
  };
  if (ev.endOfStream) {
    if (!ev.promoted) return true;
    write(ev.promoted->frame);
    log_.markGapFill(ev.promoted->frame.index);
    log_.setGeotag(ev.promoted->frame.index, note);
    return ok;
  }
  const Decision& d = ev.decision;
  if (outputs_.active()) outputs_.decision(d);
  if (ev.promoted) {
    write(ev.promoted->frame);
    log_.setGeotag(ev.promoted->frame.index, note);
  }
  note.clear();
  if (d.kept && ev.keyframe) write(ev.keyframe->frame);
  // The record's row as the decisions file's: a kept frame's with its geotag note.
  if (outputs_.active()) {
    decisionJson_.clear();  // its room stays: no allocation per frame
    DecisionLog::appendJsonRow(decisionJson_, d, note);
    outputs_.recordDecision(d, decisionJson_);
  }
  std::string e;
  if (!log_.add(d, e, note)) failed(e);
  return ok;
}

}  // namespace keyframed
