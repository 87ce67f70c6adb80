#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "core/frame.h"

namespace keyframed {

// JPEG compression with libjpeg-turbo, straight from the capture pixel format.
// One encoder per thread (a tjhandle is not thread-safe). Buffers are reused: with the
// same `out` vector and frame size, encoding allocates nothing in steady state.
//
// Plane layouts (Frame::stride is the first plane's row pitch):
//   Gray8, BGR24  one plane.
//   YUV420 (I420) Y, then U, then V, contiguous; chroma planes are (w+1)/2 x (h+1)/2
//                 with a pitch of (stride+1)/2.
//   NV12          Y, then interleaved UV (h+1)/2 rows with the same pitch as Y.
//   YUYV          packed 4:2:2 (Y0 U Y1 V).
// Colour is encoded as YCbCr 4:2:0 (YUV420, NV12, BGR24), 4:2:2 (YUYV) or grey.
//
// JPEG (JFIF) stores full-range YCbCr (0-255). Cameras' video streams usually deliver
// limited ("TV") range, Y 16-235 and chroma 16-240; those samples are expanded while
// the planes are copied (one table look-up per byte), otherwise the keyframes would
// come out washed out. BT.601 vs BT.709 matrices are not converted.
enum class YuvRange { Limited, Full };

class JpegEncoder {
 public:
  JpegEncoder();
  ~JpegEncoder();
  JpegEncoder(const JpegEncoder&) = delete;
  JpegEncoder& operator=(const JpegEncoder&) = delete;

  // False when libjpeg-turbo could not be set up.
  [[nodiscard]] bool isValid() const { return handle_ != nullptr; }

  // Range of YUV420/NV12/YUYV input (default Limited, what V4L2 and libcamera video
  // streams give unless asked for sYCC/JPEG colour space).
  void setYuvRange(YuvRange range);

  // Replaces `out` with the JPEG. quality 1..100. False with a one-line error.
  [[nodiscard]] bool encode(const Frame& frame, int quality, std::vector<std::uint8_t>& out,
                            std::string& error);
  [[nodiscard]] bool encode(const cv::Mat& bgr, int quality, std::vector<std::uint8_t>& out,
                            std::string& error);

 private:
  bool compressPacked(const std::uint8_t* data, int width, int stride, int height, int pixelFormat,
                      int subsamp, int quality, std::vector<std::uint8_t>& out, std::string& error);
  bool compressPlanes(const std::uint8_t* const planes[3], const int strides[3], int width,
                      int height, int subsamp, int quality, std::vector<std::uint8_t>& out,
                      std::string& error);

  void* handle_ = nullptr;            // tjhandle
  std::vector<std::uint8_t> planes_;  // Y, U, V planes rebuilt from the YUV input (reused)
  std::uint8_t lumaLut_[256] = {};    // input sample -> full-range sample
  std::uint8_t chromaLut_[256] = {};
};

}  // namespace keyframed
