#include "capture/libcamera_select.h"

#include <algorithm>
#include <cctype>

#include <libcamera/formats.h>

namespace keyframed {
namespace {

const libcamera::PixelFormat kPreferred[] = {libcamera::formats::NV12, libcamera::formats::YUV420,
                                             libcamera::formats::YUYV};

std::string upper(const std::string& s) {
  std::string out;
  for (char c : s) out += static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  return out;
}

std::string join(const std::vector<libcamera::PixelFormat>& formats) {
  std::string s;
  for (const auto& f : formats) {
    if (!s.empty()) s += ", ";
    s += f.toString();
  }
  return s.empty() ? "none" : s;
}

}  // namespace

std::shared_ptr<libcamera::Camera> selectCamera(
    const std::vector<std::shared_ptr<libcamera::Camera>>& cameras, const std::string& id,
    std::string& error) {
  if (cameras.empty()) {
    error = "no camera found";
    return nullptr;
  }
  if (id.empty()) return cameras.front();
  std::string ids;
  for (const auto& c : cameras) {
    if (c->id() == id) return c;
    if (!ids.empty()) ids += ", ";
    ids += c->id();
  }
  error = "camera '" + id + "' not found (available: " + ids + ")";
  return nullptr;
}

libcamera::PixelFormat chooseLibcameraFormat(const std::vector<libcamera::PixelFormat>& offered,
                                             const std::string& wanted, std::string& error) {
  const auto has = [&](const libcamera::PixelFormat& f) {
    return std::find(offered.begin(), offered.end(), f) != offered.end();
  };
  if (!wanted.empty()) {
    const std::string w = upper(wanted);
    libcamera::PixelFormat f;
    if (w == "NV12") f = libcamera::formats::NV12;
    if (w == "YUV420" || w == "YU12" || w == "I420") f = libcamera::formats::YUV420;
    if (w == "YUYV" || w == "YUY2") f = libcamera::formats::YUYV;
    if (!f.isValid()) {
      error = "unknown pixel format '" + wanted + "' for libcamera (supported: NV12, YUV420, YUYV)";
      return {};
    }
    if (!has(f)) {
      error = "camera does not offer " + f.toString() + " (offers: " + join(offered) + ")";
      return {};
    }
    return f;
  }
  for (const auto& f : kPreferred) {
    if (has(f)) return f;
  }
  error = "camera offers no supported pixel format (offers: " + join(offered) +
          "; supported: NV12, YUV420, YUYV)";
  return {};
}

libcamera::Size chooseLibcameraSize(const libcamera::StreamFormats& formats,
                                    const libcamera::PixelFormat& format,
                                    const libcamera::Size& wanted, const libcamera::Size& current) {
  if (wanted.width == 0 || wanted.height == 0) return current;
  // range() of discrete sizes spans them with steps of 0; one size is a range of one.
  const libcamera::SizeRange range = formats.range(format);
  if (range.hStep > 0 && range.vStep > 0 && range.min != range.max &&
      wanted.width >= range.min.width && wanted.height >= range.min.height &&
      wanted.width <= range.max.width && wanted.height <= range.max.height) {
    return wanted;
  }
  const std::vector<libcamera::Size> offered = formats.sizes(format);
  if (offered.empty()) return wanted;  // the pipeline scales: let validate() adjust
  const libcamera::Size* best = nullptr;
  for (const auto& s : offered) {
    if (s == wanted) return s;
    if (s.width >= wanted.width && s.height >= wanted.height &&
        (best == nullptr ||
         std::uint64_t{s.width} * s.height < std::uint64_t{best->width} * best->height)) {
      best = &s;
    }
  }
  if (best != nullptr) return *best;
  return *std::max_element(offered.begin(), offered.end(), [](const auto& a, const auto& b) {
    return std::uint64_t{a.width} * a.height < std::uint64_t{b.width} * b.height;
  });
}

bool toFrameFormat(const libcamera::PixelFormat& format, PixelFormat& out) {
  if (format == libcamera::formats::NV12) {
    out = PixelFormat::NV12;
  } else if (format == libcamera::formats::YUV420) {
    out = PixelFormat::YUV420;
  } else if (format == libcamera::formats::YUYV) {
    out = PixelFormat::YUYV;
  } else {
    return false;
  }
  return true;
}

}  // namespace keyframed
