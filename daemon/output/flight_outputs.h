#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <string_view>

#include "app/keyframe_writer.h"
#include "core/selector.h"
#include "tagging/camera_model.h"
#include "telemetry/pose.h"

namespace keyframed {

// What is wrong with a Zenoh configuration file as zenoh reads it (empty: nothing, or
// a build without Zenoh), so that a configuration check finds it before a run starts.
std::string zenohConfigError(const std::string& path);

struct FlightOutputOptions {
  std::string mcapPath;                // --mcap FILE; empty: no recording
  std::string zenohConfig;             // --zenoh-config FILE; empty: no Zenoh
  std::string vehicle = "uav";         // --vehicle NAME
  std::string keyframeDir;             // where KeyframeWriter puts JPEGs + keyframes.csv
  std::string flight;                  // the run's flight id (KeyframePublisherOptions)
  std::string flightsDir;              // where earlier flights' directories are
  bool offline = true;                 // offline: the recorder waits instead of dropping
  bool zenoh = false;                  // publish even without a config file (Zenoh's defaults)
  std::uint64_t mcapRotateBytes = 0;   // a new MCAP part after this many bytes (0: never)
  std::int64_t mcapRotateSeconds = 0;  // ... or seconds (0: never)
  std::string zenohSetting = "--zenoh-config";  // how the user named the Zenoh config
  int zenohRetryMs = 0;  // a session that cannot open: 0 fails open(), else tried again
  // A live run's close(): keyframes still queued for the link are put for this long at
  // most, the rest left to the queryable (they are on disk, served to a ground station
  // by the next run too), so that a stop on a congested link ends inside systemd's
  // TimeoutStopSec (15 s) with the record and summary written.
  int stopDrainMs = 4000;
  bool mcapFsync = false;                // output.mcap_fsync: fsync at each timed flush
  std::string mcapCompression = "zstd";  // zstd | lz4 | none
  // The clock of the times given to decision(), keyframe(), ...: liveClock means
  // CLOCK_MONOTONIC (a live run), mapped onto unix time with the offset measured at
  // open(); otherwise unixOffsetNs maps it, and startNs is its time at open().
  bool liveClock = false;
  std::int64_t unixOffsetNs = 0;
  std::int64_t startNs = 0;
  // Where FlightOutputs' own warnings go (a publish that failed); empty: stderr.
  std::function<void(const std::string&)> warn;
  std::function<void(const std::string&)> note;  // informational lines; empty: stderr
  // A part of the outputs stopped for the rest of the run (the recorder hit a full
  // disk); empty: warn.
  std::function<void(const std::string&)> error;
};

// Everything a run sends beyond its keyframe directory: the MCAP flight record and
// the Zenoh stream. The run calls it at each step; failures after open() are
// logged and never stop the run (the keyframe directory is the durable store).
class FlightOutputs {
 public:
  FlightOutputs();
  ~FlightOutputs();
  FlightOutputs(const FlightOutputs&) = delete;
  FlightOutputs& operator=(const FlightOutputs&) = delete;

  // Opens what the options ask for; false with a one-line error when it cannot.
  bool open(const FlightOutputOptions& options, int width, int height, const CameraModel* camera,
            std::string& error);
  [[nodiscard]] bool active() const;
  // An MCAP file is being written (false once a write error, a full disk, stopped it).
  [[nodiscard]] bool recording() const;
  // Messages the MCAP writer has written so far (0 without a record).
  [[nodiscard]] std::uint64_t recordedMessages() const;

  // Every analysed frame, before its keyframe (the scores a keyframe is published
  // with); then its row, decisionJson as DecisionLog::jsonRow writes it, for the
  // record, once the keyframe's geotag note is known.
  void decision(const Decision& d);
  void recordDecision(const Decision& d, const std::string& decisionJson);
  // Every keyframe written, with its tagged JPEG bytes.
  void keyframe(const KeyframeRecord& record, std::span<const std::uint8_t> jpeg);
  // Keyframes that were not indexed when keyframe() had them (a full disk) and now
  // are (KeyframeWriter::takeIndexedLate()): the queryable serves them from disk.
  void keyframesIndexedLate(std::span<const std::int64_t> sequences);
  // A raw MAVLink packet as received (thread-safe; the telemetry thread calls it).
  void mavlink(std::int64_t timeNs, std::uint32_t systemId, std::uint32_t componentId,
               std::uint32_t messageId, std::span<const std::uint8_t> packet);
  // The autopilot's position (WGS84, metres above mean sea level) and attitude (body to
  // NED) as it reported them, for the record's /vehicle/location and /vehicle/pose.
  void vehicleLocation(std::int64_t timeNs, double latDeg, double lonDeg, double altAmslM);
  void vehicleAttitude(std::int64_t timeNs, const Quaternion& bodyToNed);
  // One frame of the preview stream, for replay: format "jpeg" or "png" on
  // /camera/preview, "h264" (one picture's packet) on /camera/video. JPEGs also go to
  // Zenoh's preview key (previewStill()).
  void preview(std::int64_t timeNs, std::span<const std::uint8_t> image, const char* format);
  // Zenoh's preview key gets a JPEG twice a second at most: whether one is due now, and
  // the still itself (dropped when none is due).
  [[nodiscard]] bool previewStillDue() const;
  void previewStill(std::span<const std::uint8_t> jpeg);
  // The selection settings in force from timeNs (selection.KEY=VALUE lines), for a
  // replay of the record to select as the flight did. Main thread.
  void settings(std::int64_t timeNs, const std::string& selectionLines);
  // What the keyframes are tagged with, for a replay to tag as the flight did:
  // tagging.KEY=VALUE lines (EXIF make and model, the camera mount) and the camera
  // model, when there is one, as a [camera] table (camera_model_toml.h). Every
  // settings() message from then on carries them. Before the first settings().
  void tagging(const std::string& taggingLines, const CameraModel* camera);
  // The vehicle's pose (JSON) on Zenoh's .../telemetry key.
  void telemetry(const std::string& json);
  [[nodiscard]] bool publishing() const;  // a Zenoh session is open
  // Progress (status on Zenoh about once a second): its `kept` is keyframesOut(kept).
  void progress(std::int64_t framesRead, std::int64_t kept);
  // Of the first `kept` keyframes (sequence numbers 0..kept-1), how many are out on
  // the link: put, or left to the queryable; not one still waiting to be put, nor any
  // after it. Thread-safe.
  [[nodiscard]] std::int64_t keyframesOut(std::int64_t kept) const;
  // One line of the daemon's log into the record's /keyframed/log, stamped now.
  // Thread-safe and never waits (the logger calls it under its lock); level is a
  // syslog priority (3 error ... 7 debug).
  void log(int level, std::string_view category, std::string_view message);
  // Last status and close; false when the MCAP file is incomplete (error says why; the
  // recorder said it through options.error when it failed).
  bool close(const std::string& state, std::string& error);

  // Tests: replaces the Zenoh put of keyframes (false with an error: a failed put).
  using KeyframePut = std::function<bool(std::span<const std::uint8_t> jpeg,
                                         const std::string& meta, std::string& error)>;
  void setKeyframePutForTesting(KeyframePut put);

 private:
  struct Impl;  // empty when built without the I/O crate
  std::unique_ptr<Impl> impl_;
};

}  // namespace keyframed
