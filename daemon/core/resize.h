#pragma once

#include <cstdint>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "core/frame.h"

namespace keyframed {

// 2x2 box average into dst (floor(w/2) x floor(h/2)), rounded: exactly what
// cv::resize with INTER_AREA computes for a factor of 2. dst is (re)created
// only when its size changes.
void halveArea(GrayView src, cv::Mat& dst);

// Bilinear resize with cv::INTER_LINEAR's sample positions (pixel centres
// aligned, edges clamped), within one grey level of it. The index and weight
// tables are built once per source/destination size, so repeated calls at one
// size allocate nothing.
class BilinearResizer {
 public:
  void resize(GrayView src, cv::Size size, cv::Mat& dst);

 private:
  void prepare(cv::Size src, cv::Size dst);

  cv::Size src_;
  cv::Size dst_;
  std::vector<std::int32_t> x0_;   // left source column of each destination column
  std::vector<std::uint16_t> wx_;  // weight of the column right of it, out of 2048
  std::vector<std::int32_t> y0_;
  std::vector<std::int32_t> y1_;
  std::vector<std::uint16_t> wy_;    // weight of y1_, out of 256
  std::vector<std::uint16_t> rowV_;  // one source-width row blended vertically, x256
  bool threeHalves_ = false;         // a 3:2 width ratio with a fixed pattern
  std::uint16_t evenW_[2] = {};      // its weights for even and odd outputs
  std::uint16_t oddW_[2] = {};
};

// Downscaling to an analysis width: halve (2x2 average) while the result is
// still at least the target width, then one bilinear step to the exact size.
// 1920 -> 640: one halving and a 1.5x bilinear step. The quality of a box
// filter where it matters most, at a fraction of INTER_AREA's cost for
// non-integer factors; no allocation once the sizes are known.
class DownScaler {
 public:
  // `src` scaled to width x height, or `src` itself when it is no wider than
  // `width`. The view stays valid until the next call.
  GrayView scale(GrayView src, int width, int height);
  // `src` at `width` (0: as it is), the height in proportion (at least a row).
  GrayView scaleToWidth(GrayView src, int width);

 private:
  std::vector<cv::Mat> halves_;
  BilinearResizer bilinear_;
  cv::Mat out_;
};

}  // namespace keyframed
