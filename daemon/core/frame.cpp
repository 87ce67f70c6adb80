#include "core/frame.h"

#include <opencv2/imgproc.hpp>

namespace keyframed {

cv::Mat GrayView::mat() const {
  // cv::Mat has no const header; callers only read through it.
  return cv::Mat(height, width, CV_8UC1, const_cast<std::uint8_t*>(data),
                 static_cast<size_t>(stride));
}

GrayView GrayView::of(const cv::Mat& gray) {
  CV_Assert(gray.type() == CV_8UC1);
  return GrayView{gray.data, gray.cols, gray.rows, static_cast<int>(gray.step[0])};
}

Frame Frame::ofBgr(const cv::Mat& bgr, std::int64_t index, std::int64_t timestampNs) {
  CV_Assert(bgr.type() == CV_8UC3);
  return Frame{PixelFormat::BGR24, bgr.data, bgr.cols, bgr.rows, static_cast<int>(bgr.step[0]),
               timestampNs,        index};
}

Frame Frame::ofGray(const cv::Mat& gray, std::int64_t index, std::int64_t timestampNs) {
  CV_Assert(gray.type() == CV_8UC1);
  return Frame{PixelFormat::Gray8, gray.data, gray.cols, gray.rows, static_cast<int>(gray.step[0]),
               timestampNs,        index};
}

GrayView LumaExtractor::luma(const Frame& frame) {
  switch (frame.format) {
    case PixelFormat::Gray8:
    case PixelFormat::NV12:
    case PixelFormat::YUV420:
      // The Y plane comes first and is a plain 8-bit image: borrow it.
      return GrayView{frame.data, frame.width, frame.height, frame.stride};
    case PixelFormat::BGR24: {
      const cv::Mat bgr(frame.height, frame.width, CV_8UC3, const_cast<std::uint8_t*>(frame.data),
                        static_cast<size_t>(frame.stride));
      cv::cvtColor(bgr, buffer_, cv::COLOR_BGR2GRAY);
      return GrayView::of(buffer_);
    }
    case PixelFormat::YUYV: {
      const cv::Mat yuyv(frame.height, frame.width, CV_8UC2, const_cast<std::uint8_t*>(frame.data),
                         static_cast<size_t>(frame.stride));
      cv::extractChannel(yuyv, buffer_, 0);
      return GrayView::of(buffer_);
    }
  }
  return {};
}

}  // namespace keyframed
