#pragma once

#include <cstdint>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "core/frame.h"
#include "core/resize.h"
#include "tagging/jpeg_encoder.h"

namespace keyframed {

// The preview stream of the flight record: each frame in colour, scaled to `width`
// (0: off) as a JPEG, or at or above the frame's width lossless as a PNG, so that a
// replay sees the very pixels the live selection saw.
//
// A camera's YUV420 or NV12 frame is scaled plane by plane (core/resize, as the
// analysis image) and encoded from YUV: only the small picture is ever touched in
// colour (converting 1080p to BGR first cost more than the rest of the preview).
// BGR24, grey and YUYV go through BGR. Buffers are reused.
class PreviewEncoder {
 public:
  explicit PreviewEncoder(int width) : width_(width) {}

  // False when the preview is off or encoding failed; `out` then holds nothing useful.
  bool encode(const Frame& frame, std::vector<std::uint8_t>& out);
  // "jpeg" or "png": what the last encode() produced.
  [[nodiscard]] const char* format() const { return format_; }
  // The preview's size for a frame of `width` x `height` (even, for 4:2:0 chroma).
  [[nodiscard]] cv::Size sizeFor(int width, int height) const;

 private:
  bool encodeYuv(const Frame& frame, std::vector<std::uint8_t>& out);

  static constexpr int kQuality = 85;
  int width_;
  const char* format_ = "jpeg";
  cv::Mat bgr_, small_, half_, halfSpare_;  // BGR path
  DownScaler luma_, chromaU_, chromaV_;     // YUV path: one per plane, sizes fixed
  cv::Mat chromaUFull_, chromaVFull_;       // NV12: its chroma de-interleaved
  std::vector<std::uint8_t> planes_;        // the scaled picture, I420
  JpegEncoder encoder_;
};

}  // namespace keyframed
