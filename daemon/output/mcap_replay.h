#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "capture/frame_source.h"
#include "tagging/camera_model.h"
#include "telemetry/timed_packet.h"

namespace keyframed {

// A flight record (MCAP written by `keyframed run`) as a frame source: the preview
// stream (/camera/preview, JPEG or PNG; or /camera/video, H.264 from its first IDR
// picture on) decoded frame by frame with the live capture
// timestamps (the messages' own timestamp fields, on the run's clock) and the live
// frame indices (from /keyframed/decision: frames the live run dropped leave the same
// gaps; by position in the stream for records without decisions), and the raw
// MAVLink packets (/mavlink/raw) for the telemetry. open() reads the record once for
// the MAVLink packets; frames are then streamed, one chunk in memory at a time. A
// file cut short replays up to the cut. A record rotated into parts (flight.mcap,
// flight-001.mcap, ...) replays whole when given its first part.
class McapReplaySource final : public FrameSource {
 public:
  static std::unique_ptr<McapReplaySource> open(const std::string& path, std::string& error);
  ~McapReplaySource() override;

  [[nodiscard]] const SourceInfo& info() const override { return info_; }
  ReadStatus next(Frame& frame, std::string& error) override;

  [[nodiscard]] const std::vector<TimedPacket>& mavlink() const { return mavlink_; }
  [[nodiscard]] bool truncated() const { return truncated_; }
  // The files replayed, in order (one, or every part of a rotated record).
  [[nodiscard]] const std::vector<std::string>& parts() const { return parts_; }
  // Run clock -> unix time, as the record's log times map it (0 for older records).
  [[nodiscard]] std::int64_t unixOffsetNs() const { return unixOffsetNs_; }
  [[nodiscard]] std::int64_t firstTimeNs() const { return firstTimeNs_; }
  // The last frame next() returned as recorded (JPEG, PNG or an H.264 packet) and its
  // format ("jpeg", "png", "h264"), so a replay's own record can carry the stream on.
  [[nodiscard]] std::span<const std::uint8_t> encoded() const;
  [[nodiscard]] const std::string& format() const { return format_; }
  // The live run kept the last frame next() returned as a commanded capture
  // (MAV_CMD_IMAGE_START_CAPTURE): a replay asks for one there too.
  [[nodiscard]] bool commanded() const { return commanded_; }
  // The record's camera calibration (/camera/calibration: K and D at the video's
  // resolution), when it has one.
  [[nodiscard]] const std::optional<CameraModel>& calibration() const { return calibration_; }
  // The selection settings the flight started with (/keyframed/settings:
  // selection.KEY=VALUE lines; empty for records without them), and how many times
  // they changed during it (SIGHUP reloads).
  [[nodiscard]] const std::string& selectionSettings() const { return selection_; }
  // What its keyframes were tagged with (the same message: tagging.KEY=VALUE lines,
  // config.h's taggingOverrides, and the whole camera model: make, model, sensor size
  // and focal length beside K and D); empty / none for records from before they were
  // kept, or a flight without a camera model.
  [[nodiscard]] const std::string& taggingSettings() const { return tagging_; }
  [[nodiscard]] const std::optional<CameraModel>& camera() const { return camera_; }
  [[nodiscard]] int settingsChanges() const { return settingsChanges_; }

 private:
  McapReplaySource() = default;
  struct Impl;
  std::unique_ptr<Impl> impl_;
  SourceInfo info_;
  std::vector<TimedPacket> mavlink_;
  bool truncated_ = false;
  std::int64_t index_ = 0;
  std::int64_t lastIndex_ = -1;  // the index the frame before was given
  std::vector<std::string> parts_;
  std::size_t part_ = 0;  // the part next() reads
  std::int64_t unixOffsetNs_ = 0;
  std::int64_t firstTimeNs_ = 0;
  std::string format_;
  bool commanded_ = false;
  std::optional<CameraModel> calibration_;
  std::string selection_;
  std::string tagging_;
  std::optional<CameraModel> camera_;
  int settingsChanges_ = 0;
};

// The parts of a rotated flight record, given its first: path itself, then
// <stem>-001<ext>, <stem>-002<ext>, ... for as long as they exist.
std::vector<std::string> mcapParts(const std::string& path);

// True when `path` names an MCAP file (by its magic bytes).
bool isMcapFile(const std::string& path);

}  // namespace keyframed
