#include "tagging/jpeg_encoder.h"

#include <algorithm>
#include <cmath>

#include <turbojpeg.h>

namespace keyframed {
namespace {

tjhandle tj(void* h) {
  return static_cast<tjhandle>(h);
}

bool checkQuality(int quality, std::string& error) {
  if (quality < 1 || quality > 100) {
    error = "JPEG quality must be 1..100, got " + std::to_string(quality);
    return false;
  }
  return true;
}

}  // namespace

JpegEncoder::JpegEncoder() : handle_(tjInitCompress()) {
  setYuvRange(YuvRange::Limited);
}

void JpegEncoder::setYuvRange(YuvRange range) {
  for (int i = 0; i < 256; ++i) {
    double yv = i;
    double cv = i;
    if (range == YuvRange::Limited) {
      yv = (i - 16) * 255.0 / 219.0;
      cv = (i - 128) * 255.0 / 224.0 + 128.0;
    }
    lumaLut_[i] = static_cast<std::uint8_t>(std::clamp(std::lround(yv), 0L, 255L));
    chromaLut_[i] = static_cast<std::uint8_t>(std::clamp(std::lround(cv), 0L, 255L));
  }
}

JpegEncoder::~JpegEncoder() {
  if (handle_ != nullptr) tjDestroy(tj(handle_));
}

// Compresses straight into `out`: it is sized to libjpeg-turbo's worst case first and
// TJFLAG_NOREALLOC stops the library from allocating a buffer of its own.
bool JpegEncoder::compressPacked(const std::uint8_t* data, int width, int stride, int height,
                                 int pixelFormat, int subsamp, int quality,
                                 std::vector<std::uint8_t>& out, std::string& error) {
  out.resize(tjBufSize(width, height, subsamp));
  unsigned char* dst = out.data();
  unsigned long size = out.size();
  if (tjCompress2(tj(handle_), data, width, stride, height, pixelFormat, &dst, &size, subsamp,
                  quality, TJFLAG_NOREALLOC) != 0) {
    error = std::string("JPEG compression failed: ") + tjGetErrorStr2(tj(handle_));
    out.clear();
    return false;
  }
  out.resize(size);
  return true;
}

bool JpegEncoder::compressPlanes(const std::uint8_t* const planes[3], const int strides[3],
                                 int width, int height, int subsamp, int quality,
                                 std::vector<std::uint8_t>& out, std::string& error) {
  out.resize(tjBufSize(width, height, subsamp));
  unsigned char* dst = out.data();
  unsigned long size = out.size();
  const unsigned char* src[3] = {planes[0], planes[1], planes[2]};
  if (tjCompressFromYUVPlanes(tj(handle_), src, width, strides, height, subsamp, &dst, &size,
                              quality, TJFLAG_NOREALLOC) != 0) {
    error = std::string("JPEG compression failed: ") + tjGetErrorStr2(tj(handle_));
    out.clear();
    return false;
  }
  out.resize(size);
  return true;
}

bool JpegEncoder::encode(const Frame& f, int quality, std::vector<std::uint8_t>& out,
                         std::string& error) {
  if (handle_ == nullptr) {
    error = "libjpeg-turbo compressor could not be created";
    return false;
  }
  if (!checkQuality(quality, error)) return false;
  if (f.data == nullptr || f.width <= 0 || f.height <= 0) {
    error = "empty frame";
    return false;
  }
  const int minStride = f.format == PixelFormat::BGR24  ? f.width * 3
                        : f.format == PixelFormat::YUYV ? 2 * ((f.width + 1) / 2) * 2
                                                        : f.width;
  if (f.stride < minStride) {
    error = std::string("frame stride too small for ") + toString(f.format);
    return false;
  }
  // An odd-width I420 frame whose rows are not padded has chroma rows (stride / 2)
  // shorter than its chroma is wide: nothing to read the last sample from.
  if (f.format == PixelFormat::YUV420 && f.stride / 2 < (f.width + 1) / 2) {
    error = "YUV420 frame of odd width " + std::to_string(f.width) + " without row padding";
    return false;
  }
  const int cw = (f.width + 1) / 2;
  const int ch = (f.height + 1) / 2;
  const std::uint8_t* y = f.data;
  const std::size_t ySize = static_cast<std::size_t>(f.stride) * f.height;
  switch (f.format) {
    case PixelFormat::Gray8:
      return compressPacked(f.data, f.width, f.stride, f.height, TJPF_GRAY, TJSAMP_GRAY, quality,
                            out, error);
    case PixelFormat::BGR24:
      return compressPacked(f.data, f.width, f.stride, f.height, TJPF_BGR, TJSAMP_420, quality, out,
                            error);
    case PixelFormat::YUV420:
    case PixelFormat::NV12: {
      // Rebuild planar Y, U, V in a reused buffer: NV12's chroma is interleaved, and
      // limited-range samples are expanded on the way.
      const std::size_t plane = static_cast<std::size_t>(cw) * ch;
      planes_.resize(static_cast<std::size_t>(f.width) * f.height + 2 * plane);
      std::uint8_t* yp = planes_.data();
      std::uint8_t* up = yp + static_cast<std::size_t>(f.width) * f.height;
      std::uint8_t* vp = up + plane;
      for (int r = 0; r < f.height; ++r) {
        const std::uint8_t* src = y + static_cast<std::ptrdiff_t>(r) * f.stride;
        std::uint8_t* dst = yp + static_cast<std::size_t>(r) * f.width;
        for (int c = 0; c < f.width; ++c) dst[c] = lumaLut_[src[c]];
      }
      const std::uint8_t* chroma = y + ySize;
      // Chroma rows as planeSizes lays them out: NV12's as long as luma's, I420's
      // half as long, rounded down.
      const int cs = f.format == PixelFormat::NV12 ? f.stride : f.stride / 2;
      for (int r = 0; r < ch; ++r) {
        std::uint8_t* u = up + static_cast<std::size_t>(r) * cw;
        std::uint8_t* v = vp + static_cast<std::size_t>(r) * cw;
        if (f.format == PixelFormat::NV12) {
          const std::uint8_t* src = chroma + static_cast<std::ptrdiff_t>(r) * cs;
          for (int c = 0; c < cw; ++c) {
            u[c] = chromaLut_[src[2 * c]];
            v[c] = chromaLut_[src[2 * c + 1]];
          }
        } else {
          const std::uint8_t* su = chroma + static_cast<std::ptrdiff_t>(r) * cs;
          const std::uint8_t* sv =
              chroma + static_cast<std::ptrdiff_t>(cs) * ch + static_cast<std::ptrdiff_t>(r) * cs;
          for (int c = 0; c < cw; ++c) {
            u[c] = chromaLut_[su[c]];
            v[c] = chromaLut_[sv[c]];
          }
        }
      }
      const std::uint8_t* planes[3] = {yp, up, vp};
      const int strides[3] = {f.width, cw, cw};
      return compressPlanes(planes, strides, f.width, f.height, TJSAMP_420, quality, out, error);
    }
    case PixelFormat::YUYV: {
      // Packed 4:2:2 -> Y, U, V planes (4:2:2 kept: no chroma is thrown away).
      const int yw = 2 * cw;  // even luma width covering the image
      const std::size_t yPlane = static_cast<std::size_t>(yw) * f.height;
      const std::size_t cPlane = static_cast<std::size_t>(cw) * f.height;
      planes_.resize(yPlane + 2 * cPlane);
      std::uint8_t* yp = planes_.data();
      std::uint8_t* up = yp + yPlane;
      std::uint8_t* vp = up + cPlane;
      for (int r = 0; r < f.height; ++r) {
        const std::uint8_t* src = f.data + static_cast<std::ptrdiff_t>(r) * f.stride;
        std::uint8_t* yr = yp + static_cast<std::size_t>(r) * yw;
        std::uint8_t* ur = up + static_cast<std::size_t>(r) * cw;
        std::uint8_t* vr = vp + static_cast<std::size_t>(r) * cw;
        for (int c = 0; c < cw; ++c) {
          yr[2 * c] = lumaLut_[src[4 * c]];
          ur[c] = chromaLut_[src[4 * c + 1]];
          yr[2 * c + 1] = lumaLut_[src[4 * c + 2]];
          vr[c] = chromaLut_[src[4 * c + 3]];
        }
      }
      const std::uint8_t* planes[3] = {yp, up, vp};
      const int strides[3] = {yw, cw, cw};
      return compressPlanes(planes, strides, f.width, f.height, TJSAMP_422, quality, out, error);
    }
  }
  error = "unsupported pixel format";
  return false;
}

bool JpegEncoder::encode(const cv::Mat& bgr, int quality, std::vector<std::uint8_t>& out,
                         std::string& error) {
  if (bgr.type() != CV_8UC3 && bgr.type() != CV_8UC1) {
    error = "expected an 8-bit BGR or grey image";
    return false;
  }
  const Frame f = bgr.channels() == 3 ? Frame::ofBgr(bgr, 0, 0) : Frame::ofGray(bgr, 0, 0);
  return encode(f, quality, out, error);
}

}  // namespace keyframed
