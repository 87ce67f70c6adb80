#pragma once

#include <cstdint>

#include <opencv2/core/mat.hpp>

namespace keyframed {

// Pixel layouts a FrameSource may deliver. Planar/semi-planar YUV frames expose
// their Y plane directly; packed formats are converted once.
enum class PixelFormat { Gray8, NV12, YUV420, YUYV, BGR24 };

// Inline (no OpenCV needed): the static V4L2 probe uses it too.
inline const char* toString(PixelFormat format) {
  switch (format) {
    case PixelFormat::Gray8: return "GRAY8";
    case PixelFormat::NV12: return "NV12";
    case PixelFormat::YUV420: return "YUV420";
    case PixelFormat::YUYV: return "YUYV";
    case PixelFormat::BGR24: return "BGR24";
  }
  return "unknown";
}

// A non-owning 8-bit single-channel image.
struct GrayView {
  const std::uint8_t* data = nullptr;
  int width = 0;
  int height = 0;
  int stride = 0;  // bytes between rows

  [[nodiscard]] bool empty() const { return data == nullptr || width <= 0 || height <= 0; }
  [[nodiscard]] const std::uint8_t* row(int y) const {
    return data + static_cast<std::ptrdiff_t>(y) * stride;
  }
  // A cv::Mat header on the same memory (no copy).
  [[nodiscard]] cv::Mat mat() const;
  static GrayView of(const cv::Mat& gray);
};

// One captured frame: pixels (borrowed), capture time and sequence index.
struct Frame {
  PixelFormat format = PixelFormat::Gray8;
  const std::uint8_t* data = nullptr;  // first plane
  int width = 0;
  int height = 0;
  int stride = 0;                // bytes per row of the first plane
  std::int64_t timestampNs = 0;  // capture time on the source's clock
  std::int64_t index = 0;        // zero-based frame number from the source

  static Frame ofBgr(const cv::Mat& bgr, std::int64_t index, std::int64_t timestampNs);
  static Frame ofGray(const cv::Mat& gray, std::int64_t index, std::int64_t timestampNs);
};

// Gives the luma plane of a frame: a view without a copy for Gray8, NV12 and
// YUV420; one conversion into a reused buffer for BGR24 and YUYV.
class LumaExtractor {
 public:
  [[nodiscard]] GrayView luma(const Frame& frame);

 private:
  cv::Mat buffer_;
};

}  // namespace keyframed
