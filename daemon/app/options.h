#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "app/settings.h"
#include "core/selector.h"

namespace keyframed {

enum class DecisionFormat { Csv, JsonLines };

// Everything `keyframed select` can be told. Each field names its flag.
struct SelectOptions {
  std::string video;                               // positional VIDEO
  std::string outDir;                              // --out DIR (required)
  SelectorConfig selector;                         // --mode, --target, --band, --blur-*, ...
  DecisionFormat decisions = DecisionFormat::Csv;  // --decisions csv|jsonl
  int jpegQuality = 92;                            // --jpeg-quality 1..100
  std::int64_t maxFrames = -1;                     // --max-frames N (stop after N frames)
  std::optional<bool> progress;  // --progress / --no-progress (default: when stderr is a TTY)
  bool quiet = false;            // --quiet: no summary on stdout
  bool overwrite = false;        // --overwrite: replace an earlier run's output in outDir

  // Telemetry and tagging.
  std::string telemetry;    // --telemetry URL|FILE.tlog (see openMavlinkLink)
  std::string calibration;  // --calibration FILE (OpenCV YAML/XML, TOML, JSON)
  // --set telemetry.KEY=VALUE: the daemon's [telemetry] settings (stale limits,
  // GPS fix, clock windows, ...), applied before the options above.
  std::vector<std::string> telemetrySets;
  std::string make;                              // --make TEXT (EXIF Make)
  std::string model;                             // --model TEXT (EXIF Model)
  std::optional<std::int64_t> videoStartUnixNs;  // --video-start ISO8601|UNIX_SECONDS
  bool videoStartAuto = false;  // --video-start auto: found from the motion (app/video_sync.h)
  double mountRollDeg = 0.0;    // --mount ROLL,PITCH,YAW (degrees, body FRD)
  double mountPitchDeg = -90.0;
  double mountYawDeg = 0.0;
  bool mountGimbal = false;          // --mount gimbal
  bool realtime = false;             // --realtime: deliver frames at the video's rate
  int telemetryWaitMs = 1000;        // --telemetry-wait MS: wait for poses this long
  double timeOffsetMs = 0.0;         // --time-offset MS: frame time -> exposure time
  int telemetryStartWaitMs = 10000;  // --telemetry-start-wait MS: first pose, live links
  int autopilotSystem = 0;           // --autopilot SYS[:COMP] (0: first autopilot)
  int autopilotComponent = 0;
  int mavlinkSystemId = 0;  // --mavlink-sysid N (0: the autopilot's)

  // Recording and streaming (daemon/output/flight_outputs.h).
  std::string mcap;             // --mcap FILE: MCAP flight record
  std::string zenohConfig;      // --zenoh-config FILE: publish keyframes on Zenoh
  std::string vehicle = "uav";  // --vehicle NAME: keyframed/<NAME>/... keys

  // The command line as parsed, so that a replay can apply its selection options on
  // top of the settings a flight record was made with.
  std::vector<std::string> args;
  // The selector was set whole (the Python API's config): a flight record's own
  // settings do not replace it. Without it and without args, a replay selects with
  // the record's settings.
  bool selectorGiven = false;
};

struct ParseResult {
  bool ok = false;
  bool help = false;
  std::string error;  // one line
  // Options given that have no effect with the others (a paper-mode option in the
  // geometric mode, a live link's without one): one line each, to be said.
  std::vector<std::string> warnings;
};

// Parses the arguments after `select`.
ParseResult parseSelectOptions(const std::vector<std::string>& args, SelectOptions& out);

// The selection settings' agreement with each other (band, target, tracks, ...), named
// by their options; empty when they agree. parseSelectOptions checks them, except over
// a flight record, whose own settings the options go on top of.
std::string checkSelectSettings(const SelectorConfig& selector);

std::string selectUsage();

}  // namespace keyframed
