#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "capture/frame_source.h"

namespace keyframed {

// A MAVLink packet as the live link received it, with its arrival time.
struct TimedPacket {
  std::int64_t timeNs = 0;
  std::vector<std::uint8_t> bytes;
};

// A flight record (MCAP written by `keyframed run`) as a frame source: the preview
// stream (/camera/preview, JPEG) decoded frame by frame with the live capture
// timestamps, and the raw MAVLink packets (/mavlink/raw) for the telemetry. open()
// reads the file once for the MAVLink packets; frames are then streamed, one chunk
// in memory at a time. A file cut short replays up to the cut.
class McapReplaySource final : public FrameSource {
 public:
  static std::unique_ptr<McapReplaySource> open(const std::string& path, std::string& error);
  ~McapReplaySource() override;

  [[nodiscard]] const SourceInfo& info() const override { return info_; }
  ReadStatus next(Frame& frame, std::string& error) override;

  [[nodiscard]] const std::vector<TimedPacket>& mavlink() const { return mavlink_; }
  [[nodiscard]] bool truncated() const { return truncated_; }

 private:
  McapReplaySource() = default;
  struct Impl;
  std::unique_ptr<Impl> impl_;
  SourceInfo info_;
  std::vector<TimedPacket> mavlink_;
  bool truncated_ = false;
  std::int64_t index_ = 0;
};

// True when `path` names an MCAP file (by its magic bytes).
bool isMcapFile(const std::string& path);

}  // namespace keyframed
