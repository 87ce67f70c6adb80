#include "output/mcap_recorder.h"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>

#include "core/thread_name.h"
#include "output/dir_sync.h"
#include "output/foxglove_proto.h"

namespace keyframed {
namespace {

// JSON Schemas of the keyframed-specific JSON channels.
constexpr const char* kDecisionSchema = R"json({
  "title": "keyframed.Decision",
  "description": "The selector's verdict on one analysed frame",
  "type": "object",
  "properties": {
    "index": {"type": "integer", "description": "zero-based frame index"},
    "timestamp_ns": {"type": "integer"},
    "kept": {"type": "boolean"},
    "reason": {"type": "string"},
    "candidate": {"type": "boolean", "description": "best fallback since the last keyframe"},
    "promoted": {"type": ["integer", "null"], "description": "earlier candidate kept now"},
    "sharpness": {"type": ["number", "null"]},
    "threshold": {"type": ["number", "null"]},
    "sharp": {"type": "boolean"},
    "overlap": {"type": ["number", "null"]},
    "paper_distance": {"type": ["number", "null"]},
    "tracking": {"type": "boolean"},
    "motion_px": {"type": ["number", "null"]},
    "fast_motion": {"type": "boolean"},
    "features": {"type": "integer"},
    "matches": {"type": "integer"},
    "inliers": {"type": "integer"},
    "luma_ms": {"type": "number"},
    "blur_ms": {"type": "number"},
    "resize_ms": {"type": "number"},
    "overlap_ms": {"type": "number"},
    "total_ms": {"type": "number"},
    "geotag": {"type": ["string", "null"]}
  }
})json";

constexpr const char* kKeyframeMetaSchema = R"json({
  "title": "keyframed.KeyframeMeta",
  "description": "What is known about one keyframe (also the Zenoh attachment)",
  "type": "object",
  "properties": {
    "vehicle": {"type": "string"},
    "flight": {"type": ["string", "null"],
               "description": "the run's flight id (keyframed run; sequence numbers restart)"},
    "sequence": {"type": "integer", "description": "0, 1, 2, ... in order of writing"},
    "frame_index": {"type": "integer"},
    "file": {"type": "string", "description": "file name in the keyframe directory"},
    "time_ns": {"type": "integer", "description": "frame time on the run's clock"},
    "decided_ns": {"type": ["integer", "null"],
                   "description": "when it was selected (CLOCK_MONOTONIC), for latency"},
    "utc_us": {"type": ["integer", "null"]},
    "lat": {"type": ["number", "null"]},
    "lon": {"type": ["number", "null"]},
    "alt_amsl": {"type": ["number", "null"]},
    "alt_rel": {"type": ["number", "null"]},
    "cam_q": {"type": ["array", "null"], "items": {"type": "number"},
              "description": "camera to NED quaternion w, x, y, z"},
    "yaw": {"type": ["number", "null"]},
    "pitch": {"type": ["number", "null"]},
    "roll": {"type": ["number", "null"]},
    "hdop": {"type": ["number", "null"]},
    "fix_type": {"type": ["integer", "null"]},
    "geotag": {"type": ["string", "null"]},
    "scores": {"type": ["object", "null"]}
  }
})json";

constexpr const char* kSettingsSchema = R"json({
  "title": "keyframed.Settings",
  "description": "The selection settings in force from this message on (start, SIGHUP reload), and what keyframes are tagged with",
  "type": "object",
  "properties": {
    "selection": {"type": "string",
                  "description": "one selection.KEY=VALUE per line, TOML values"},
    "tagging": {"type": "string",
                "description": "one KEY=VALUE per line (tagging.make, model, mount, mount_roll, mount_pitch, mount_yaw and camera.time_offset_ms), TOML values"},
    "camera": {"type": "string",
               "description": "the camera model as a TOML [camera] table, as a calibration file holds it"}
  }
})json";

struct TopicSpec {
  const char* topic;
  const char* schema;
  const char* schemaEncoding;
  const char* messageEncoding;
};

constexpr TopicSpec kTopics[] = {
    {"/keyframed/keyframe", "foxglove.CompressedImage", "protobuf", "protobuf"},
    {"/keyframed/keyframe_meta", "keyframed.KeyframeMeta", "jsonschema", "json"},
    {"/keyframed/decision", "keyframed.Decision", "jsonschema", "json"},
    {"/mavlink/raw", "keyframed.MavlinkPacket", "protobuf", "protobuf"},
    {"/keyframed/location", "foxglove.LocationFix", "protobuf", "protobuf"},
    {"/keyframed/camera_pose", "foxglove.PoseInFrame", "protobuf", "protobuf"},
    {"/camera/calibration", "foxglove.CameraCalibration", "protobuf", "protobuf"},
    {"/keyframed/log", "foxglove.Log", "protobuf", "protobuf"},
    {"/camera/preview", "foxglove.CompressedImage", "protobuf", "protobuf"},
    {"/vehicle/location", "foxglove.LocationFix", "protobuf", "protobuf"},
    {"/vehicle/pose", "foxglove.PoseInFrame", "protobuf", "protobuf"},
    {"/keyframed/settings", "keyframed.Settings", "jsonschema", "json"},
    {"/camera/video", "foxglove.CompressedVideo", "protobuf", "protobuf"},
};
static_assert(std::size(kTopics) == static_cast<std::size_t>(McapTopic::Count));

std::span<const std::uint8_t> schemaData(const TopicSpec& t) {
  if (std::string(t.schemaEncoding) == "protobuf") return proto::descriptorSet(t.schema);
  const std::string name = t.schema;
  const char* text = name == "keyframed.Decision"   ? kDecisionSchema
                     : name == "keyframed.Settings" ? kSettingsSchema
                                                    : kKeyframeMetaSchema;
  return {reinterpret_cast<const std::uint8_t*>(text), std::char_traits<char>::length(text)};
}

}  // namespace

const char* McapRecorder::topicName(McapTopic topic) {
  return kTopics[static_cast<int>(topic)].topic;
}

McapRecorder::~McapRecorder() {
  std::string ignored;
  close(ignored);
}

bool McapRecorder::open(const McapRecorderOptions& options, std::string& error) {
  options_ = options;
  spare_.reserve(kSpareBuffers);
  if (!openFile(options.path, error)) return false;
  thread_ = std::thread([this] {
    nameThisThread("kf-mcap");
    run();
  });
  return true;
}

std::string McapRecorder::partPath(int part) const {
  if (part == 0) return options_.path;
  const std::filesystem::path p(options_.path);
  char suffix[16];
  std::snprintf(suffix, sizeof suffix, "-%03d", part);
  return (p.parent_path() / (p.stem().string() + suffix + p.extension().string())).string();
}

bool McapRecorder::rotateBefore(const Item& next) const {
  if (!rotationDue_) return false;
  if (!videoInPart_ || (next.topic == McapTopic::Video && next.startsGroup)) return true;
  return std::chrono::steady_clock::now() - *rotationDue_ >=
         std::chrono::milliseconds(options_.videoRotationWaitMs);
}

bool McapRecorder::rotate(std::string& error) {
  rotationDue_.reset();
  videoInPart_ = false;
  if (!writer_->close(error)) {
    error = "closing " + partPath(part_) + ": " + error;
    return false;
  }
  writer_.reset();
  ++part_;
  if (!openFile(partPath(part_), error)) {
    error = "rotating to " + partPath(part_) + ": " + error;
    return false;
  }
  const auto now =
      static_cast<std::uint64_t>(std::max<std::int64_t>(lastTimeNs_ + options_.timeOffsetNs, 0));
  for (const auto& [topic, data] : {std::pair{McapTopic::Calibration, &latchedCalibration_},
                                    std::pair{McapTopic::Settings, &latchedSettings_}}) {
    const int t = static_cast<int>(topic);
    if (!data->empty() && !writer_->write(channels_[t], ++sequences_[t], now, now, *data, error)) {
      error = partPath(part_) + ": " + error;
      return false;
    }
  }
  return true;
}

bool McapRecorder::openFile(const std::string& path, std::string& error) {
  const McapRecorderOptions& options = options_;
  fileBytes_ = 0;
  fileStart_ = std::chrono::steady_clock::now();
  McapWriterOptions wo;
  wo.path = path;
  wo.compression = options.compression;
  wo.chunkSize = options.chunkSize;
  writer_ = McapWriter::open(wo, error);
  if (!writer_) return false;
  // A part that fails before its first message holds nothing of the flight: it goes,
  // rather than stay as an empty file that a replay would take for a record.
  const auto failed = [&] {
    writer_.reset();
    std::error_code ec;
    std::filesystem::remove(path, ec);
    return false;
  };
  for (int i = 0; i < static_cast<int>(McapTopic::Count); ++i) {
    const TopicSpec& t = kTopics[i];
    const auto data = schemaData(t);
    if (data.empty()) {
      error = std::string("no schema compiled in for ") + t.schema;
      return failed();
    }
    std::uint16_t schemaId = 0;
    if (!writer_->addSchema(t.schema, t.schemaEncoding, data, schemaId, error) ||
        !writer_->addChannel(schemaId, t.topic, t.messageEncoding, {}, channels_[i], error)) {
      return failed();
    }
  }
  // Schemas and channels reach the disk now: a file cut short later still reads. With
  // fsync on (power cuts), so does the new file's name.
  if (!writer_->flush(options.fsync, error)) return failed();
  if (options.fsync) syncParentDirectory(path);
  std::lock_guard lock(mutex_);
  ++stats_.files;
  return true;
}

void McapRecorder::record(McapTopic topic, std::int64_t timeNs, std::vector<std::uint8_t> message,
                          std::uint32_t sequence, bool startsGroup) {
  enqueue(topic, timeNs, std::move(message), sequence, options_.blockWhenFull, startsGroup);
}

void McapRecorder::tryRecord(McapTopic topic, std::int64_t timeNs,
                             std::vector<std::uint8_t> message) {
  enqueue(topic, timeNs, std::move(message), 0, false);
}

void McapRecorder::enqueue(McapTopic topic, std::int64_t timeNs, std::vector<std::uint8_t> message,
                           std::uint32_t sequence, bool mayWait, bool startsGroup) {
  if (!thread_.joinable()) return;  // never opened: nothing is being recorded
  std::unique_lock lock(mutex_);
  if (failed_.load() || closing_) {
    ++stats_.dropped;  // the recorder stopped: the rest of the flight is not recorded
    return;
  }
  const std::size_t n = message.size();
  if (queuedBytes_ + n > options_.maxQueueBytes && !queue_.empty()) {
    if (!mayWait) {
      ++stats_.dropped;
      return;
    }
    space_.wait(lock, [&] {
      return queuedBytes_ + n <= options_.maxQueueBytes || queue_.empty() || failed_.load() ||
             closing_;
    });
    if (failed_.load() || closing_) {
      ++stats_.dropped;
      return;
    }
  }
  queuedBytes_ += n;
  queue_.push_back(Item{topic, sequence, timeNs, std::move(message), startsGroup});
  wake_.notify_one();
}

void McapRecorder::recordText(McapTopic topic, std::int64_t timeNs, const std::string& json) {
  std::vector<std::uint8_t> message = buffer(json.size());
  message.assign(json.begin(), json.end());
  record(topic, timeNs, std::move(message));
}

std::vector<std::uint8_t> McapRecorder::buffer(std::size_t bytes) {
  std::lock_guard lock(mutex_);
  if (spare_.empty()) return {};
  // The smallest with room enough (the large stay for large messages), or else the
  // largest (it grows the least).
  auto pick = spare_.begin();
  for (auto it = spare_.begin(); it != spare_.end(); ++it) {
    const bool fits = it->capacity() >= bytes, pickFits = pick->capacity() >= bytes;
    if (fits ? !pickFits || it->capacity() < pick->capacity()
             : !pickFits && it->capacity() > pick->capacity())
      pick = it;
  }
  std::vector<std::uint8_t> b = std::move(*pick);
  if (pick != spare_.end() - 1) *pick = std::move(spare_.back());
  spare_.pop_back();
  spareBytes_ -= b.capacity();
  return b;
}

void McapRecorder::fail(const std::string& error) {
  {
    std::lock_guard lock(mutex_);
    error_ = error;
    stats_.dropped += queue_.size();
    queue_.clear();
    queuedBytes_ = 0;
  }
  failed_.store(true);
  space_.notify_all();
  const std::string line = "MCAP recorder stopped, the run goes on without it: " + error;
  if (options_.onFailure) {
    options_.onFailure(line);
  } else {
    std::fprintf(stderr, "keyframed: %s\n", line.c_str());
  }
}

void McapRecorder::run() {
  using SteadyClock = std::chrono::steady_clock;
  const auto interval = std::chrono::milliseconds(std::max(options_.flushIntervalMs, 10));
  auto nextFlush = SteadyClock::now() + interval;
  bool dirty = false;
  std::vector<Item> batch;
  std::string error;
  while (true) {
    bool closing = false;
    {
      std::unique_lock lock(mutex_);
      wake_.wait_until(lock, nextFlush, [&] { return !queue_.empty() || closing_; });
      batch.swap(queue_);
      queuedBytes_ = 0;
      closing = closing_;
    }
    space_.notify_all();
    std::uint64_t written = 0, bytes = 0;
    for (Item& it : batch) {
      if (failed_.load()) break;
      if (rotateBefore(it)) {
        if (!rotate(error)) {
          fail(error);
          break;
        }
        dirty = false;
        if (options_.onNewPart) options_.onNewPart(partPath(part_));
      }
      const int t = static_cast<int>(it.topic);
      const std::uint32_t seq = it.sequence != 0 ? it.sequence : ++sequences_[t];
      const auto time =
          static_cast<std::uint64_t>(std::max<std::int64_t>(it.timeNs + options_.timeOffsetNs, 0));
      if (!writer_->write(channels_[t], seq, time, time, it.data, error)) {
        fail(error);
        break;
      }
      ++written;
      bytes += it.data.size();
      fileBytes_ += it.data.size();
      lastTimeNs_ = it.timeNs;
      if (it.topic == McapTopic::Calibration) latchedCalibration_ = it.data;
      if (it.topic == McapTopic::Settings) latchedSettings_ = it.data;
      if (it.topic == McapTopic::Video) videoInPart_ = true;
      dirty = true;
      const bool full = options_.rotateBytes > 0 && fileBytes_ >= options_.rotateBytes;
      const bool old =
          options_.rotateSeconds > 0 &&
          SteadyClock::now() - fileStart_ >= std::chrono::seconds(options_.rotateSeconds);
      if ((full || old) && !rotationDue_) rotationDue_ = SteadyClock::now();
    }
    const std::size_t leftover = failed_.load() ? batch.size() - written : 0;
    {
      // The buffers go back for buffer(), as many as the spare bounds allow.
      std::lock_guard lock(mutex_);
      for (Item& it : batch) {
        const std::size_t room = it.data.capacity();
        if (room == 0 || spare_.size() >= kSpareBuffers || spareBytes_ + room > kSpareBytes)
          continue;
        it.data.clear();
        spareBytes_ += room;
        spare_.push_back(std::move(it.data));
      }
    }
    batch.clear();
    // One reading of the clock for both: a deadline passing between two readings
    // would re-arm the timer without the flush, leaving two intervals unsynced.
    const auto now = SteadyClock::now();
    if (!failed_.load() && dirty && (closing || now >= nextFlush)) {
      if (!writer_->flush(options_.fsync, error)) {
        fail(error);
      } else {
        dirty = false;
        std::lock_guard lock(mutex_);
        ++stats_.flushes;
      }
    }
    if (now >= nextFlush) nextFlush = now + interval;
    {
      std::lock_guard lock(mutex_);
      stats_.written += written;
      stats_.bytes += bytes;
      stats_.dropped += leftover;
      if (closing && queue_.empty()) break;
    }
  }
}

bool McapRecorder::close(std::string& error) {
  if (!thread_.joinable()) {
    if (writer_) writer_.reset();
    return true;
  }
  {
    std::lock_guard lock(mutex_);
    closing_ = true;
  }
  wake_.notify_one();
  space_.notify_all();
  thread_.join();
  bool ok = !failed_.load();
  std::string e;
  if (ok && !writer_->close(e)) {
    fail(e);
    ok = false;
  }
  writer_.reset();
  if (!ok) {
    std::lock_guard lock(mutex_);
    error = error_;
  }
  return ok;
}

McapRecorderStats McapRecorder::stats() const {
  std::lock_guard lock(mutex_);
  return stats_;
}

}  // namespace keyframed
