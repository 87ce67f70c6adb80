#include "app/preview_encoder.h"

#include <algorithm>
#include <cstring>
#include <string>
#include <utility>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace keyframed {

namespace {
// `rows` x `cols` of `from` into a tight plane at `to`; false when `from` is smaller.
bool copyPlane(GrayView from, int cols, int rows, std::uint8_t* to) {
  if (from.width < cols || from.height < rows) return false;
  for (int r = 0; r < rows; ++r)
    std::memcpy(to + static_cast<std::size_t>(r) * static_cast<std::size_t>(cols), from.row(r),
                static_cast<std::size_t>(cols));
  return true;
}
// Scaled plane by plane (scaleYuv), never converted to colour at full size.
bool planar(PixelFormat format) {
  return format == PixelFormat::YUV420 || format == PixelFormat::NV12 ||
         format == PixelFormat::YUYV;
}
}  // namespace

PreviewEncoder::PreviewEncoder(int width, Format format, double fps)
    : width_(width),
      mode_(format),
      format_(format == Format::H264 ? "h264" : "jpeg"),
      h264_({.keyframeIntervalNs = 1'000'000'000, .crf = 23, .fps = fps > 0 ? fps : 30}) {}

cv::Size PreviewEncoder::sizeFor(int width, int height) const {
  if (width_ <= 0 || width <= 0) return {0, 0};
  // At least 2 wide (a YUV picture's chroma is half of it): halving stops there.
  const int w = std::max(2, std::min(width_, width) & ~1);
  const int h = static_cast<int>(static_cast<std::int64_t>(height) * w / width) & ~1;
  return {w, h > 0 ? h : 2};
}

Frame PreviewEncoder::planesFrame() const {
  Frame small;
  small.format = PixelFormat::YUV420;
  small.data = picture_;
  small.width = planesSize_.width;
  small.height = planesSize_.height;
  small.stride = planesSize_.width;
  return small;
}

bool PreviewEncoder::scaleYuv(const Frame& f) {
  const cv::Size size = sizeFor(f.width, f.height);
  const int cw = size.width / 2, ch = size.height / 2;
  const std::size_t lumaBytes = static_cast<std::size_t>(size.area());
  const std::size_t chromaBytes = static_cast<std::size_t>(cw) * static_cast<std::size_t>(ch);
  planes_.resize(lumaBytes + 2 * chromaBytes);
  planesSize_ = size;
  picture_ = planes_.data();
  std::uint8_t* y = planes_.data();

  const std::size_t stride = static_cast<std::size_t>(f.stride);
  const std::uint8_t* chroma = f.data + stride * static_cast<std::size_t>(f.height);
  const int srcCw = (f.width + 1) / 2, srcCh = (f.height + 1) / 2;
  GrayView luma{f.data, f.width, f.height, f.stride};
  GrayView u, v;
  if (f.format == PixelFormat::YUYV) {
    // Y0 U Y1 V: luma de-interleaved, chroma (4:2:2) from every other row as 4:2:0.
    yuyvLuma_.create(f.height, f.width, CV_8UC1);
    chromaUFull_.create(srcCh, srcCw, CV_8UC1);
    chromaVFull_.create(srcCh, srcCw, CV_8UC1);
    for (int r = 0; r < f.height; ++r) {
      const std::uint8_t* in = f.data + stride * static_cast<std::size_t>(r);
      std::uint8_t* lumaRow = yuyvLuma_.ptr(r);
      for (int c = 0; c < f.width; ++c) lumaRow[c] = in[2 * c];
      if (r % 2 != 0) continue;
      std::uint8_t* cu = chromaUFull_.ptr(r / 2);
      std::uint8_t* cv = chromaVFull_.ptr(r / 2);
      for (int c = 0; c < f.width / 2; ++c) {
        cu[c] = in[4 * c + 1];
        cv[c] = in[4 * c + 3];
      }
      if (f.width % 2 != 0) {  // an odd last column has no chroma of its own
        cu[srcCw - 1] = srcCw > 1 ? cu[srcCw - 2] : 128;
        cv[srcCw - 1] = srcCw > 1 ? cv[srcCw - 2] : 128;
      }
    }
    luma = GrayView::of(yuyvLuma_);
    u = GrayView::of(chromaUFull_);
    v = GrayView::of(chromaVFull_);
  } else if (f.format == PixelFormat::NV12) {
    chromaUFull_.create(srcCh, srcCw, CV_8UC1);
    chromaVFull_.create(srcCh, srcCw, CV_8UC1);
    cv::Mat parts[] = {chromaUFull_, chromaVFull_};
    cv::split(cv::Mat(srcCh, srcCw, CV_8UC2, const_cast<std::uint8_t*>(chroma), stride), parts);
    u = GrayView::of(chromaUFull_);
    v = GrayView::of(chromaVFull_);
  } else {
    // As the frame's planes are laid out and copied (planeSizes, frameBytes): rows of
    // half the luma stride, rounded down, and no wider than that.
    const int cstride = f.stride / 2;
    const int cols = std::min(srcCw, cstride);
    u = GrayView{chroma, cols, srcCh, cstride};
    v = GrayView{chroma + static_cast<std::size_t>(cstride) * static_cast<std::size_t>(srcCh), cols,
                 srcCh, cstride};
  }
  return copyPlane(luma_.scale(luma, size.width, size.height), size.width, size.height, y) &&
         copyPlane(chromaU_.scale(u, cw, ch), cw, ch, y + lumaBytes) &&
         copyPlane(chromaV_.scale(v, cw, ch), cw, ch, y + lumaBytes + chromaBytes);
}

void PreviewEncoder::scaleBgr(cv::Size size) {
  if (size == bgr_.size()) {
    small_ = bgr_;
    return;
  }
  // Halve with INTER_AREA while that stays above the target, then one bilinear step,
  // as DownScaler does for one plane.
  const cv::Mat* from = &bgr_;
  while (from->cols / 2 >= size.width) {
    cv::resize(*from, half_, cv::Size(from->cols / 2, from->rows / 2), 0, 0, cv::INTER_AREA);
    std::swap(half_, halfSpare_);
    from = &halfSpare_;
  }
  cv::resize(*from, small_, size, 0, 0, cv::INTER_LINEAR);
}

namespace {
// The whole frame in colour (BGR), a view where it already is.
void toBgr(const Frame& f, cv::Mat& bgr) {
  auto* data = const_cast<std::uint8_t*>(f.data);
  const auto stride = static_cast<std::size_t>(f.stride);
  const int rows420 = f.height * 3 / 2;  // as OpenCV's 4:2:0 conversions take them
  switch (f.format) {
    case PixelFormat::BGR24: bgr = cv::Mat(f.height, f.width, CV_8UC3, data, stride); break;
    case PixelFormat::Gray8:
      cv::cvtColor(cv::Mat(f.height, f.width, CV_8UC1, data, stride), bgr, cv::COLOR_GRAY2BGR);
      break;
    case PixelFormat::NV12:
      cv::cvtColor(cv::Mat(rows420, f.width, CV_8UC1, data, stride), bgr, cv::COLOR_YUV2BGR_NV12);
      break;
    case PixelFormat::YUV420:
      cv::cvtColor(cv::Mat(rows420, f.width, CV_8UC1, data, stride), bgr, cv::COLOR_YUV2BGR_I420);
      break;
    case PixelFormat::YUYV:
      cv::cvtColor(cv::Mat(f.height, f.width, CV_8UC2, data, stride), bgr, cv::COLOR_YUV2BGR_YUYV);
      break;
  }
}
}  // namespace

bool PreviewEncoder::scaleToI420(const Frame& f) {
  if (planar(f.format)) return scaleYuv(f);
  toBgr(f, bgr_);
  const cv::Size size = sizeFor(f.width, f.height);
  scaleBgr(size);
  cv::cvtColor(small_, i420_, cv::COLOR_BGR2YUV_I420);
  picture_ = i420_.data;  // continuous: cvtColor made it
  planesSize_ = size;
  return true;
}

bool PreviewEncoder::encode(const Frame& f, std::vector<std::uint8_t>& out) {
  error_.clear();
  if (width_ <= 0 || f.data == nullptr || f.width < 2 || f.height < 2) return false;
  if (mode_ == Format::H264) {
    if (!scaleToI420(f)) {
      error_ = "the frame cannot be scaled";
      return false;
    }
    return h264_.encode({picture_, planesSize_.width, planesSize_.height}, f.timestampNs, out,
                        error_);
  }
  const bool full = width_ >= f.width;
  format_ = full ? "png" : "jpeg";
  if (!full && planar(f.format)) {
    if (!scaleYuv(f)) {
      error_ = "the frame cannot be scaled";
      return false;
    }
    return encoder_.encode(planesFrame(), kQuality, out, error_);
  }
  toBgr(f, bgr_);
  if (full) {
    // Lossless, so that a replay reproduces the live decisions exactly.
    return cv::imencode(".png", bgr_, out, {cv::IMWRITE_PNG_COMPRESSION, 1});
  }
  scaleBgr(sizeFor(f.width, f.height));
  return encoder_.encode(small_, kQuality, out, error_);
}

bool PreviewEncoder::still(const Frame& f, std::vector<std::uint8_t>& out) {
  error_.clear();
  if (width_ <= 0 || f.data == nullptr || f.width < 2 || f.height < 2) return false;
  if (!scaleToI420(f)) {
    error_ = "the frame cannot be scaled";
    return false;
  }
  return encoder_.encode(planesFrame(), kQuality, out, error_);
}

bool PreviewEncoder::lastAsJpeg(std::vector<std::uint8_t>& out) {
  if (mode_ != Format::H264 || picture_ == nullptr) return false;
  return encoder_.encode(planesFrame(), kQuality, out, error_);
}

}  // namespace keyframed
