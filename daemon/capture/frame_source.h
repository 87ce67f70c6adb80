#pragma once

#include <cstdint>
#include <string>

#include "core/frame.h"

namespace keyframed {

struct SourceInfo {
  int width = 0;
  int height = 0;
  double fps = 0.0;
  std::int64_t frameCount = -1;  // -1 when unknown (live cameras)
  std::string description;
};

enum class ReadStatus { Frame, End, Error };

// What instant a frame's timestamp marks. The pose a keyframe is tagged with is
// looked up for that instant (moved by camera.time_offset_ms), so a timestamp taken
// at the end of readout places a moving aircraft a frame period too far along.
enum class TimestampOrigin {
  Unknown,          // not said (yet)
  StartOfExposure,  // the sensor's or driver's start of exposure (libcamera, V4L2 SOE)
  EndOfFrame,       // the driver's time of the frame's last byte (V4L2 EOF)
  Arrival,          // when the process received it: no driver time
  Container,        // a video file's presentation time
};

// "start of exposure", "end of frame", ...
inline const char* describe(TimestampOrigin o) {
  switch (o) {
    case TimestampOrigin::StartOfExposure: return "start of exposure";
    case TimestampOrigin::EndOfFrame: return "end of frame";
    case TimestampOrigin::Arrival: return "arrival";
    case TimestampOrigin::Container: return "container time";
    case TimestampOrigin::Unknown: break;
  }
  return "unknown";
}

// Where frames come from: cameras, files, replays. One small interface; each
// backend lives in its own file.
class FrameSource {
 public:
  virtual ~FrameSource() = default;
  [[nodiscard]] virtual const SourceInfo& info() const = 0;
  // The next frame. Its pixels stay valid until the next call. On Error,
  // `error` holds a one-line reason.
  virtual ReadStatus next(Frame& frame, std::string& error) = 0;
  // True once next() has returned an Error the source cannot recover from (a
  // truncated file, a camera gone for good): calling again would only repeat it.
  [[nodiscard]] virtual bool failed() const { return false; }
  // Frames the camera produced that never came out of next(): the driver had no free
  // buffer for them (gaps in its sequence numbers), or they came broken and were
  // skipped. Counted by the source, read by any thread (STATUS, the summary).
  [[nodiscard]] virtual std::uint64_t lostFrames() const { return 0; }
  // What the timestamps of the frames delivered so far mark; read by any thread.
  [[nodiscard]] virtual TimestampOrigin timestampOrigin() const { return TimestampOrigin::Unknown; }
  // Called from another thread when the owner stops: a next() waiting for the
  // device returns at once (Error, "interrupted"), and so does every later one.
  // Sources whose next() never waits long (files) need not do anything.
  virtual void interrupt() {}
  // Frames that already wait in the device (filled while no one read, before the
  // capture started) are handed back to it unread; how many. A camera that stamps
  // frames when they are read rather than when they are taken would otherwise give
  // a view from seconds ago the time of now. Sources that hold none need not do
  // anything. The reading thread calls it.
  virtual std::uint64_t discardQueued() { return 0; }
};

}  // namespace keyframed
