#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "output/io.h"

namespace keyframed {

// What the flight recorder writes; each is one MCAP channel (see docs/formats.md).
enum class McapTopic : std::uint8_t {
  Keyframe,         // /keyframed/keyframe       foxglove.CompressedImage (the tagged JPEG)
  KeyframeMeta,     // /keyframed/keyframe_meta  JSON: sequence, frame index, pose, scores
  Decision,         // /keyframed/decision       JSON: one per analysed frame
  Mavlink,          // /mavlink/raw              keyframed.MavlinkPacket
  Location,         // /keyframed/location       foxglove.LocationFix at each keyframe
  CameraPose,       // /keyframed/camera_pose    foxglove.PoseInFrame (camera -> NED)
  Calibration,      // /camera/calibration       foxglove.CameraCalibration
  Log,              // /keyframed/log            foxglove.Log
  Preview,          // /camera/preview           foxglove.CompressedImage (every frame, JPEG)
  VehicleLocation,  // /vehicle/location     foxglove.LocationFix (GLOBAL_POSITION_INT)
  VehiclePose,      // /vehicle/pose         foxglove.PoseInFrame (ATTITUDE[_QUATERNION])
  Settings,         // /keyframed/settings   JSON: the selection settings, at start and reload
  Video,            // /camera/video         foxglove.CompressedVideo (every frame, H.264)
  Count
};

struct McapRecorderOptions {
  std::string path;
  std::string compression = "zstd";      // zstd | lz4 | none
  std::uint64_t chunkSize = 256 * 1024;  // small chunks: a crash loses one at most
  int flushIntervalMs = 1000;            // chunks end at least this often
  bool fsync = false;                    // fsync at each timed flush (power loss)
  // Added to every message's time for its log and publish time: maps the clock the
  // caller stamps with (CLOCK_MONOTONIC for a live run) onto unix time.
  std::int64_t timeOffsetNs = 0;
  std::size_t maxQueueBytes = 64u << 20;  // queued but unwritten message bytes
  bool blockWhenFull = false;             // true: producers wait (offline); false: drop
  // Rotation: a new file once this many message bytes (uncompressed) or seconds went
  // into the current one (0: never). Parts after the first are named
  // <stem>-001<ext>, <stem>-002<ext>, ...; each is a complete MCAP file with every
  // schema and channel, and the latest calibration repeated.
  std::uint64_t rotateBytes = 0;
  std::int64_t rotateSeconds = 0;
  // Called on the writer thread with each new part's path (not under any lock of the
  // recorder's: it may log).
  std::function<void(const std::string&)> onNewPart;
  // A part that holds video (McapTopic::Video) ends just before the next picture a
  // decoder can start at (record()'s `startsGroup`), so that each part plays on its
  // own; at most this long after it was due, it ends anyway (a stream that stopped).
  int videoRotationWaitMs = 3000;
  // Called once, on the thread that hit it, when a write error stops the recorder
  // (disk full, I/O error); not under any lock of the recorder's. Unset: one line on
  // stderr.
  std::function<void(const std::string&)> onFailure;
};

struct McapRecorderStats {
  std::uint64_t written = 0;  // messages
  std::uint64_t bytes = 0;    // message payload bytes
  std::uint64_t dropped = 0;  // queue full or recorder stopped
  std::uint64_t flushes = 0;
  std::uint64_t files = 0;  // parts written (1 without rotation)
};

// The flight recorder: one writer thread owns the MCAP file; any thread queues
// messages. A write error (disk full, I/O error) stops the recorder with one log
// line on stderr; the caller is never blocked or failed by it afterwards.
class McapRecorder {
 public:
  McapRecorder() = default;
  ~McapRecorder();
  McapRecorder(const McapRecorder&) = delete;
  McapRecorder& operator=(const McapRecorder&) = delete;

  // Creates the file, writes every schema and channel and flushes them at once, so
  // a file cut short at any later point still names its channels.
  bool open(const McapRecorderOptions& options, std::string& error);
  // Queues one encoded message (see foxglove_proto.h); timeNs on the caller's clock
  // (the file's log and publish time: timeNs + options.timeOffsetNs).
  // sequence 0: the channel's own counter. startsGroup: for McapTopic::Video, whether
  // a decoder can start at this picture (an H.264 IDR); other topics ignore it.
  void record(McapTopic topic, std::int64_t timeNs, std::vector<std::uint8_t> message,
              std::uint32_t sequence = 0, bool startsGroup = true);
  // As record(), but never waits for room (drops instead): for callers that hold a
  // lock the writer thread may need, such as the logger's.
  void tryRecord(McapTopic topic, std::int64_t timeNs, std::vector<std::uint8_t> message);
  void recordText(McapTopic topic, std::int64_t timeNs, const std::string& json);
  // An empty buffer for a message, with room for `bytes` where a written message's
  // buffer had it (the writer thread hands them back): messages made in these, and
  // queued with record(), cost no allocation in steady state.
  [[nodiscard]] std::vector<std::uint8_t> buffer(std::size_t bytes = 0);
  // Drains the queue, writes the summary and closes. False when the recorder failed
  // at any point (error says why).
  bool close(std::string& error);

  [[nodiscard]] bool isOpen() const { return thread_.joinable(); }
  [[nodiscard]] bool failed() const { return failed_.load(); }
  [[nodiscard]] McapRecorderStats stats() const;
  [[nodiscard]] static const char* topicName(McapTopic topic);

 private:
  struct Item {
    McapTopic topic;
    std::uint32_t sequence;
    std::int64_t timeNs;
    std::vector<std::uint8_t> data;
    bool startsGroup;
  };
  void enqueue(McapTopic topic, std::int64_t timeNs, std::vector<std::uint8_t> message,
               std::uint32_t sequence, bool mayWait, bool startsGroup = true);
  // Whether the part ends before `next`: rotation is due and, in a part with video,
  // `next` opens a group of pictures (or the wait for one is over).
  [[nodiscard]] bool rotateBefore(const Item& next) const;
  void run();
  void fail(const std::string& error);
  bool openFile(const std::string& path, std::string& error);
  bool rotate(std::string& error);
  [[nodiscard]] std::string partPath(int part) const;

  McapRecorderOptions options_;
  std::unique_ptr<McapWriter> writer_;
  std::uint16_t channels_[static_cast<int>(McapTopic::Count)] = {};
  std::uint32_t sequences_[static_cast<int>(McapTopic::Count)] = {};
  std::thread thread_;
  int part_ = 0;
  std::uint64_t fileBytes_ = 0;
  std::int64_t lastTimeNs_ = 0;
  std::chrono::steady_clock::time_point fileStart_;
  bool videoInPart_ = false;  // the part holds a video picture
  std::optional<std::chrono::steady_clock::time_point> rotationDue_;  // since when
  // Repeated at the start of each part, so that one part replays and reads on its own:
  // the camera calibration and the selection settings in force.
  std::vector<std::uint8_t> latchedCalibration_;
  std::vector<std::uint8_t> latchedSettings_;

  mutable std::mutex mutex_;
  std::condition_variable wake_;   // writer: work or closing
  std::condition_variable space_;  // producers: queue has room
  std::vector<Item> queue_;        // swapped with the writer's batch: both keep their room
  std::size_t queuedBytes_ = 0;
  // Written messages' buffers, emptied, for buffer(): at most kSpareBuffers holding
  // at most kSpareBytes in all.
  static constexpr std::size_t kSpareBuffers = 64;
  static constexpr std::size_t kSpareBytes = 8u << 20;
  std::vector<std::vector<std::uint8_t>> spare_;
  std::size_t spareBytes_ = 0;
  bool closing_ = false;
  McapRecorderStats stats_;
  std::string error_;
  std::atomic<bool> failed_{false};
};

}  // namespace keyframed
