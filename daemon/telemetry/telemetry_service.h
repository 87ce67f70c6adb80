#pragma once

#include <atomic>
#include <cmath>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "core/capture_answer.h"
#include "telemetry/link.h"
#include "telemetry/mavlink_codec.h"
#include "telemetry/telemetry_decoder.h"
#include "telemetry/timed_packet.h"

namespace keyframed {

// What the camera component says about itself (CAMERA_INFORMATION).
struct CameraDescription {
  std::string vendor = "keyframed";
  std::string model = "camera";
  float focalLengthMm = NAN;  // NaN where unknown, never 0
  float sensorWidthMm = NAN;
  float sensorHeightMm = NAN;
  int width = 0;
  int height = 0;
};

// One keyframe, reported to the autopilot as CAMERA_IMAGE_CAPTURED.
struct CaptureReport {
  std::int64_t timeNs = 0;  // frame time, companion clock
  std::int32_t imageIndex = 0;
  Pose pose;                                 // position used when present
  std::optional<Quaternion> cameraAttitude;  // camera (OpenCV axes) -> NED
  std::string fileUrl;
  // Written to disk. A keyframe that was not (a full disk; it still went out on Zenoh)
  // is reported with capture_result 0 and no file URL.
  bool saved = true;
};

// CAMERA_IMAGE_CAPTURED.q: the camera's attitude in MAVLink's camera frame (x along
// the optical axis, y right, z down in the image; identity = looking along north,
// level, image top up) -> NED, from the camera -> NED attitude in OpenCV axes (x
// right, y down, z optical axis) that tagging uses.
[[nodiscard]] Quaternion mavlinkCameraAttitude(const Quaternion& cameraToNed);

// What the telemetry thread has to say (clock estimate, link state). The daemon
// routes it to its log (app/telemetry_log.h).
enum class TelemetryLogLevel { Warning, Notice, Info };

struct TelemetryServiceConfig {
  std::string url;        // see openMavlinkLink()
  int systemId = 0;       // our system id; 0: the autopilot's once known (else 1)
  int componentId = 100;  // MAV_COMP_ID_CAMERA
  bool timesync = true;   // send TIMESYNC requests (1 Hz)
  bool camera = true;     // act as a MAVLink camera component
  bool mavlink1 = false;  // send MAVLink 1 frames (ids above 255 still go as MAVLink 2)
  // Asks the autopilot (MAV_CMD_SET_MESSAGE_INTERVAL) for ATTITUDE and
  // GLOBAL_POSITION_INT at this rate, GPS_RAW_INT at up to 5 Hz and SYSTEM_TIME at
  // 1 Hz, once it is known and after it reboots; 0 leaves its stream rates alone.
  double messageRateHz = 20.0;
  std::size_t maxPendingCaptures = 256;  // unsent CAMERA_IMAGE_CAPTURED kept for the link
  std::size_t captureHistory = 1024;     // sent ones kept for MAV_CMD_REQUEST_MESSAGE
  // A serial device not there at start() (a USB autopilot powered after the
  // companion) is no failure: said, and opened once it appears (tried every second).
  bool waitForSerialDevice = false;
  TelemetryConfig decoder;
};

struct TelemetryServiceStats {
  ParserStats parser;
  TelemetryStats decoder;
  std::uint64_t linkErrors = 0;
  std::uint64_t reconnects = 0;
  std::uint64_t capturesSent = 0;      // CAMERA_IMAGE_CAPTURED really written to the link
  std::uint64_t capturesPending = 0;   // waiting for the link (no peer yet, write failed)
  std::uint64_t capturesDropped = 0;   // pushed out of a full pending queue, never sent
  std::uint64_t capturesResent = 0;    // sent again on MAV_CMD_REQUEST_MESSAGE
  std::uint64_t timesyncRejected = 0;  // replies not from the autopilot, or to no request of ours
  std::uint64_t infoSent = 0;
  std::uint64_t capturesReported = 0;  // keyframes reported (reportCapture): image_count
  std::uint64_t captureRequests = 0;   // captures asked of the selector (IMAGE_START_CAPTURE)
  std::uint64_t captureRefused = 0;    // ... that it could not take (too many waiting)
  std::uint64_t rateRequests = 0;      // MAV_CMD_SET_MESSAGE_INTERVAL sent to the autopilot
  std::uint64_t rateAccepted = 0;      // ... acknowledged as accepted
  std::uint64_t rateRefused = 0;       // ... acknowledged with any other result
  bool replayDone = false;
  bool truncated = false;
};

// The telemetry thread: reads the link, feeds the decoder, and speaks for the
// camera (HEARTBEAT, TIMESYNC, CAMERA_INFORMATION on request, CAMERA_IMAGE_CAPTURED).
// A replay link (tlog) is read at start() instead, and reaches the decoder, with its
// own times, as advanceReplay() asks.
class TelemetryService {
 public:
  TelemetryService(TelemetryServiceConfig config, CameraDescription camera);
  ~TelemetryService();
  TelemetryService(const TelemetryService&) = delete;
  TelemetryService& operator=(const TelemetryService&) = delete;

  bool start(std::string& error);
  // Starts on a link opened by the caller (tests, fuzzing); config.url is not used.
  bool start(std::unique_ptr<MavlinkLink> link, std::string& error);
  // A replay of recorded packets (arrival time in ns, bytes), e.g. a flight
  // record's /mavlink/raw: replayed like a tlog; no link, nothing sent. utc: the
  // arrival times are unix time, as a tlog's (TelemetryDecoder::setLocalClockIsUtc).
  void startFromPackets(std::vector<TimedPacket> packets, bool utc = false);
  // A replay reaches the decoder as the frames go: every packet recorded up to
  // localNs + kReplayLeadNs, what a live link would have delivered by the time that
  // frame is tagged. The clock estimate (a window of recent arrivals), the history
  // kept and an autopilot's reboot then act as they did in flight, not as they stand
  // at the end of a log that may run for an hour. Call it with the frame's time
  // before asking the decoder about it. Thread-safe; nothing for a live link.
  void advanceReplay(std::int64_t localNs);
  static constexpr std::int64_t kReplayLeadNs = 2'000'000'000;
  // Stops the telemetry thread; a replay is fed to its end (for the statistics).
  void stop();

  [[nodiscard]] const TelemetryDecoder& decoder() const { return decoder_; }
  [[nodiscard]] bool isReplay() const { return replay_; }
  // CLOCK_MONOTONIC when start() opened the link (0 before).
  [[nodiscard]] std::int64_t startedNs() const { return startNs_; }
  // A replay's packets as recorded, in order (empty for a live link), so that an
  // offline run's flight record can carry them on.
  [[nodiscard]] const std::vector<TimedPacket>& replayPackets() const { return replayPackets_; }
  // Queues a capture report; the telemetry thread sends it, and keeps it queued
  // (up to maxPendingCaptures, oldest dropped first) while the link cannot take it.
  // Thread-safe.
  void reportCapture(const CaptureReport& report);
  // Where a capture asked for over MAVLink goes (MAV_CMD_IMAGE_START_CAPTURE: one
  // image, or one every interval until a count or MAV_CMD_IMAGE_STOP_CAPTURE): the
  // selector's requestCapture(); Busy when it cannot take one more now, Ended when
  // the source has ended (the command is then denied, and an interval capture
  // stops). Without a sink
  // the camera does not advertise CAMERA_CAP_FLAGS_CAPTURE_IMAGE and refuses the
  // command. Set before start(); called on the telemetry thread.
  // intervalTick: an interval capture's tick, to be skipped while any request waits.
  using CaptureRequestSink = std::function<CaptureAnswer(bool intervalTick)>;
  static constexpr double kMinCaptureIntervalS = 0.05;
  void setCaptureRequestSink(CaptureRequestSink sink) { captureSink_ = std::move(sink); }
  // The camera is on a gimbal whose attitude tags it (tagging.mount = "gimbal"):
  // GIMBAL_DEVICE_ATTITUDE_STATUS is then asked for at messageRateHz too (ArduPilot
  // sends it in its EXTRA3 stream group, often at 1-2 Hz). Set before start().
  void setGimbalMount(bool gimbal) { gimbalMount_ = gimbal; }
  // Every MAVLink message received on a live link, with its arrival time (e.g. for
  // the flight record), those of other dialects too (unchecked: their message id is
  // not in the common dialect). Called on the telemetry thread; set or clear at any
  // time.
  using RawSink = std::function<void(const mavlink_message_t& msg, std::int64_t timeNs)>;
  void setRawSink(RawSink sink);
  // Where the telemetry thread reports the clock estimate (when first known and when
  // it changes notably), the autopilot it follows, link errors, silences and
  // reconnects, autopilot reboots. Rate-limited. Called on the telemetry thread.
  using LogSink = std::function<void(TelemetryLogLevel level, const std::string& message)>;
  void setLogSink(LogSink sink);
  // One received message, as the telemetry thread handles it (tests); not while the
  // thread runs. Without a link, nothing is sent.
  void handleMessage(const mavlink_message_t& msg, std::int64_t timeNs) { onMessage(msg, timeNs); }
  [[nodiscard]] TelemetryServiceStats stats() const;

 private:
  void run();
  void onMessage(const mavlink_message_t& msg, std::int64_t timeNs);
  bool send(const std::vector<std::uint8_t>& bytes);
  void sendHeartbeat();
  void sendTimesync(std::int64_t nowNs);
  void onTimesync(const mavlink_message_t& msg, std::int64_t timeNs);
  // A COMMAND_LONG, or a COMMAND_INT read as one (x, y, z as params 5-7), for us.
  void onCommand(const mavlink_command_long_t& c, const mavlink_message_t& msg);
  void onCommandAck(const mavlink_message_t& msg);
  void requestMessageRates(std::int64_t nowNs);
  void resendCaptures(const mavlink_command_long_t& c, const mavlink_message_t& msg);
  void startCapture(const mavlink_command_long_t& c, const mavlink_message_t& msg);
  CaptureAnswer requestCapture(bool intervalTick);
  // The COMMAND_ACK result (MAV_RESULT) for an answer.
  static std::uint8_t ackFor(CaptureAnswer answer);
  bool forOurCamera(const mavlink_command_long_t& c, const mavlink_message_t& msg);
  void runCaptureInterval(std::int64_t nowNs);
  void sendCaptureStatus();
  void sendPendingCaptures(std::int64_t nowNs);
  void log(TelemetryLogLevel level, const std::string& message);
  void logClock(std::int64_t nowNs);
  void sendCameraInformation();
  void sendCommandAck(std::uint16_t command, std::uint8_t result, std::uint8_t targetSys,
                      std::uint8_t targetComp);
  bool sendCapture(const CaptureReport& report);
  std::uint32_t bootMs() const;
  // The camera protocol's time_boot_ms of an instant on our clock: the autopilot's boot
  // clock once mapped (one base for every message of the camera's), else bootMs().
  std::uint32_t bootMsAt(std::int64_t localNs) const;
  std::uint8_t systemId() const;

  TelemetryServiceConfig config_;
  CameraDescription camera_;
  TelemetryDecoder decoder_;
  std::unique_ptr<MavlinkLink> link_;
  MavlinkParser parser_;
  std::unique_ptr<MavlinkEncoder> encoder_;
  std::thread thread_;
  std::atomic<bool> stop_{false};
  bool startUnopened_ = false;  // the link's device was not there at start()
  std::mutex sinkMutex_;
  RawSink sink_;
  std::mutex logMutex_;
  LogSink logSink_;
  // A TIMESYNC answer in a replay of a flight record: the clock mapped by it as live.
  void replayTimesync(const mavlink_message_t& msg, std::int64_t timeNs);
  bool replay_ = false;
  bool replayUtc_ = false;  // the replay's times are unix time (a tlog), not the live clock
  std::vector<TimedPacket> replayPackets_;
  std::mutex replayMutex_;
  std::size_t replayFed_ = 0;             // packets of replayPackets_ given to the decoder
  std::uint64_t replaySkippedBytes_ = 0;  // garbage between the replay's records
  std::int64_t startNs_ = 0;

  // Telemetry thread only.
  std::deque<std::int64_t> timesyncRequests_;  // ts1 of our recent TIMESYNC requests
  ClockMapper::Source loggedSource_ = ClockMapper::Source::None;
  std::int64_t loggedOffsetNs_ = 0;
  std::int64_t lastClockLogNs_ = 0;
  bool autopilotHeard_ = false;  // a message from the chosen autopilot (telemetry thread)
  int loggedAutopilot_ = 0;      // system * 256 + component, once logged
  std::uint64_t loggedReboots_ = 0;
  // MAVLink 2 from the autopilot seen; when it has spoken MAVLink 1 only for a while,
  // the encoder switches to MAVLink 1 (telemetry.mavlink1 does so from the start).
  bool autopilotV2_ = false;
  std::int64_t autopilotV1SinceNs_ = 0;
  struct {
    int autopilot = 0;          // sysid << 8 | compid the requests went to
    std::uint64_t reboots = 0;  // its reboots then: another asks again
    int rounds = 0;             // sent so far (all the messages each)
    std::int64_t nextNs = 0;    // when to send the next round
    bool done = false;          // answered, or given up (and said so)
  } rates_;
  std::int64_t lastCaptureWarningNs_ = 0;
  CaptureRequestSink captureSink_;
  bool gimbalMount_ = false;
  struct {
    int sequence = 0;  // param4 of the last single capture taken (a repeat is ignored)
    int sender = 0;    // its sysid << 8 | compid
    std::int64_t timeNs = 0;
  } lastCapture_;
  std::int64_t captureIntervalNs_ = 0;  // > 0: interval capture running
  std::int64_t nextCaptureNs_ = 0;
  std::int64_t capturesLeft_ = 0;  // of the interval capture; 0: until stopped

  mutable std::mutex mutex_;           // guards queue_, history_ and stats_
  std::deque<CaptureReport> queue_;    // to send
  std::deque<CaptureReport> history_;  // sent, newest last
  TelemetryServiceStats stats_;
};

}  // namespace keyframed
