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
  // Called from another thread when the owner stops: a next() waiting for the
  // device returns at once (Error, "interrupted"), and so does every later one.
  // Sources whose next() never waits long (files) need not do anything.
  virtual void interrupt() {}
};

}  // namespace keyframed
