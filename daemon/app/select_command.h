#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <string>

#include "app/options.h"

namespace keyframed {

struct SelectSummary {
  std::int64_t framesRead = 0;
  std::int64_t kept = 0;
  std::int64_t rejectedBlur = 0;     // Reason::Blurry, or Lost and not sharp; never promoted
  std::int64_t rejectedOverlap = 0;  // Reason::Redundant, never promoted
  std::int64_t promoted = 0;         // kept later as gap fills (included in kept)
  double seconds = 0.0;              // wall time of the run
  double framesPerSecond = 0.0;
  double analysisMsMean = 0.0;  // selector time per frame (no decode, no JPEG)
  bool truncated = false;       // the video ended before its announced length
  bool interrupted = false;     // stopped by a signal or --max-frames
  std::string error;            // non-empty: the run failed (one line)
  // Non-empty: the --mcap record stopped (a full disk) or is incomplete; the run's
  // keyframes and decisions are complete, so this is no failure of the run.
  std::string recordError;
  bool badOptions = false;  // ... because the options do not fit the flight record
  struct Telemetry {
    std::string source;  // empty: no telemetry
    std::int64_t geotagged = 0;
    std::string clock = "none";
    std::string clockOffsetMs = "null";
    std::string clockUncertaintyMs = "null";  // TIMESYNC: half the width of its bounds
    std::string recordClockAheadMs = "null";  // tlog record times minus SYSTEM_TIME
    std::uint64_t messages = 0;
    std::uint64_t rejected = 0;
    std::uint64_t unknownIds = 0;
    std::uint64_t skippedBytes = 0;
    std::uint64_t otherSources = 0;
    std::uint64_t gimbal = 0;      // gimbal attitude messages used
    std::uint64_t badSamples = 0;  // attitudes (NaN, no rotation) and positions not used
    std::uint64_t reboots = 0;     // the autopilot's clock went back: it restarted
    std::uint64_t capturesSent = 0;
    std::uint64_t capturesPending = 0;    // never sent: the link did not take them by the end
    std::uint64_t capturesDropped = 0;    // pushed out of the full queue while the link was down
    std::uint64_t capturesResent = 0;     // sent again on MAV_CMD_REQUEST_MESSAGE
    std::uint64_t capturesRequested = 0;  // MAV_CMD_IMAGE_START_CAPTURE images asked for
    std::uint64_t capturesRefused = 0;    // ... refused, or interval ticks skipped
    std::uint64_t capturesUnserved = 0;   // ... taken, but the video ended first
    std::uint64_t linkErrors = 0;
    std::uint64_t reconnects = 0;
    bool truncated = false;
  } telemetry;
  // Where the video sits on the tlog's clock: given (--video-start TIME) or found from
  // the motion (--video-start auto).
  struct VideoStart {
    std::string method;  // "", "given", "motion"
    std::int64_t unixNs = 0;
    double correlation = 0.0;  // motion: at the lag found, and the best elsewhere
    double runnerUp = 0.0;
    double seconds = 0.0;  // motion: wall time of the pass
  } videoStart;
  std::string summaryPath;
  std::string decisionsPath;
};

using ProgressFn = std::function<void(std::int64_t framesRead, std::int64_t totalFrames,
                                      std::int64_t kept, double fps)>;

// Runs selection over a video file and writes keyframes, decisions and summary
// into opts.outDir. Keyframes already written are never lost: on a read error
// the outputs up to that frame are complete and the error is reported.
SelectSummary runSelection(const SelectOptions& opts, const ProgressFn& progress = {},
                           const std::atomic<bool>* stop = nullptr);

// `keyframed select ...`: returns the process exit code.
int selectMain(const std::vector<std::string>& args);

}  // namespace keyframed
