#include "app/keyframe_writer.h"

#include <cmath>
#include <filesystem>
#include <new>

#include "app/text_io.h"
#include "tagging/exif_writer.h"

namespace keyframed {

KeyframeWriter::~KeyframeWriter() {
  std::string ignored;
  close(ignored);
}

std::string KeyframeWriter::indexHeader() {
  return "sequence,index,file,time_ns,utc_us,lat,lon,alt_amsl,alt_rel,cam_qw,cam_qx,cam_qy,"
         "cam_qz,yaw,pitch,roll,hdop,fix_type,geotag";
}

bool KeyframeWriter::open(KeyframeWriterConfig config, std::string& error) {
  config_ = std::move(config);
  if (!config_.camera && (!config_.make.empty() || !config_.model.empty())) {
    // Identity only: uncalibrated, so no intrinsics are tagged; an unset one stays out.
    config_.camera.emplace();
    config_.camera->make = config_.make;
    config_.camera->model = config_.model;
  } else if (config_.camera) {
    if (!config_.make.empty()) config_.camera->make = config_.make;
    if (!config_.model.empty()) config_.camera->model = config_.model;
  }
  scaled_.reset();
  if (!encoder_.isValid()) {
    error = "cannot set up the JPEG encoder (libjpeg-turbo)";
    return false;
  }
  std::error_code ec;
  config_.dir = std::filesystem::absolute(config_.dir, ec).lexically_normal().string();
  const std::string indexPath = config_.dir + "/keyframes.csv";
  if (!index_.open(indexPath, indexHeader() + "\n", error)) return false;
  syncDirectoryOf(indexPath);
  return true;
}

bool KeyframeWriter::appendIndexRows(std::string& error, std::int64_t current) {
  while (!pendingRows_.empty()) {
    const Row& row = pendingRows_.front();
    // A row the disk does not take (whole) stays, to be written once there is room,
    // and the next ones after it.
    if (!index_.append(row.text, error)) return false;
    const std::int64_t sequence = row.sequence;
    pendingRows_.pop_front();  // written: never again, whatever follows
    if (sequence != current) indexedLate_.push_back(sequence);
  }
  // Like the keyframes themselves, the index survives a power cut as far as written.
  if (!index_.sync(error)) {
    ++syncErrors_;
    return false;
  }
  return true;
}

const CameraModel* KeyframeWriter::cameraFor(int width, int height) {
  if (!config_.camera) return nullptr;
  if (!scaled_ || scaled_->width != width || scaled_->height != height) {
    const CameraModel& c = *config_.camera;
    scaled_ =
        (c.width > 0 && (c.width != width || c.height != height)) ? c.scaledTo(width, height) : c;
    if (scaled_->width <= 0) {
      scaled_->width = width;
      scaled_->height = height;
    }
  }
  return &*scaled_;
}

bool KeyframeWriter::write(const cv::Mat& bgr, std::int64_t frameIndex, std::int64_t timeNs,
                           const Pose* pose, KeyframeRecord& rec, std::string& error) {
  if (!encoder_.encode(bgr, config_.quality, jpeg_, error)) return false;
  return finishWrite(bgr.cols, bgr.rows, frameIndex, timeNs, pose, rec, error);
}

bool KeyframeWriter::write(const Frame& frame, const Pose* pose, KeyframeRecord& rec,
                           std::string& error) {
  // Straight from the camera's YUV where the frame is YUV: no colour conversion.
  if (!encoder_.encode(frame, config_.quality, jpeg_, error)) return false;
  return finishWrite(frame.width, frame.height, frame.index, frame.timestampNs, pose, rec, error);
}

bool KeyframeWriter::finishWrite(int width, int height, std::int64_t frameIndex,
                                 std::int64_t timeNs, const Pose* pose, KeyframeRecord& rec,
                                 std::string& error) {
  rec = KeyframeRecord{};
  rec.sequence = count_;
  rec.frameIndex = frameIndex;
  rec.timeNs = timeNs;
  rec.file = config_.dir + "/" + fileName(frameIndex);

  TagSet tags;
  tags.camera = cameraFor(width, height);
  tags.frameIndex = frameIndex;
  if (pose != nullptr) {
    rec.pose = *pose;
    if (config_.mount.gimbal) {
      // The gimbal is a body carrying the camera forward-looking: a 0,0,0 mount.
      if (pose->gimbal) rec.cameraToNed = cameraToNed(*pose->gimbal, CameraMount{0, 0, 0});
    } else if (pose->attitude) {
      rec.cameraToNed = cameraToNed(*pose->attitude, config_.mount);
    }
    tags.cameraToNed = rec.cameraToNed;
    tags.position = pose->position;
    tags.gps = pose->gps;
    tags.utcUs = pose->utcUs;
    if (pose->position && rec.cameraToNed) {
      rec.geotag = "ok";
    } else {
      rec.geotag = pose->staleReason;
      if (config_.mount.gimbal && !pose->gimbal) {
        if (!rec.geotag.empty()) rec.geotag += "; ";
        rec.geotag += pose->gimbalReason.empty() ? "no gimbal attitude" : pose->gimbalReason;
      }
    }
    if (rec.geotag.empty()) rec.geotag = "incomplete";
  }
  if (!tags.utcUs && config_.utcFallback) {
    tags.utcUs = config_.utcFallback(timeNs);
    rec.pose.utcUs = tags.utcUs;
  }
  // A keyframe whose tags cannot be written is still a keyframe: kept untagged (the
  // JPEG is left as encoded), the reason in its geotag column, and reported.
  std::string tagError;
  if (!writeTags(jpeg_, tags, tagError)) {
    std::string why = tagError;
    for (char& c : why) {
      if (c == '"' || c == '\n' || c == '\r') c = '\'';  // one CSV field
    }
    rec.geotag = "untagged (" + why + ")";  // the pose stays in the index
  }
  rec.encoded = true;
  // The sequence number is taken whether or not the file can be saved: a receiver
  // sees one gap-free sequence, and what it missed is served from disk when it is there.
  ++count_;
  if (rec.pose.position && tagError.empty()) ++geotagged_;

  const auto& p = rec.pose;
  std::string row = std::to_string(rec.sequence) + "," + std::to_string(frameIndex) + "," +
                    fileName(frameIndex) + "," + std::to_string(timeNs) + "," +
                    (p.utcUs ? std::to_string(*p.utcUs) : "") + ",";
  if (p.position) {
    row += formatFixed(p.position->latDeg, 9) + "," + formatFixed(p.position->lonDeg, 9) + "," +
           formatFixed(p.position->altAmslM, 4) + "," + formatFixed(p.position->altRelM, 4) + ",";
  } else {
    row += ",,,,";
  }
  if (rec.cameraToNed) {
    const Quaternion& q = *rec.cameraToNed;
    const Pix4dAngles a = pix4dAngles(q);
    row += formatFixed(q.w, 9) + "," + formatFixed(q.x, 9) + "," + formatFixed(q.y, 9) + "," +
           formatFixed(q.z, 9) + "," + formatFixed(a.yawDeg, 4) + "," + formatFixed(a.pitchDeg, 4) +
           "," + formatFixed(a.rollDeg, 4) + ",";
  } else {
    row += ",,,,,,,";
  }
  row += formatFixed(p.gps.hdop, 2) + "," + (pose != nullptr ? std::to_string(p.gps.fixType) : "") +
         ",\"" + rec.geotag + "\"\n";

  // Those a full disk held back go first: files and index rows in sequence order.
  if (!saveHeld(error) || !writeFileAtomically(rec.file, jpeg_, error)) {
    rec.file.clear();
    ++unsaved_;
    try {
      held_.push_back(
          {config_.dir + "/" + fileName(frameIndex), jpeg_, Row{rec.sequence, std::move(row)}});
      heldBytes_ += jpeg_.size();
    } catch (const std::bad_alloc&) {
      ++letGo_;  // no memory to hold it either: unsaved, and counted as let go
      return false;
    }
    while (heldBytes_ > config_.maxHeldBytes && held_.size() > 1) {
      heldBytes_ -= held_.front().jpeg.size();
      held_.pop_front();
      ++letGo_;
    }
    return false;
  }
  if (!tagError.empty())
    error = "keyframe " + fileName(frameIndex) + " saved untagged: " + tagError;
  if (index_.isOpen()) {
    pendingRows_.push_back(Row{rec.sequence, std::move(row)});
    if (!appendIndexRows(error, rec.sequence)) {
      // Written, only not synced (the disk's error is the caller's): indexed all the same.
      rec.indexed = pendingRows_.empty();
      return false;
    }
  }
  rec.indexed = true;
  return tagError.empty();
}

bool KeyframeWriter::saveHeld(std::string& error) {
  bool ok = true;
  std::size_t saved = 0;
  while (!held_.empty()) {
    Held& h = held_.front();
    if (!writeFileAtomically(h.file, h.jpeg, error)) {
      ok = false;
      break;
    }
    if (index_.isOpen()) pendingRows_.push_back(std::move(h.row));
    heldBytes_ -= h.jpeg.size();
    held_.pop_front();
    ++saved;
  }
  unsaved_ -= static_cast<std::int64_t>(saved);
  savedLate_ += static_cast<std::int64_t>(saved);
  // Their rows now (a row the disk does not take yet stays pending for the next).
  std::string rowError;
  if (saved > 0 && index_.isOpen()) appendIndexRows(rowError);
  return ok;
}

bool KeyframeWriter::close(std::string& error) {
  if (!index_.isOpen()) return true;
  // Keyframes and rows a full disk held back, if there is room now.
  bool ok = saveHeld(error);
  std::string rowError;
  if (!appendIndexRows(rowError) && ok) {
    error = rowError;
    ok = false;
  }
  if (!index_.close(rowError) && ok) {
    error = rowError;
    ok = false;
  }
  return ok;
}

}  // namespace keyframed
