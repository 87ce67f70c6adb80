#include "app/preview_encoder.h"

#include <string>
#include <utility>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace keyframed {

cv::Size PreviewEncoder::sizeFor(int width, int height) const {
  if (width_ <= 0 || width <= 0) return {0, 0};
  const int w = width_ & ~1;
  const int h = static_cast<int>(static_cast<std::int64_t>(height) * w / width) & ~1;
  return {w, h > 0 ? h : 2};
}

// Halve with INTER_AREA while that stays above the target, then one bilinear step:
// 1080p -> 640 costs a fraction of a direct INTER_AREA (the analysis image is made
// the same way; docs/performance.md).
void PreviewEncoder::Scaler::scale(const cv::Mat& from, cv::Mat& to) {
  const cv::Mat* src = &from;
  while (src->cols / 2 >= to.cols && src->rows / 2 >= to.rows) {
    cv::resize(*src, half, cv::Size(src->cols / 2, src->rows / 2), 0, 0, cv::INTER_AREA);
    std::swap(half, spare);
    src = &spare;
  }
  cv::resize(*src, to, to.size(), 0, 0, cv::INTER_LINEAR);
}

bool PreviewEncoder::encodeYuv(const Frame& f, std::vector<std::uint8_t>& out) {
  const cv::Size size = sizeFor(f.width, f.height);
  const int cw = size.width / 2, ch = size.height / 2;
  const std::size_t lumaBytes = static_cast<std::size_t>(size.area());
  const std::size_t chromaBytes = static_cast<std::size_t>(cw) * static_cast<std::size_t>(ch);
  planes_.resize(lumaBytes + 2 * chromaBytes);
  std::uint8_t* y = planes_.data();
  std::uint8_t* u = y + lumaBytes;
  std::uint8_t* v = u + chromaBytes;
  cv::Mat yOut(size, CV_8UC1, y), uOut(ch, cw, CV_8UC1, u), vOut(ch, cw, CV_8UC1, v);

  auto* data = const_cast<std::uint8_t*>(f.data);
  const auto stride = static_cast<std::size_t>(f.stride);
  luma_.scale(cv::Mat(f.height, f.width, CV_8UC1, data, stride), yOut);
  std::uint8_t* chroma = data + stride * static_cast<std::size_t>(f.height);
  const int srcCw = (f.width + 1) / 2, srcCh = (f.height + 1) / 2;
  if (f.format == PixelFormat::NV12) {
    uv_.create(ch, cw, CV_8UC2);
    colour_.scale(cv::Mat(srcCh, srcCw, CV_8UC2, chroma, stride), uv_);
    cv::Mat split[] = {uOut, vOut};
    cv::split(uv_, split);
  } else {
    const std::size_t cstride = (stride + 1) / 2;
    chromaU_.scale(cv::Mat(srcCh, srcCw, CV_8UC1, chroma, cstride), uOut);
    chromaV_.scale(
        cv::Mat(srcCh, srcCw, CV_8UC1, chroma + cstride * static_cast<std::size_t>(srcCh), cstride),
        vOut);
  }
  Frame small;
  small.format = PixelFormat::YUV420;
  small.data = y;
  small.width = size.width;
  small.height = size.height;
  small.stride = size.width;
  std::string error;
  return encoder_.encode(small, kQuality, out, error);
}

bool PreviewEncoder::encode(const Frame& f, std::vector<std::uint8_t>& out) {
  if (width_ <= 0 || f.data == nullptr || f.width < 2 || f.height < 2) return false;
  const bool full = width_ >= f.width;
  format_ = full ? "png" : "jpeg";
  if (!full && (f.format == PixelFormat::YUV420 || f.format == PixelFormat::NV12)) {
    return encodeYuv(f, out);
  }
  auto* data = const_cast<std::uint8_t*>(f.data);
  const auto stride = static_cast<std::size_t>(f.stride);
  const int rows420 = f.height * 3 / 2;  // as OpenCV's 4:2:0 conversions take them
  switch (f.format) {
    case PixelFormat::BGR24: bgr_ = cv::Mat(f.height, f.width, CV_8UC3, data, stride); break;
    case PixelFormat::Gray8:
      cv::cvtColor(cv::Mat(f.height, f.width, CV_8UC1, data, stride), bgr_, cv::COLOR_GRAY2BGR);
      break;
    case PixelFormat::NV12:
      cv::cvtColor(cv::Mat(rows420, f.width, CV_8UC1, data, stride), bgr_, cv::COLOR_YUV2BGR_NV12);
      break;
    case PixelFormat::YUV420:
      cv::cvtColor(cv::Mat(rows420, f.width, CV_8UC1, data, stride), bgr_, cv::COLOR_YUV2BGR_I420);
      break;
    case PixelFormat::YUYV:
      cv::cvtColor(cv::Mat(f.height, f.width, CV_8UC2, data, stride), bgr_, cv::COLOR_YUV2BGR_YUYV);
      break;
  }
  if (full) {
    // Lossless, so that a replay reproduces the live decisions exactly.
    return cv::imencode(".png", bgr_, out, {cv::IMWRITE_PNG_COMPRESSION, 1});
  }
  small_.create(sizeFor(f.width, f.height), CV_8UC3);
  colour_.scale(bgr_, small_);
  std::string error;
  return encoder_.encode(small_, kQuality, out, error);
}

}  // namespace keyframed
