#pragma once

// How a camera's frame planes become the one contiguous picture a Frame
// describes (Y, then chroma, rows `stride` apart). libcamera hands each plane as
// its own (fd, offset, length): often back to back in one dmabuf, but pipelines
// may pad between planes or put them in separate buffers. Pure: unit-tested
// without a camera.

#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "core/frame.h"

namespace keyframed {

// One mapped plane as the driver filled it.
struct PlaneSpan {
  const std::uint8_t* data = nullptr;
  std::size_t length = 0;  // bytes mapped for this plane (may include padding)
};

// Bytes of up to three planes, held in place: asked for every frame, so no heap.
struct PlaneSizes {
  std::array<std::size_t, 3> bytes{};
  std::size_t count = 0;

  [[nodiscard]] const std::size_t* begin() const { return bytes.data(); }
  [[nodiscard]] const std::size_t* end() const { return bytes.data() + count; }
  [[nodiscard]] std::size_t size() const { return count; }
  std::size_t operator[](std::size_t i) const { return bytes[i]; }
  [[nodiscard]] std::size_t total() const { return bytes[0] + bytes[1] + bytes[2]; }
};

// Bytes each plane of `format` holds at `stride` (the luma stride) and `height`:
// NV12: Y, interleaved UV; YUV420: Y, U, V (chroma rows half as long); packed
// formats: one plane.
inline PlaneSizes planeSizes(PixelFormat format, int stride, int height) {
  const auto s = static_cast<std::size_t>(stride);
  const auto h = static_cast<std::size_t>(height);
  const std::size_t ch = (h + 1) / 2;
  switch (format) {
    case PixelFormat::NV12: return {{s * h, s * ch, 0}, 2};
    case PixelFormat::YUV420: return {{s * h, s / 2 * ch, s / 2 * ch}, 3};
    case PixelFormat::Gray8:
    case PixelFormat::YUYV:
    case PixelFormat::BGR24: break;
  }
  return {{s * h, 0, 0}, 1};
}

// The start of the frame laid out contiguously: the first plane itself when every
// plane follows the one before it without a gap (no copy), else `packed`, filled
// plane by plane from each plane's own memory. nullptr and a one-line error when a
// plane is missing or shorter than the format needs. A single plane that holds the
// whole frame (some pipelines describe it so) is used as is.
inline const std::uint8_t* contiguousFrame(PixelFormat format, int stride, int height,
                                           std::span<const PlaneSpan> planes,
                                           std::vector<std::uint8_t>& packed, std::string& error) {
  const PlaneSizes need = planeSizes(format, stride, height);
  const std::size_t total = need.total();
  if (planes.empty() || planes[0].data == nullptr) {
    error = "frame buffer has no planes";
    return nullptr;
  }
  if (planes.size() == 1 && planes[0].length >= total) return planes[0].data;
  if (planes.size() < need.size()) {
    error = "frame buffer has " + std::to_string(planes.size()) + " planes, " + toString(format) +
            " needs " + std::to_string(need.size());
    return nullptr;
  }
  bool adjacent = true;
  for (std::size_t i = 0; i < need.size(); ++i) {
    if (planes[i].data == nullptr || planes[i].length < need[i]) {
      error = "plane " + std::to_string(i) + " holds " + std::to_string(planes[i].length) +
              " bytes, " + toString(format) + " needs " + std::to_string(need[i]);
      return nullptr;
    }
    if (i > 0 && planes[i].data != planes[i - 1].data + need[i - 1]) adjacent = false;
  }
  if (adjacent) return planes[0].data;
  if (packed.size() < total) packed.resize(total);  // once: the size does not change
  std::size_t at = 0;
  for (std::size_t i = 0; i < need.size(); ++i) {
    std::copy_n(planes[i].data, need[i], packed.data() + at);
    at += need[i];
  }
  return packed.data();
}

}  // namespace keyframed
