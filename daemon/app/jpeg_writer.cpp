#include "app/jpeg_writer.h"

#include <cerrno>
#include <cstdio>
#include <cstring>

#include <opencv2/imgcodecs.hpp>

namespace keyframed {

JpegWriter::JpegWriter(std::string dir, int quality)
    : dir_(std::move(dir)), quality_(quality), params_{cv::IMWRITE_JPEG_QUALITY, quality} {}

std::string JpegWriter::fileName(std::int64_t frameIndex) {
  char name[32];
  std::snprintf(name, sizeof name, "%06lld.jpg", static_cast<long long>(frameIndex));
  return name;
}

bool JpegWriter::write(const cv::Mat& bgr, std::int64_t frameIndex, std::string& error) {
  if (!cv::imencode(".jpg", bgr, buffer_, params_)) {
    error = "JPEG encoding failed for frame " + std::to_string(frameIndex);
    return false;
  }
  const std::string path = dir_ + "/" + fileName(frameIndex);
  const std::string tmp = path + ".tmp";
  std::FILE* f = std::fopen(tmp.c_str(), "wb");
  if (f == nullptr) {
    error = "cannot create " + tmp + ": " + std::strerror(errno);
    return false;
  }
  const bool wrote = std::fwrite(buffer_.data(), 1, buffer_.size(), f) == buffer_.size();
  const int writeErr = errno;
  const bool closed = std::fclose(f) == 0;
  if (!wrote || !closed) {
    error = "cannot write " + tmp + ": " + std::strerror(wrote ? errno : writeErr);
    std::remove(tmp.c_str());
    return false;
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) {
    error = "cannot rename " + tmp + ": " + std::strerror(errno);
    std::remove(tmp.c_str());
    return false;
  }
  return true;
}

}  // namespace keyframed
