#include "capture/mjpeg_decoder.h"

#include <turbojpeg.h>

namespace keyframed {

namespace {
// EOI (FF D9) among the last bytes: drivers may pad a frame after it, with zeros or
// a few bytes of junk, but not by much.
bool hasEndMarker(const std::uint8_t* data, std::size_t size) {
  constexpr std::size_t kTail = 4096;
  const std::size_t from = size > kTail ? size - kTail : 0;
  for (std::size_t i = size; i-- > from + 1;) {
    if (data[i - 1] == 0xFF && data[i] == 0xD9) return true;
  }
  return false;
}
}  // namespace

MjpegDecoder::MjpegDecoder() : handle_(tjInitDecompress()) {}

MjpegDecoder::~MjpegDecoder() {
  if (handle_ != nullptr) tjDestroy(handle_);
}

bool MjpegDecoder::decode(const std::uint8_t* data, std::size_t size, std::string& error,
                          int expectedWidth, int expectedHeight) {
  if (handle_ == nullptr) {
    error = "libjpeg-turbo decompressor could not be created";
    return false;
  }
  // A JPEG starts with SOI (FF D8); drivers hand over empty or garbage payloads
  // when a USB transfer was lost.
  if (data == nullptr || size < 4 || data[0] != 0xFF || data[1] != 0xD8) {
    error = "MJPEG frame is not a JPEG (" + std::to_string(size) + " bytes)";
    return false;
  }
  int w = 0, h = 0, subsamp = 0, colorspace = 0;
  // turbojpeg's API takes non-const buffers in 2.1.
  auto* src = const_cast<unsigned char*>(data);
  const auto len = static_cast<unsigned long>(size);
  if (tjDecompressHeader3(handle_, src, len, &w, &h, &subsamp, &colorspace) != 0 || w <= 0 ||
      h <= 0) {
    error = std::string("MJPEG header: ") + tjGetErrorStr2(handle_);
    return false;
  }
  if ((expectedWidth > 0 && w != expectedWidth) || (expectedHeight > 0 && h != expectedHeight)) {
    error = "MJPEG frame is " + std::to_string(w) + "x" + std::to_string(h) + ", not " +
            std::to_string(expectedWidth) + "x" + std::to_string(expectedHeight);
    return false;
  }
  const std::size_t bytes = static_cast<std::size_t>(w) * static_cast<std::size_t>(h) * 3;
  if (bgr_.size() < bytes) bgr_.resize(bytes);
  if (tjDecompress2(handle_, src, len, bgr_.data(), w, w * 3, h, TJPF_BGR, TJFLAG_FASTDCT) != 0) {
    if (tjGetErrorCode(handle_) != TJERR_WARNING) {
      error = std::string("MJPEG decode: ") + tjGetErrorStr2(handle_);
      return false;
    }
    // A warning with the end marker in place (stray bytes in the data) leaves a
    // usable picture. Without it the frame was cut short in the USB transfer (UVC
    // flags short frames only for uncompressed formats): the rows after the cut are
    // grey filler, and a sharp top half could pass the blur test as a keyframe.
    if (!hasEndMarker(data, size)) {
      error = std::string("MJPEG frame cut short (no end marker): ") + tjGetErrorStr2(handle_);
      return false;
    }
  }
  width_ = w;
  height_ = h;
  return true;
}

}  // namespace keyframed
