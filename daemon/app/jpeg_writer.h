#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>

namespace keyframed {

// Writes keyframe JPEGs into a directory, atomically (temp file + rename), so a
// reader never sees half a file.
class JpegWriter {
 public:
  JpegWriter(std::string dir, int quality);
  // Returns false with a one-line error (disk full, permissions).
  bool write(const cv::Mat& bgr, std::int64_t frameIndex, std::string& error);
  [[nodiscard]] static std::string fileName(std::int64_t frameIndex);

 private:
  std::string dir_;
  int quality_;
  std::vector<int> params_;
  std::vector<std::uint8_t> buffer_;
};

}  // namespace keyframed
