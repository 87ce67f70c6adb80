#include "output/mcap_replay.h"

#include <cstring>
#include <fstream>
#include <optional>
#include <span>

#include <opencv2/core/mat.hpp>
#include <opencv2/imgcodecs.hpp>

#ifdef KEYFRAMED_HAVE_IO
#include "output/io_ffi.h"
#endif

namespace keyframed {

namespace {

// The bytes of length-delimited field `field` of a protobuf message (the first
// occurrence), or nothing. Enough for foxglove.CompressedImage.data (2) and
// keyframed.MavlinkPacket.packet (5).
std::optional<std::span<const std::uint8_t>> bytesField(std::span<const std::uint8_t> msg,
                                                        std::uint32_t field) {
  std::size_t i = 0;
  auto varint = [&](std::uint64_t& v) {
    v = 0;
    for (int shift = 0; i < msg.size() && shift < 64; shift += 7) {
      const std::uint8_t b = msg[i++];
      v |= static_cast<std::uint64_t>(b & 0x7F) << shift;
      if ((b & 0x80) == 0) return true;
    }
    return false;
  };
  while (i < msg.size()) {
    std::uint64_t key = 0;
    if (!varint(key)) return std::nullopt;
    const auto wire = static_cast<int>(key & 7);
    std::uint64_t v = 0;
    switch (wire) {
      case 0:
        if (!varint(v)) return std::nullopt;
        break;
      case 1: i += 8; break;
      case 5: i += 4; break;
      case 2: {
        if (!varint(v) || v > msg.size() - i) return std::nullopt;
        if ((key >> 3) == field) return msg.subspan(i, static_cast<std::size_t>(v));
        i += static_cast<std::size_t>(v);
        break;
      }
      default: return std::nullopt;
    }
  }
  return std::nullopt;
}

}  // namespace

bool isMcapFile(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  char magic[8] = {};
  f.read(magic, sizeof magic);
  return f && std::memcmp(magic, "\x89MCAP0\r\n", 8) == 0;
}

struct McapReplaySource::Impl {
  struct Image {
    std::int64_t timeNs;
    std::vector<std::uint8_t> jpeg;
  };
  std::vector<Image> images;
  std::size_t next = 0;
  cv::Mat bgr;
};

McapReplaySource::~McapReplaySource() = default;

std::unique_ptr<McapReplaySource> McapReplaySource::open(const std::string& path,
                                                         std::string& error) {
#ifdef KEYFRAMED_HAVE_IO
  const char* topics[] = {"/camera/preview", "/mavlink/raw"};
  char err[512] = {};
  kfio_mcap_reader* r = kfio_mcap_reader_open(path.c_str(), topics, 2, err, sizeof err);
  if (r == nullptr) {
    error = err;
    return nullptr;
  }
  std::unique_ptr<McapReplaySource> s(new McapReplaySource());
  s->impl_ = std::make_unique<Impl>();
  std::uint32_t topic = 0;
  std::uint64_t time = 0;
  const std::uint8_t* data = nullptr;
  std::size_t len = 0;
  while (kfio_mcap_reader_next(r, &topic, &time, &data, &len) == 1) {
    const std::span<const std::uint8_t> msg(data, len);
    const auto field = bytesField(msg, topic == 0 ? 2 : 5);
    if (!field) continue;
    if (topic == 0) {
      s->impl_->images.push_back({static_cast<std::int64_t>(time), {field->begin(), field->end()}});
    } else {
      s->mavlink_.push_back({static_cast<std::int64_t>(time), {field->begin(), field->end()}});
    }
  }
  s->truncated_ = kfio_mcap_reader_truncated(r) != 0;
  kfio_mcap_reader_close(r);
  auto& images = s->impl_->images;
  if (images.empty()) {
    error = path +
            ": no preview stream (/camera/preview) to replay: record with output.preview_width > 0";
    return nullptr;
  }
  const cv::Mat first = cv::imdecode(images.front().jpeg, cv::IMREAD_COLOR);
  if (first.empty()) {
    error = path + ": the first preview frame is not a JPEG";
    return nullptr;
  }
  s->info_.width = first.cols;
  s->info_.height = first.rows;
  s->info_.frameCount = static_cast<std::int64_t>(images.size());
  const double span = static_cast<double>(images.back().timeNs - images.front().timeNs) / 1e9;
  s->info_.fps = span > 0 ? static_cast<double>(images.size() - 1) / span : 0.0;
  s->info_.description = "mcap:" + path;
  return s;
#else
  error = path + ": this keyframed was built without MCAP support (KEYFRAMED_WITH_IO=OFF)";
  return nullptr;
#endif
}

ReadStatus McapReplaySource::next(Frame& frame, std::string& error) {
  auto& images = impl_->images;
  if (impl_->next >= images.size()) return ReadStatus::End;
  const auto& img = images[impl_->next++];
  impl_->bgr = cv::imdecode(img.jpeg, cv::IMREAD_COLOR);
  if (impl_->bgr.empty() || impl_->bgr.cols != info_.width || impl_->bgr.rows != info_.height) {
    error = "preview frame " + std::to_string(index_) + " cannot be decoded";
    return ReadStatus::Error;
  }
  frame = Frame::ofBgr(impl_->bgr, index_++, img.timeNs);
  return ReadStatus::Frame;
}

}  // namespace keyframed
