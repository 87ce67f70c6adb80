#include "capture/file_source.h"

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <system_error>

#include <opencv2/imgproc.hpp>

namespace keyframed {

namespace {

// The signatures of the still-image formats FFmpeg opens as a one-frame video:
// JPEG, PNG, BMP, TIFF (both byte orders), WebP.
bool isStillImage(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  unsigned char m[12] = {};
  if (!in.read(reinterpret_cast<char*>(m), sizeof m)) return false;
  const auto is = [&m](std::initializer_list<unsigned char> sig, std::size_t at = 0) {
    std::size_t i = at;
    for (unsigned char c : sig)
      if (m[i++] != c) return false;
    return true;
  };
  return is({0xFF, 0xD8, 0xFF}) || is({0x89, 'P', 'N', 'G'}) || is({'B', 'M'}) ||
         is({'I', 'I', 42, 0}) || is({'M', 'M', 0, 42}) ||
         (is({'R', 'I', 'F', 'F'}) && is({'W', 'E', 'B', 'P'}, 8));
}

// An MPEG transport stream's packet size: 188 bytes (plain TS), 192 (M2TS, a 4-byte
// time code first), or 0 when the file does not start as one (every packet starts
// with the sync byte 0x47). A TS has no index to compare with, but a file cut at a
// random byte almost always ends part-way through a packet.
std::size_t transportPacketSize(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  unsigned char b[192 * 5] = {};
  if (!in.read(reinterpret_cast<char*>(b), sizeof b)) return 0;
  for (const std::size_t size : {std::size_t{188}, std::size_t{192}}) {
    const std::size_t sync = size - 188;
    bool all = true;
    for (std::size_t i = 0; i < 5 && all; ++i) all = b[i * size + sync] == 0x47;
    if (all) return size;
  }
  return 0;
}

// FNV-1a over every 509th byte (a prime: not in step with rows or channels), about
// 12,000 of a 1080p frame's 6 MB: the same value twice running is the same picture
// (a camera's noise, or a video's, changes some of them every frame).
std::uint64_t sampleHash(const cv::Mat& m) {
  std::uint64_t h = 1469598103934665603ULL;
  const std::size_t rowBytes = m.cols * m.elemSize();
  std::size_t k = 0;
  for (int y = 0; y < m.rows; ++y) {
    const std::uint8_t* row = m.ptr<std::uint8_t>(y);
    for (; k < rowBytes; k += 509) h = (h ^ row[k]) * 1099511628211ULL;
    k -= rowBytes;
  }
  return h;
}

}  // namespace

std::unique_ptr<FileSource> FileSource::open(const std::string& path, std::string& error) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) {
    error = "no such file: " + path;
    return nullptr;
  }
  if (std::filesystem::is_directory(path, ec)) {
    error = "is a directory, not a video: " + path;
    return nullptr;
  }
  // FFmpeg's own log lines would interleave with ours; errors are reported once
  // below. A user-set OPENCV_FFMPEG_LOGLEVEL wins.
  setenv("OPENCV_FFMPEG_LOGLEVEL", "-8", 0);
  std::unique_ptr<FileSource> src(new FileSource());
  src->path_ = path;
  if (!src->capture_.open(path, cv::CAP_FFMPEG) || !src->capture_.isOpened()) {
    error = "not a readable video: " + path;
    return nullptr;
  }
  // Probe: a file that opens but yields no picture is not a video either.
  if (!src->capture_.read(src->bgr_) || src->bgr_.empty() || src->bgr_.type() != CV_8UC3) {
    error = "not a readable video (no decodable frame): " + path;
    return nullptr;
  }
  src->primed_ = true;
  SourceInfo& info = src->info_;
  info.width = src->bgr_.cols;
  info.height = src->bgr_.rows;
  info.fps = src->capture_.get(cv::CAP_PROP_FPS);
  const double count = src->capture_.get(cv::CAP_PROP_FRAME_COUNT);
  info.frameCount = count > 0 && std::isfinite(count) ? static_cast<std::int64_t>(count) : -1;
  // FFmpeg's frame count is the duration times the frame rate; a rate it got wrong
  // (an MPEG-TS's 90 kHz clock) makes the count wrong too, and a complete file would
  // look truncated.
  if (!(info.fps > 0.0 && info.fps < 1000.0)) {
    info.fps = 0.0;
    info.frameCount = -1;
  }
  info.description = "file:" + path;
  if (std::filesystem::is_regular_file(path, ec)) {
    src->packetSize_ = transportPacketSize(path);
    if (src->packetSize_ > 0) src->fileSize_ = std::filesystem::file_size(path, ec);
    if (ec) src->packetSize_ = 0;
  }
  // FFmpeg reads a photograph as a one-frame video; say what it is instead. Only a
  // regular file can be a photograph here: a FIFO or device carrying MJPEG starts
  // with a JPEG's signature too. A concatenated MJPEG file does as well, so the
  // verdict needs a second frame to be missing (read with a second decoder, so the
  // first keeps its position).
  if (info.frameCount <= 1 && std::filesystem::is_regular_file(path, ec) && isStillImage(path)) {
    cv::VideoCapture probe;
    cv::Mat scratch;
    const bool second = probe.open(path, cv::CAP_FFMPEG) && probe.read(scratch) &&
                        probe.read(scratch) && !scratch.empty();
    if (!second) {
      error = "a still image, not a video: " + path;
      return nullptr;
    }
  }
  return src;
}

bool FileSource::setOutputFormat(PixelFormat format, std::string& error) {
  if (format != PixelFormat::BGR24 && format != PixelFormat::YUV420 &&
      format != PixelFormat::NV12) {
    error = std::string("a video file is delivered as BGR24 (as decoded), YUV420 or NV12, not ") +
            toString(format);
    return false;
  }
  if (format != PixelFormat::BGR24 && (info_.width % 2 != 0 || info_.height % 2 != 0)) {
    error = std::string(toString(format)) + " needs an even width and height; the video is " +
            std::to_string(info_.width) + "x" + std::to_string(info_.height) + ": " + path_;
    return false;
  }
  output_ = format;
  return true;
}

void FileSource::toCameraFormat(Frame& frame) {
  const int w = info_.width, h = info_.height;
  cv::cvtColor(bgr_, yuv_, cv::COLOR_BGR2YUV_I420);
  frame.format = output_;
  frame.width = w;
  frame.height = h;
  frame.stride = w;
  frame.data = yuv_.data;
  if (output_ != PixelFormat::NV12) return;
  // I420 -> NV12 in place: the luma stays, the two chroma planes (copied aside)
  // are written back interleaved.
  const std::size_t luma = static_cast<std::size_t>(w) * static_cast<std::size_t>(h);
  const std::size_t quarter = luma / 4;
  std::uint8_t* uv = yuv_.data + luma;
  chroma_.assign(uv, uv + 2 * quarter);
  for (std::size_t i = 0; i < quarter; ++i) {
    uv[2 * i] = chroma_[i];
    uv[2 * i + 1] = chroma_[quarter + i];
  }
}

ReadStatus FileSource::next(Frame& frame, std::string& error) {
  if (!failure_.empty()) {
    error = failure_;
    return ReadStatus::Error;
  }
  if (!primed_) {
    bool ok = false;
    try {
      ok = capture_.read(bgr_);
    } catch (const cv::Exception& e) {
      error = "decoding failed at frame " + std::to_string(index_) + ": " + e.what();
      return ReadStatus::Error;
    }
    if (!ok || bgr_.empty()) {
      // Allow a little slack: container frame counts are estimates for some formats.
      if (info_.frameCount > 0 && index_ + 1 < info_.frameCount) {
        truncated_ = true;
        failure_ = "video ended early: read " + std::to_string(index_) + " of " +
                   std::to_string(info_.frameCount) + " frames (truncated or corrupt): " + path_;
        error = failure_;
        return ReadStatus::Error;
      }
      if (packetSize_ > 0 && fileSize_ % packetSize_ != 0) {
        truncated_ = true;
        failure_ = "video ended early: read " + std::to_string(index_) +
                   " frames, and the file stops part-way through a transport packet (" +
                   std::to_string(fileSize_) + " bytes is not a multiple of " +
                   std::to_string(packetSize_) + "; truncated): " + path_;
        error = failure_;
        return ReadStatus::Error;
      }
      return ReadStatus::End;
    }
    if (bgr_.cols != info_.width || bgr_.rows != info_.height || bgr_.type() != CV_8UC3) {
      failure_ = "frame size changed mid-stream at frame " + std::to_string(index_) + ": " + path_;
      error = failure_;
      return ReadStatus::Error;
    }
  }
  primed_ = false;
  const std::uint64_t sample = sampleHash(bgr_);
  if (index_ == 0 || sample != lastSample_) runFrom_ = index_;
  lastSample_ = sample;
  if (const std::int64_t run = index_ - runFrom_ + 1; run >= 30 && run > repeatedFrames_) {
    repeatedFrom_ = runFrom_;
    repeatedFrames_ = run;
  }
  double ms = capture_.get(cv::CAP_PROP_POS_MSEC);
  std::int64_t ts = 0;
  if (std::isfinite(ms) && ms >= 0.0 && !(index_ > 0 && ms == 0.0)) {
    ts = static_cast<std::int64_t>(std::llround(ms * 1e6));
  } else if (info_.fps > 0.0) {
    ts = static_cast<std::int64_t>(std::llround(static_cast<double>(index_) * 1e9 / info_.fps));
  }
  if (output_ == PixelFormat::BGR24) {
    frame = Frame::ofBgr(bgr_, index_, ts);
  } else {
    toCameraFormat(frame);
    frame.index = index_;
    frame.timestampNs = ts;
  }
  ++index_;
  return ReadStatus::Frame;
}

}  // namespace keyframed
