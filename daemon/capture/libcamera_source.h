#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "capture/frame_source.h"

namespace keyframed {

struct LibcameraOptions {
  std::string cameraId;  // empty: the first camera
  std::string format;    // "NV12", "YUV420", "YUYV"; empty: the first offered, in that order
  int width = 0;         // 0: the pipeline's default for the role
  int height = 0;
  double fps = 0.0;  // fixed frame duration when > 0
  int bufferCount = 4;
  int timeoutMs = 2000;   // longest wait for one frame (interrupt() ends it sooner)
  bool videoRole = true;  // StreamRole::VideoRecording, else Viewfinder
};

// libcamera capture behind FrameSource (Raspberry Pi cameras and any
// libcamera-supported sensor). The completion callback only moves the finished
// request into a queue; next() does the work on the caller's thread and hands
// the request back to the camera on the following call. Timestamps:
// controls::SensorTimestamp, else the buffer's timestamp (nanoseconds).
class LibcameraSource final : public FrameSource {
 public:
  ~LibcameraSource() override;
  LibcameraSource(const LibcameraSource&) = delete;
  LibcameraSource& operator=(const LibcameraSource&) = delete;

  // Ids of the cameras libcamera sees (may be empty). Creates its own
  // CameraManager: libcamera allows one per process at a time.
  static std::vector<std::string> listCameras(std::string& error);

  // nullptr and a one-line error ("no camera found", unknown id, no supported
  // format, camera busy) when the camera cannot be started.
  static std::unique_ptr<LibcameraSource> open(const LibcameraOptions& options, std::string& error);

  [[nodiscard]] const SourceInfo& info() const override { return info_; }
  ReadStatus next(Frame& frame, std::string& error) override;
  // The camera was disconnected: it is not reopened (the daemon exits and systemd
  // restarts it), so every later next() fails at once.
  [[nodiscard]] bool failed() const override;
  // Wakes a next() that waits for a completed request.
  void interrupt() override;

  [[nodiscard]] const std::string& cameraId() const { return cameraId_; }
  // True when the last frame's time came from controls::SensorTimestamp.
  [[nodiscard]] bool sensorTimestamps() const { return sensorTimestamps_; }
  [[nodiscard]] std::uint64_t failedFrames() const { return failedFrames_.load(); }
  // Frames the sensor produced with no request queued (gaps in
  // FrameMetadata::sequence), and failed ones.
  [[nodiscard]] std::uint64_t sequenceGaps() const { return sequenceGaps_.load(); }
  [[nodiscard]] std::uint64_t lostFrames() const override {
    return failedFrames_.load() + sequenceGaps_.load();
  }
  // controls::SensorTimestamp: the start of the first line's exposure. Without it,
  // the buffer's timestamp, whose meaning depends on the pipeline: Unknown.
  [[nodiscard]] TimestampOrigin timestampOrigin() const override { return origin_.load(); }

 private:
  struct Impl;
  LibcameraSource();

  std::unique_ptr<Impl> impl_;
  SourceInfo info_;
  std::string cameraId_;
  bool sensorTimestamps_ = false;
  std::atomic<TimestampOrigin> origin_{TimestampOrigin::Unknown};
  std::atomic<std::uint64_t> failedFrames_{0};
  std::atomic<std::uint64_t> sequenceGaps_{0};
  std::uint32_t lastSequence_ = 0;
  bool haveSequence_ = false;
  std::int64_t index_ = 0;
  int timeoutMs_ = 2000;
};

}  // namespace keyframed
