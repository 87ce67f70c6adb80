#include "output/mcap_replay.h"

#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <unordered_map>
#include <unordered_set>

#include <opencv2/core/base.hpp>
#include <opencv2/core/mat.hpp>
#include <opencv2/imgcodecs.hpp>

#include "output/h264.h"
#include "tagging/camera_model_toml.h"
#ifdef KEYFRAMED_HAVE_IO
#include "output/io.h"
#endif

namespace keyframed {

namespace {

// One field of a protobuf message: its number and wire type, and its value (varint,
// fixed32, fixed64) or its bytes (length-delimited).
struct ProtoField {
  std::uint64_t number = 0;
  int wire = 0;
  std::uint64_t value = 0;
  std::span<const std::uint8_t> bytes;
};

// Calls `f` for each field of `msg` in order until it returns false. False when the
// message is malformed (a truncated varint or field, an unknown wire type).
template <typename F>
bool forEachField(std::span<const std::uint8_t> msg, F&& f) {
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
  auto fixed = [&](std::size_t n, std::uint64_t& v) {
    if (msg.size() - i < n) return false;
    v = 0;
    std::memcpy(&v, msg.data() + i, n);  // little-endian, as protobuf and the hosts
    i += n;
    return true;
  };
  while (i < msg.size()) {
    std::uint64_t key = 0;
    if (!varint(key)) return false;
    ProtoField field;
    field.number = key >> 3;
    field.wire = static_cast<int>(key & 7);
    switch (field.wire) {
      case 0:
        if (!varint(field.value)) return false;
        break;
      case 1:
        if (!fixed(8, field.value)) return false;
        break;
      case 5:
        if (!fixed(4, field.value)) return false;
        break;
      case 2: {
        std::uint64_t n = 0;
        if (!varint(n) || n > msg.size() - i) return false;
        field.bytes = msg.subspan(i, static_cast<std::size_t>(n));
        i += static_cast<std::size_t>(n);
        break;
      }
      default: return false;
    }
    if (!f(field)) return true;
  }
  return true;
}

// The bytes of length-delimited field `number` (the first occurrence), or nothing.
// Enough for foxglove.CompressedImage.data (2) and keyframed.MavlinkPacket.packet (5).
[[maybe_unused]] std::optional<std::span<const std::uint8_t>> bytesField(
    std::span<const std::uint8_t> msg, std::uint64_t number) {
  std::optional<std::span<const std::uint8_t>> found;
  const bool ok = forEachField(msg, [&](const ProtoField& f) {
    if (f.wire == 2 && f.number == number) found = f.bytes;
    return !found;
  });
  return ok ? found : std::nullopt;
}

// Seconds a record's times stay under: 2096 in unix time, 126 years of uptime.
constexpr std::int64_t kMaxRecordSeconds = 4'000'000'000;
constexpr std::int64_t kMaxRecordNs = kMaxRecordSeconds * 1'000'000'000;

// A google.protobuf.Timestamp message (seconds 1, nanos 2) as ns.
[[maybe_unused]] std::optional<std::int64_t> timestampOf(std::span<const std::uint8_t> ts) {
  std::int64_t seconds = 0, nanos = 0;
  bool varints = true;
  const bool ok = forEachField(ts, [&](const ProtoField& f) {
    varints = f.wire == 0;
    if (f.number == 1) seconds = static_cast<std::int64_t>(f.value);
    if (f.number == 2) nanos = static_cast<std::int64_t>(f.value);
    return varints;
  });
  if (!ok || !varints) return std::nullopt;
  // As a damaged record may have them: no time before 1970 or after 2096 (nor a
  // CLOCK_MONOTONIC one that large), no nanoseconds outside a second.
  if (seconds < 0 || seconds >= kMaxRecordSeconds || nanos < 0 || nanos >= 1'000'000'000)
    return std::nullopt;
  return seconds * 1'000'000'000 + nanos;
}

// A message's time: its own timestamp field, else (none) its log time; nothing when
// that is not a time a record can hold (a damaged one), so that no arithmetic on it
// overflows and the message is skipped.
[[maybe_unused]] std::optional<std::int64_t> messageTime(std::span<const std::uint8_t> msg,
                                                         std::uint64_t logTimeNs) {
  if (const auto ts = bytesField(msg, 1)) return timestampOf(*ts);
  if (logTimeNs >= static_cast<std::uint64_t>(kMaxRecordNs)) return std::nullopt;
  return static_cast<std::int64_t>(logTimeNs);
}

// foxglove.CameraCalibration (width 2, height 3: fixed32; D 5, K 6: packed doubles)
// as a camera model; nothing when it lacks K or a size.
[[maybe_unused]] std::optional<CameraModel> calibrationOf(std::span<const std::uint8_t> msg) {
  CameraModel c;
  std::vector<double> k;
  auto doubles = [](std::span<const std::uint8_t> bytes, std::vector<double>& out) {
    for (std::size_t j = 0; j + 8 <= bytes.size(); j += 8) {
      double d = 0;
      std::memcpy(&d, bytes.data() + j, 8);
      out.push_back(d);
    }
  };
  const bool ok = forEachField(msg, [&](const ProtoField& f) {
    if (f.wire == 5 && f.number == 2) c.width = static_cast<int>(f.value);
    if (f.wire == 5 && f.number == 3) c.height = static_cast<int>(f.value);
    if (f.wire == 2 && f.number == 4) {
      const std::string model(f.bytes.begin(), f.bytes.end());
      if (model == "kannala_brandt") c.lens = CameraModel::Lens::Fisheye;
    }
    if (f.wire == 2 && f.number == 5) doubles(f.bytes, c.distortion);
    if (f.wire == 2 && f.number == 6) doubles(f.bytes, k);
    return true;
  });
  if (!ok) return std::nullopt;
  if (k.size() != 9 || c.width <= 0 || c.height <= 0) return std::nullopt;
  c.fx = k[0];
  c.cx = k[2];
  c.fy = k[4];
  c.cy = k[5];
  std::string error;  // held to what a calibration file is held to
  if (!c.calibrated() || !checkCameraModel("record", c, error)) return std::nullopt;
  return c;
}

}  // namespace

std::vector<std::string> mcapParts(const std::string& path) {
  std::vector<std::string> parts{path};
  const std::filesystem::path p(path);
  for (int i = 1; i < 100000; ++i) {
    char suffix[16];
    std::snprintf(suffix, sizeof suffix, "-%03d", i);
    const std::filesystem::path next =
        p.parent_path() / (p.stem().string() + suffix + p.extension().string());
    std::error_code ec;
    if (!std::filesystem::is_regular_file(next, ec)) break;
    parts.push_back(next.string());
  }
  return parts;
}

bool isMcapFile(const std::string& path) {
  // Only a regular file is read: a FIFO's open would wait for a writer.
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) return false;
  std::ifstream f(path, std::ios::binary);
  char magic[8] = {};
  f.read(magic, sizeof magic);
  return f && std::memcmp(magic, "\x89MCAP0\r\n", 8) == 0;
}

namespace {

// {"index":N,"timestamp_ns":T,...}: a decision row's frame index and time.
bool decisionIndex(std::span<const std::uint8_t> json, std::int64_t& index, std::int64_t& time) {
  const std::string head(reinterpret_cast<const char*>(json.data()),
                         std::min<std::size_t>(json.size(), 96));
  long long i = 0, t = 0;
  if (std::sscanf(head.c_str(), "{\"index\":%lld,\"timestamp_ns\":%lld", &i, &t) != 2) return false;
  // A damaged row (sscanf saturates what does not fit): not a frame of this flight.
  if (i < 0 || i > (1LL << 40) || t < 0 || t >= kMaxRecordNs) return false;
  index = i;
  time = t;
  return true;
}

// A string field of a /keyframed/settings message ("selection", "tagging",
// "camera"), unescaped as FlightOutputs::settings escapes it (jsonEscape).
std::optional<std::string> settingsField(std::span<const std::uint8_t> json,
                                         std::string_view name) {
  const std::string_view s(reinterpret_cast<const char*>(json.data()), json.size());
  // (appended, not concatenated: GCC 12's -Wrestrict misreads "x" + std::string)
  std::string key(1, '"');
  key.append(name).append("\":\"");
  const auto at = s.find(key);
  if (at == std::string::npos) return std::nullopt;
  std::string out;
  for (std::size_t i = at + key.size(); i < s.size(); ++i) {
    const char c = s[i];
    if (c == '"') return out;
    if (c != '\\') {
      out += c;
      continue;
    }
    if (++i >= s.size()) break;
    out += s[i] == 'n' ? '\n' : s[i];
  }
  return std::nullopt;  // unterminated
}

}  // namespace

struct McapReplaySource::Impl {
#ifdef KEYFRAMED_HAVE_IO
  std::unique_ptr<McapReader> images;  // the preview stream, read as frames are asked for
#endif
  std::unordered_map<std::int64_t, std::int64_t> indexAt;  // frame time -> live frame index
  std::unordered_set<std::int64_t> commandedAt;            // frame times kept live as "commanded"
  std::int64_t frames = 0;                                 // preview frames the first pass found
  std::vector<std::uint8_t> encoded;  // the last frame as recorded (a JPEG, PNG or H.264 packet)
  cv::Mat bgr;
  // An H.264 record (/camera/video): decoded from its first IDR picture on.
  bool video = false;
  bool started = false;
  H264Decoder decoder;
  std::vector<std::uint8_t> i420;
  [[nodiscard]] const char* topic() const {
    return video ? "/camera/video" : "/camera/preview";
  }
};

McapReplaySource::~McapReplaySource() = default;

std::span<const std::uint8_t> McapReplaySource::encoded() const {
  return impl_->encoded;
}

std::unique_ptr<McapReplaySource> McapReplaySource::open(const std::string& path,
                                                         std::string& error) {
#ifdef KEYFRAMED_HAVE_IO
  // Two passes, each one chunk at a time: the first keeps the MAVLink packets (small;
  // telemetry must be known ahead of the frames) and counts the preview frames; the
  // second streams the frames. Memory does not grow with the file. Times are the
  // messages' own (the run's clock, which the MAVLink link's TIMESYNC used too); the
  // log time of the first frame gives the record's offset to unix time.
  const std::vector<std::string> topics = {"/camera/preview",     "/mavlink/raw",
                                           "/camera/calibration", "/keyframed/decision",
                                           "/keyframed/settings", "/camera/video"};
  std::unique_ptr<McapReplaySource> s(new McapReplaySource());
  s->impl_ = std::make_unique<Impl>();
  s->parts_ = mcapParts(path);
  Impl& impl = *s->impl_;
  std::int64_t firstNs = 0;
  std::int64_t lastNs = 0;
  std::string lastSettings;
  for (std::size_t part = 0; part < s->parts_.size(); ++part) {
    const auto r = McapReader::open(s->parts_[part], topics, error);
    if (!r && part == 0) return nullptr;
    if (!r) {
      // A later part that does not open (empty: the disk filled, or a power cut came,
      // as it was made) ends the record like a cut one: the parts before it replay.
      s->truncated_ = true;
      std::fprintf(stderr,
                   "keyframed: %s: replaying the record up to that part, not the %zu part(s) "
                   "from it on\n",
                   error.c_str(), s->parts_.size() - part);
      error.clear();
      s->parts_.resize(part);
      break;
    }
    McapReader::Message m;
    while (r->next(m)) {
      const std::span<const std::uint8_t> msg = m.data;
      const std::uint32_t topic = m.topic;
      const std::uint64_t time = m.logTimeNs;
      if (topic == 2) {
        if (!s->calibration_) s->calibration_ = calibrationOf(msg);
        continue;
      }
      if (topic == 3) {
        std::int64_t index = 0, t = 0;
        if (decisionIndex(msg, index, t)) {
          impl.indexAt.emplace(t, index);
          const std::string_view row(reinterpret_cast<const char*>(msg.data()), msg.size());
          if (row.find("\"reason\":\"commanded\"") != std::string_view::npos)
            impl.commandedAt.insert(t);
        }
        continue;
      }
      if (topic == 4) {
        // Each part repeats the settings in force: a change is one that differs from
        // the message before it.
        if (const auto text = settingsField(msg, "selection")) {
          if (s->selection_.empty()) {
            s->selection_ = *text;
            // What the keyframes were tagged with, from the same message.
            s->tagging_ = settingsField(msg, "tagging").value_or("");
            if (const auto camera = settingsField(msg, "camera")) {
              CameraModel c;
              std::string e;
              if (cameraFromTomlText(*camera, "the record's camera", c, e))
                s->camera_ = std::move(c);
              else
                std::fprintf(stderr, "keyframed: warning: %s\n", e.c_str());
            }
          } else if (*text != lastSettings) {
            ++s->settingsChanges_;
          }
          lastSettings = *text;
        }
        continue;
      }
      // CompressedImage.data is field 2, CompressedVideo.data 3, MavlinkPacket's 5.
      const auto field = bytesField(msg, topic == 0 ? 2 : topic == 5 ? 3 : 5);
      // No data, or no time it can have been taken at: skipped (by next() too).
      if (!field || field->empty()) continue;
      const auto when = messageTime(msg, time);
      if (!when) continue;
      const std::int64_t t = *when;
      if (topic == 0 || topic == 5) {
        const bool video = topic == 5;
        if (impl.frames == 0) {
          // A video starts at an IDR picture (a record part may open mid-way between two).
          if (video && !h264HasIdr(*field)) continue;
          impl.video = video;
          impl.encoded.assign(field->begin(), field->end());
          firstNs = t;
          // The log time is unix time (a damaged one: taken as the frame's own).
          const bool logOk = time < static_cast<std::uint64_t>(kMaxRecordNs);
          s->unixOffsetNs_ = (logOk ? static_cast<std::int64_t>(time) : t) - t;
        } else if (video != impl.video) {
          continue;  // a record with both streams replays the one that starts first
        }
        lastNs = t;
        ++impl.frames;
      } else {
        s->mavlink_.push_back({t, {field->begin(), field->end()}});
      }
    }
    if (r->truncated()) {
      s->truncated_ = true;
      // A cut part ends the record: what follows would leave a hole in the flight.
      if (part + 1 < s->parts_.size()) {
        std::fprintf(stderr,
                     "keyframed: %s is cut short: replaying the record up to it, not the %zu "
                     "part(s) after it\n",
                     s->parts_[part].c_str(), s->parts_.size() - part - 1);
      }
      s->parts_.resize(part + 1);
      break;
    }
  }
  s->firstTimeNs_ = firstNs;
  if (impl.frames == 0 && s->truncated_) {
    error = path + ": corrupt or cut short before its first preview frame";
    return nullptr;
  }
  if (impl.frames == 0) {
    error = path +
            ": no preview stream (/camera/preview or /camera/video) to replay: a record "
            "of `keyframed run` with output.preview_width > 0 has one (`select --mcap` "
            "records no stream)";
    return nullptr;
  }
  cv::Mat first;
  if (impl.video) {
    H264Decoder probe;
    std::vector<std::uint8_t> picture;
    int w = 0, h = 0;
    std::string why;
    if (!probe.decode(impl.encoded, picture, w, h, why)) {
      error = path + ": the first video frame does not decode (" + why + ")";
      return nullptr;
    }
    first = cv::Mat(h, w, CV_8UC1);  // only its size is used
  } else {
    try {
      first = cv::imdecode(impl.encoded, cv::IMREAD_COLOR);
    } catch (const cv::Exception&) {
      first.release();  // as a picture that does not decode
    }
    if (first.empty()) {
      error = path + ": the first preview frame is not a JPEG";
      return nullptr;
    }
  }
  impl.images = McapReader::open(s->parts_[0], {impl.topic()}, error);
  if (!impl.images) return nullptr;
  s->info_.width = first.cols;
  s->info_.height = first.rows;
  s->info_.frameCount = impl.frames;
  const double span = static_cast<double>(lastNs - firstNs) / 1e9;
  s->info_.fps = span > 0 ? static_cast<double>(impl.frames - 1) / span : 0.0;
  s->info_.description = "mcap:" + path;
  return s;
#else
  error = path + ": this keyframed was built without MCAP support (KEYFRAMED_WITH_IO=OFF)";
  return nullptr;
#endif
}

ReadStatus McapReplaySource::next(Frame& frame, std::string& error) {
#ifdef KEYFRAMED_HAVE_IO
  Impl& impl = *impl_;
  if (index_ >= impl.frames || !impl.images) return ReadStatus::End;  // (a part that failed)
  McapReader::Message m;
  while (true) {
    if (!impl.images->next(m)) {
      // The next part of a rotated record, if any.
      if (part_ + 1 >= parts_.size()) break;
      impl.images.reset();
      impl.images = McapReader::open(parts_[++part_], {impl.topic()}, error);
      if (!impl.images) return ReadStatus::Error;
      continue;
    }
    const std::span<const std::uint8_t> msg = m.data;
    const std::uint64_t time = m.logTimeNs;
    const auto field = bytesField(msg, impl.video ? 3 : 2);
    if (!field || field->empty()) continue;  // skipped by the first pass too
    const auto when = messageTime(msg, time);
    if (!when) continue;  // as by the first pass
    const std::int64_t t = *when;
    const std::int64_t index = [&] {
      // The live run's index for this frame (the frames it dropped leave the same
      // gaps); for a frame whose decision is not in the record (the live queue full),
      // the one after the frame before's: indices never go back or repeat.
      // (A record whose frames share a time, edited or from a camera that stamps
      // badly, would map each to the first one's index: two keyframes, one name.)
      const auto live = impl.indexAt.find(t);
      const std::int64_t next = std::max(index_, lastIndex_ + 1);
      return live != impl.indexAt.end() && live->second >= next ? live->second : next;
    }();
    if (impl.video) {
      if (!impl.started && !h264HasIdr(*field)) continue;  // as the first pass did
      impl.started = true;
      int w = 0, h = 0;
      std::string why;
      if (!impl.decoder.decode(*field, impl.i420, w, h, why)) {
        error = "video frame " + std::to_string(index_) + " cannot be decoded (" + why + ")";
        return ReadStatus::Error;
      }
      if (w != info_.width || h != info_.height) {
        error = "video frame " + std::to_string(index_) + " changes the size from " +
                std::to_string(info_.width) + "x" + std::to_string(info_.height) + " to " +
                std::to_string(w) + "x" + std::to_string(h) + ": not replayed";
        return ReadStatus::Error;
      }
      frame = Frame{};
      frame.format = PixelFormat::YUV420;
      frame.data = impl.i420.data();
      frame.width = w;
      frame.height = h;
      frame.stride = w;
      frame.timestampNs = t;
      frame.index = index;
      format_ = "h264";
    } else {
      try {
        impl.bgr = cv::imdecode(cv::Mat(1, static_cast<int>(field->size()), CV_8UC1,
                                        const_cast<std::uint8_t*>(field->data())),
                                cv::IMREAD_COLOR);
      } catch (const cv::Exception&) {
        impl.bgr.release();  // said below, as a picture that does not decode
      }
      if (impl.bgr.empty()) {
        error = "preview frame " + std::to_string(index_) + " cannot be decoded";
        return ReadStatus::Error;
      }
      if (impl.bgr.cols != info_.width || impl.bgr.rows != info_.height) {
        error = "preview frame " + std::to_string(index_) + " changes the size from " +
                std::to_string(info_.width) + "x" + std::to_string(info_.height) + " to " +
                std::to_string(impl.bgr.cols) + "x" + std::to_string(impl.bgr.rows) +
                ": not replayed";
        return ReadStatus::Error;
      }
      frame = Frame::ofBgr(impl.bgr, index, t);
      const auto format = bytesField(msg, 3);  // CompressedImage.format (4 is frame_id)
      format_ = format ? std::string(format->begin(), format->end()) : std::string("jpeg");
    }
    commanded_ = impl.commandedAt.contains(t);
    lastIndex_ = index;
    ++index_;
    impl.encoded.assign(field->begin(), field->end());
    return ReadStatus::Frame;
  }
  return ReadStatus::End;
#else
  (void)frame;
  (void)error;
  return ReadStatus::End;
#endif
}

}  // namespace keyframed
