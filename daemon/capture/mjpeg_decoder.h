#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace keyframed {

// Decodes Motion-JPEG camera frames to packed BGR with libjpeg-turbo, into one
// reused buffer. Frames without Huffman tables (common in webcam MJPEG) decode
// with the standard tables.
class MjpegDecoder {
 public:
  MjpegDecoder();
  ~MjpegDecoder();
  MjpegDecoder(const MjpegDecoder&) = delete;
  MjpegDecoder& operator=(const MjpegDecoder&) = delete;

  // Decodes `size` bytes. On success bgr() holds width()*height()*3 bytes,
  // rows width()*3 apart. On failure `error` holds a one-line reason. With an
  // expected size (the negotiated one), a header that says otherwise is refused
  // before anything is allocated: a garbled frame can claim 65535x65535 (12 GB).
  [[nodiscard]] bool decode(const std::uint8_t* data, std::size_t size, std::string& error,
                            int expectedWidth = 0, int expectedHeight = 0);

  [[nodiscard]] const std::uint8_t* bgr() const { return bgr_.data(); }
  [[nodiscard]] int width() const { return width_; }
  [[nodiscard]] int height() const { return height_; }
  [[nodiscard]] int stride() const { return width_ * 3; }

 private:
  void* handle_ = nullptr;  // tjhandle
  std::vector<std::uint8_t> bgr_;
  int width_ = 0;
  int height_ = 0;
};

}  // namespace keyframed
