#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>
#include <opencv2/videoio.hpp>

#include "capture/frame_source.h"

namespace keyframed {

// A video file decoded by OpenCV's FFmpeg backend, frame by frame, as fast as
// the reader asks. Timestamps are the container's presentation times.
class FileSource final : public FrameSource {
 public:
  // Returns nullptr and a one-line error when the file is missing or is not a
  // readable video.
  static std::unique_ptr<FileSource> open(const std::string& path, std::string& error);

  [[nodiscard]] const SourceInfo& info() const override { return info_; }
  ReadStatus next(Frame& frame, std::string& error) override;
  // After a truncation or a change of frame size: every later next() repeats that
  // Error without reading.
  [[nodiscard]] bool failed() const override { return !failure_.empty(); }
  [[nodiscard]] TimestampOrigin timestampOrigin() const override {
    return TimestampOrigin::Container;
  }
  // True when the stream ended before the frame count its header announced.
  [[nodiscard]] bool truncated() const { return truncated_; }
  [[nodiscard]] std::int64_t framesRead() const { return index_; }
  // The first frame of the longest run of 30 or more frames that repeat one picture
  // (by a sample of its bytes), and its length; -1 and 0 when there is none. OpenCV's
  // reader hands back the last picture again when the stream changes size part-way
  // (FFmpeg's scaler refuses the new size, and OpenCV does not say): what follows is
  // lost, not a hover. (A still video repeats its picture too.)
  [[nodiscard]] std::int64_t repeatedFrom() const { return repeatedFrom_; }
  [[nodiscard]] std::int64_t repeatedFrames() const { return repeatedFrames_; }
  // Deliver frames as a camera would: YUV420 (I420) or NV12, converted from the
  // decoded picture (BT.601, limited range, as cameras' video streams are), instead
  // of BGR24 as decoded. False with a one-line error for another format or a frame
  // of odd width or height. Call before the first next().
  bool setOutputFormat(PixelFormat format, std::string& error);

 private:
  FileSource() = default;
  void toCameraFormat(Frame& frame);  // bgr_ -> output_

  cv::VideoCapture capture_;
  cv::Mat bgr_;
  PixelFormat output_ = PixelFormat::BGR24;
  cv::Mat yuv_;                       // the frame as delivered, I420 or NV12
  std::vector<std::uint8_t> chroma_;  // NV12: the I420 chroma planes, while interleaving
  SourceInfo info_;
  std::string path_;
  std::int64_t index_ = 0;
  bool primed_ = false;  // bgr_ holds the first frame, read while probing
  bool truncated_ = false;
  std::size_t packetSize_ = 0;  // MPEG-TS packet size (188, 192), 0 for other containers
  std::uintmax_t fileSize_ = 0;
  std::string failure_;           // the permanent error, once there is one
  std::uint64_t lastSample_ = 0;  // sampleHash() of the frame before
  std::int64_t runFrom_ = 0;      // the current run of repeats began there
  std::int64_t repeatedFrom_ = -1;
  std::int64_t repeatedFrames_ = 0;
};

}  // namespace keyframed
