#include "app/keyframe_writer.h"

#include <cerrno>
#include <cmath>
#include <cstring>
#include <filesystem>

#include "tagging/exif_writer.h"

namespace keyframed {

namespace {

std::string num(double v, int decimals) {
  if (!std::isfinite(v)) return "";
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, v);
  return buf;
}

bool writeFileAtomically(const std::string& path, const std::vector<std::uint8_t>& bytes,
                         std::string& error) {
  const std::string tmp = path + ".tmp";
  std::FILE* f = std::fopen(tmp.c_str(), "wb");
  if (f == nullptr) {
    error = "cannot create " + tmp + ": " + std::strerror(errno);
    return false;
  }
  const bool ok = std::fwrite(bytes.data(), 1, bytes.size(), f) == bytes.size();
  const int err = errno;
  if (std::fclose(f) != 0 || !ok) {
    error = "cannot write " + tmp + ": " + std::strerror(ok ? errno : err);
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

}  // namespace

KeyframeWriter::~KeyframeWriter() {
  std::string ignored;
  close(ignored);
}

std::string KeyframeWriter::fileName(std::int64_t frameIndex) {
  char name[32];
  std::snprintf(name, sizeof name, "%06lld.jpg", static_cast<long long>(frameIndex));
  return name;
}

std::string KeyframeWriter::indexHeader() {
  return "sequence,index,file,time_ns,utc_us,lat,lon,alt_amsl,alt_rel,cam_qw,cam_qx,cam_qy,"
         "cam_qz,yaw,pitch,roll,hdop,fix_type,geotag";
}

bool KeyframeWriter::open(KeyframeWriterConfig config, std::string& error) {
  config_ = std::move(config);
  if (!encoder_.isValid()) {
    error = "cannot set up the JPEG encoder (libjpeg-turbo)";
    return false;
  }
  std::error_code ec;
  config_.dir = std::filesystem::absolute(config_.dir, ec).lexically_normal().string();
  indexPath_ = config_.dir + "/keyframes.csv";
  index_ = std::fopen(indexPath_.c_str(), "w");
  if (index_ == nullptr || std::fprintf(index_, "%s\n", indexHeader().c_str()) < 0) {
    error = "cannot create " + indexPath_ + ": " + std::strerror(errno);
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
    if (pose->attitude) rec.cameraToNed = cameraToNed(*pose->attitude, config_.mount);
    tags.cameraToNed = rec.cameraToNed;
    tags.position = pose->position;
    tags.gps = pose->gps;
    tags.utcUs = pose->utcUs;
    rec.geotag = (pose->position && pose->attitude) ? "ok" : pose->staleReason;
    if (rec.geotag.empty()) rec.geotag = "incomplete";
  }
  if (!writeTags(jpeg_, tags, error)) return false;
  if (!writeFileAtomically(rec.file, jpeg_, error)) return false;
  ++count_;
  if (rec.pose.position) ++geotagged_;

  if (index_ != nullptr) {
    const auto& p = rec.pose;
    std::string row = std::to_string(rec.sequence) + "," + std::to_string(frameIndex) + "," +
                      fileName(frameIndex) + "," + std::to_string(timeNs) + "," +
                      (p.utcUs ? std::to_string(*p.utcUs) : "") + ",";
    if (p.position) {
      row += num(p.position->latDeg, 9) + "," + num(p.position->lonDeg, 9) + "," +
             num(p.position->altAmslM, 4) + "," + num(p.position->altRelM, 4) + ",";
    } else {
      row += ",,,,";
    }
    if (rec.cameraToNed) {
      const Quaternion& q = *rec.cameraToNed;
      const Pix4dAngles a = pix4dAngles(q);
      row += num(q.w, 9) + "," + num(q.x, 9) + "," + num(q.y, 9) + "," + num(q.z, 9) + "," +
             num(a.yawDeg, 4) + "," + num(a.pitchDeg, 4) + "," + num(a.rollDeg, 4) + ",";
    } else {
      row += ",,,,,,,";
    }
    row += num(p.gps.hdop, 2) + "," + (pose != nullptr ? std::to_string(p.gps.fixType) : "") +
           ",\"" + rec.geotag + "\"";
    if (std::fprintf(index_, "%s\n", row.c_str()) < 0 || std::fflush(index_) != 0) {
      error = "cannot write " + indexPath_ + ": " + std::strerror(errno);
      return false;
    }
  }
  return true;
}

bool KeyframeWriter::close(std::string& error) {
  if (index_ == nullptr) return true;
  const bool ok = std::fclose(index_) == 0;
  index_ = nullptr;
  if (!ok) error = "cannot close " + indexPath_ + ": " + std::strerror(errno);
  return ok;
}

}  // namespace keyframed
