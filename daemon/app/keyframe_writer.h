#pragma once

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <deque>
#include <functional>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "app/text_io.h"
#include "core/frame.h"
#include "tagging/camera_model.h"
#include "tagging/camera_mount.h"
#include "tagging/jpeg_encoder.h"
#include "telemetry/pose.h"

namespace keyframed {

struct KeyframeWriterConfig {
  std::string dir;
  int quality = 92;
  std::optional<CameraModel> camera;  // scaled to the frame size when it differs
  // EXIF Make/Model: replace the camera model's; with no camera model, tag them
  // alone (with the image size) rather than nothing. "": keep / leave out.
  std::string make;
  std::string model;
  CameraMount mount;
  // UTC (unix us) of a frame time, for keyframes the autopilot gave no UTC for (no
  // SYSTEM_TIME, no telemetry); unset or nullopt: none is tagged.
  std::function<std::optional<std::int64_t>(std::int64_t timeNs)> utcFallback;
  // Keyframes a full disk did not take are held in memory up to this many bytes of
  // JPEG, to be saved once it has room; past that the oldest are let go.
  std::size_t maxHeldBytes = 32u << 20;
};

// What was written for one keyframe (also a row of keyframes.csv).
struct KeyframeRecord {
  std::int64_t sequence = 0;  // 0, 1, 2, ... in the order keyframes are written
  std::int64_t frameIndex = 0;
  std::int64_t timeNs = 0;
  std::int64_t decidedNs = 0;  // when the selector kept it (CLOCK_MONOTONIC; 0: unknown)
  std::string file;            // absolute path
  Pose pose;
  std::optional<Quaternion> cameraToNed;
  std::string geotag;    // "ok", why a part is missing, or "" without telemetry
  bool encoded = false;  // the tagged JPEG is in lastJpeg() (even when saving it failed)
  // Saved and its row in keyframes.csv, where the queryable finds it: false when either
  // failed (a full disk can take the row after the JPEG; it goes in with a later one).
  bool indexed = false;
};

// Encodes keyframes (libjpeg-turbo), tags them (EXIF/XMP with the pose at the frame
// time and the camera model), and writes each atomically (temp file + rename) as
// <dir>/<frame index>.jpg, plus one row per keyframe in <dir>/keyframes.csv.
class KeyframeWriter {
 public:
  KeyframeWriter() = default;
  ~KeyframeWriter();
  KeyframeWriter(const KeyframeWriter&) = delete;
  KeyframeWriter& operator=(const KeyframeWriter&) = delete;

  bool open(KeyframeWriterConfig config, std::string& error);
  // pose: nullptr when there is no telemetry. False with a one-line error. When only
  // saving failed (disk full), record.encoded is still true and the keyframe keeps
  // its sequence number: it can be published from lastJpeg(), and file is "". The
  // JPEG is then held in memory (up to maxHeldBytes, the oldest let go past that) and
  // saved, with its index row, as soon as the disk takes it: before the next
  // keyframe is, so that files and rows stay in sequence order, and at close().
  bool write(const cv::Mat& bgr, std::int64_t frameIndex, std::int64_t timeNs, const Pose* pose,
             KeyframeRecord& record, std::string& error);
  // The same from a frame in any pixel format (JPEG straight from YUV); the
  // frame's index and timestamp name and date the keyframe.
  bool write(const Frame& frame, const Pose* pose, KeyframeRecord& record, std::string& error);
  bool close(std::string& error);

  // Keyframes given a sequence number (saved or not), and those saved to disk.
  [[nodiscard]] std::int64_t count() const { return count_; }
  [[nodiscard]] std::int64_t saved() const { return count_ - unsaved_; }
  // Of the saved: those a full disk held back, saved later.
  [[nodiscard]] std::int64_t savedLate() const { return savedLate_; }
  // Of the unsaved: those let go from memory (more than maxHeldBytes waited), lost
  // to the disk for good; the others are still held.
  [[nodiscard]] std::int64_t letGo() const { return letGo_; }
  // Times the disk said keyframes.csv could not be synced (EIO): its rows read back,
  // but those since the last good sync may not survive a power cut.
  [[nodiscard]] std::int64_t syncErrors() const { return syncErrors_; }
  // The sequence numbers of keyframes whose write() said "not indexed" (a full disk)
  // that are now saved and in keyframes.csv, in order, since the last call: a copy
  // kept in memory for them can go.
  [[nodiscard]] std::vector<std::int64_t> takeIndexedLate() {
    return std::exchange(indexedLate_, {});
  }
  // The tagged JPEG bytes of the last keyframe written.
  [[nodiscard]] const std::vector<std::uint8_t>& lastJpeg() const { return jpeg_; }
  [[nodiscard]] std::int64_t geotagged() const { return geotagged_; }
  [[nodiscard]] const CameraMount& mount() const { return config_.mount; }
  // Inline: keyframed_output names files too, without linking the app library.
  [[nodiscard]] static std::string fileName(std::int64_t frameIndex) {
    char name[32];
    std::snprintf(name, sizeof name, "%06lld.jpg", static_cast<long long>(frameIndex));
    return name;
  }
  [[nodiscard]] static std::string indexHeader();

 private:
  const CameraModel* cameraFor(int width, int height);
  bool finishWrite(int width, int height, std::int64_t frameIndex, std::int64_t timeNs,
                   const Pose* pose, KeyframeRecord& record, std::string& error);

  KeyframeWriterConfig config_;
  JpegEncoder encoder_;
  std::vector<std::uint8_t> jpeg_;
  std::optional<CameraModel> scaled_;
  // Writes the pending rows in order; `current`: the sequence of the keyframe being
  // written (its row is not late), -1: none.
  bool appendIndexRows(std::string& error, std::int64_t current = -1);
  // Saves the held keyframes, oldest first; false (with the error) when one still
  // cannot be saved.
  bool saveHeld(std::string& error);

  RowFile index_;  // keyframes.csv
  struct Row {
    std::int64_t sequence;
    std::string text;  // its keyframes.csv row
  };
  std::deque<Row> pendingRows_;  // rows not yet written (a full disk), in order
  std::vector<std::int64_t> indexedLate_;
  // Keyframes a full disk did not take, in sequence order, and their bytes.
  struct Held {
    std::string file;  // absolute path
    std::vector<std::uint8_t> jpeg;
    Row row;
  };
  std::deque<Held> held_;
  std::size_t heldBytes_ = 0;
  std::int64_t count_ = 0;
  std::int64_t unsaved_ = 0;
  std::int64_t savedLate_ = 0;
  std::int64_t syncErrors_ = 0;
  std::int64_t letGo_ = 0;
  std::int64_t geotagged_ = 0;
};

}  // namespace keyframed
