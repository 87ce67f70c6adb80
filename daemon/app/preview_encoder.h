#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "core/frame.h"
#include "core/resize.h"
#include "output/h264.h"
#include "tagging/jpeg_encoder.h"

namespace keyframed {

// The preview stream of the flight record: each frame in colour, scaled to `width`
// (0: off) as a JPEG, or at or above the frame's width lossless as a PNG, so that a
// replay sees the very pixels the live selection saw. Or, as H.264 (format "h264"),
// the same pictures as one video stream (an IDR picture every second; full size at
// or above the frame's width, lossy): a quarter of the JPEGs' bytes.
//
// A camera's YUV420, NV12 or YUYV frame is scaled plane by plane (core/resize, as the
// analysis image; YUYV's planes de-interleaved first) and encoded from YUV: only the
// small picture is ever touched in colour (converting 1080p to BGR first cost more
// than the rest of the preview), and nothing is allocated but libjpeg-turbo's own
// work memory. BGR24 and grey go through BGR (OpenCV's resize, which takes a few
// buffers from the heap for each frame). Buffers are reused.
class PreviewEncoder {
 public:
  enum class Format : std::uint8_t { Jpeg, H264 };

  // `fps`: the source's nominal rate, for H.264's rate control.
  explicit PreviewEncoder(int width, Format format = Format::Jpeg, double fps = 30);

  // False when the preview is off or encoding failed (error() says why); `out` then
  // holds nothing useful.
  bool encode(const Frame& frame, std::vector<std::uint8_t>& out);
  // "jpeg", "png" or "h264": what the last encode() produced.
  [[nodiscard]] const char* format() const { return format_; }
  // The picture the last H.264 encode() compressed, as a JPEG (a still for Zenoh's
  // preview key); false in the other formats.
  bool lastAsJpeg(std::vector<std::uint8_t>& out);
  // The frame as a JPEG still of the preview's size, whatever the format (for Zenoh's
  // preview key when nothing is recorded).
  bool still(const Frame& frame, std::vector<std::uint8_t>& out);
  [[nodiscard]] const std::string& error() const { return error_; }
  // The preview's size for a frame of `width` x `height` (even, for 4:2:0 chroma).
  [[nodiscard]] cv::Size sizeFor(int width, int height) const;

 private:
  // The frame scaled to I420 at sizeFor() (picture_): camera YUV into planes_, BGR-like
  // formats through bgr_ into i420_.
  bool scaleToI420(const Frame& frame);
  bool scaleYuv(const Frame& frame);
  // bgr_ (the whole frame in colour) scaled to `size` into small_.
  void scaleBgr(cv::Size size);
  [[nodiscard]] Frame planesFrame() const;

  static constexpr int kQuality = 85;
  int width_;
  Format mode_;
  const char* format_ = "jpeg";
  std::string error_;
  cv::Size planesSize_;
  cv::Mat bgr_, small_, half_, halfSpare_;  // BGR path
  DownScaler luma_, chromaU_, chromaV_;     // YUV path: one per plane, sizes fixed
  cv::Mat chromaUFull_, chromaVFull_;       // NV12, YUYV: its chroma de-interleaved
  cv::Mat yuyvLuma_;                        // YUYV: its luma de-interleaved
  std::vector<std::uint8_t> planes_;        // YUV path: the scaled picture, I420
  cv::Mat i420_;                            // BGR path: small_ as I420
  const std::uint8_t* picture_ = nullptr;   // the last scaled picture: planes_ or i420_
  JpegEncoder encoder_;
  H264Encoder h264_;
};

}  // namespace keyframed
