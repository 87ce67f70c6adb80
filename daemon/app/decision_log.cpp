#include "app/decision_log.h"

#include <cerrno>
#include <cmath>
#include <cstring>

#include "app/text_io.h"

namespace keyframed {
namespace {

std::string ms(std::int64_t ns) {
  return formatFixed(static_cast<double>(ns) / 1e6, 3);
}

std::string jnum(double v, int decimals) {
  const std::string s = formatFixed(v, decimals);
  return s.empty() ? "null" : s;
}

}  // namespace

DecisionLog::~DecisionLog() {
  std::string ignored;
  close(ignored);
}

std::string DecisionLog::header() {
  return "index,timestamp_ns,kept,reason,candidate,promoted,sharpness,threshold,sharp,overlap,"
         "paper_distance,tracking,motion_px,fast_motion,features,matches,inliers,luma_ms,blur_ms,"
         "resize_ms,overlap_ms,total_ms,geotag";
}

std::string DecisionLog::csvRow(const Decision& d, const std::string& geotag) {
  std::string s;
  s.reserve(160);
  s += std::to_string(d.index) + "," + std::to_string(d.timestampNs) + "," + (d.kept ? "1" : "0") +
       "," + toString(d.reason) + "," + (d.candidate ? "1" : "0") + "," +
       (d.promotedIndex >= 0 ? std::to_string(d.promotedIndex) : "") + "," +
       formatFixed(d.sharpness, 3) + "," + formatFixed(d.threshold, 3) + "," +
       (d.sharp ? "1" : "0") + "," + formatFixed(d.overlap, 4) + "," +
       formatFixed(d.paperDistance, 3) + "," + (d.tracking ? "1" : "0") + "," +
       formatFixed(d.motionPx, 2) + "," + (d.fastMotion ? "1" : "0") + "," +
       std::to_string(d.features) + "," + std::to_string(d.matches) + "," +
       std::to_string(d.inliers) + "," + ms(d.times.lumaNs) + "," + ms(d.times.blurNs) + "," +
       ms(d.times.resizeNs) + "," + ms(d.times.overlapNs) + "," + ms(d.times.totalNs) + ",";
  // The note is free text: quote it, doubling quotes, as CSV does.
  if (!geotag.empty()) {
    s += '"';
    for (char c : geotag) s += c == '"' ? std::string("\"\"") : std::string(1, c);
    s += '"';
  }
  return s;
}

std::string DecisionLog::jsonRow(const Decision& d, const std::string& geotag) {
  std::string s =
      "{\"index\":" + std::to_string(d.index) +
      ",\"timestamp_ns\":" + std::to_string(d.timestampNs) +
      ",\"kept\":" + (d.kept ? "true" : "false") + ",\"reason\":\"" + toString(d.reason) +
      "\",\"candidate\":" + (d.candidate ? "true" : "false") +
      ",\"promoted\":" + (d.promotedIndex >= 0 ? std::to_string(d.promotedIndex) : "null") +
      ",\"sharpness\":" + jnum(d.sharpness, 3) + ",\"threshold\":" + jnum(d.threshold, 3) +
      ",\"sharp\":" + (d.sharp ? "true" : "false") + ",\"overlap\":" + jnum(d.overlap, 4) +
      ",\"paper_distance\":" + jnum(d.paperDistance, 3) +
      ",\"tracking\":" + (d.tracking ? "true" : "false") + ",\"motion_px\":" + jnum(d.motionPx, 2) +
      ",\"fast_motion\":" + (d.fastMotion ? "true" : "false") +
      ",\"features\":" + std::to_string(d.features) + ",\"matches\":" + std::to_string(d.matches) +
      ",\"inliers\":" + std::to_string(d.inliers) + ",\"luma_ms\":" + ms(d.times.lumaNs) +
      ",\"blur_ms\":" + ms(d.times.blurNs) + ",\"resize_ms\":" + ms(d.times.resizeNs) +
      ",\"overlap_ms\":" + ms(d.times.overlapNs) + ",\"total_ms\":" + ms(d.times.totalNs) +
      ",\"geotag\":";
  if (geotag.empty()) {
    s += "null";
  } else {
    s += '"';
    for (char c : geotag) {
      if (c == '"' || c == '\\') s += '\\';
      if (static_cast<unsigned char>(c) >= 0x20) s += c;
    }
    s += '"';
  }
  s += "}";
  return s;
}

bool DecisionLog::open(const std::string& path, DecisionFormat format, std::string& error) {
  path_ = path;
  format_ = format;
  file_ = std::fopen(path.c_str(), "w");
  if (file_ == nullptr) {
    error = "cannot create " + path + ": " + std::strerror(errno);
    return false;
  }
  if (format_ == DecisionFormat::Csv && std::fprintf(file_, "%s\n", header().c_str()) < 0) {
    error = "cannot write " + path + ": " + std::strerror(errno);
    return false;
  }
  return true;
}

bool DecisionLog::flushPending(std::string& error) {
  for (const Row& r : pending_) {
    const std::string row = format_ == DecisionFormat::Csv ? csvRow(r.decision, r.geotag)
                                                           : jsonRow(r.decision, r.geotag);
    if (std::fprintf(file_, "%s\n", row.c_str()) < 0) {
      error = "cannot write " + path_ + ": " + std::strerror(errno);
      pending_.clear();
      return false;
    }
  }
  pending_.clear();
  return std::fflush(file_) == 0 ||
         (error = "cannot write " + path_ + ": " + std::strerror(errno), false);
}

bool DecisionLog::add(const Decision& d, std::string& error, const std::string& geotag) {
  if (file_ == nullptr) return true;
  if (d.promotedIndex >= 0) {
    for (Row& r : pending_) {
      Decision& p = r.decision;
      if (p.index == d.promotedIndex) {
        p.kept = true;
        p.reason = Reason::GapFill;
        p.candidate = false;
      }
    }
  }
  pending_.push_back({d, geotag});
  // A keyframe or a promotion settles every row up to here; a new candidate
  // settles every row before it.
  if (d.kept || d.promotedIndex >= 0) return flushPending(error);
  if (d.candidate) {
    const Row last = pending_.back();
    pending_.pop_back();
    if (!flushPending(error)) return false;
    pending_.push_back(last);
    return true;
  }
  // This row alone: no candidate held, nothing can change it. Or held too long:
  // every row is as final as it gets.
  if (pending_.size() == 1 || pending_.size() > kMaxHeldRows) return flushPending(error);
  return true;
}

void DecisionLog::setGeotag(std::int64_t index, const std::string& geotag) {
  for (Row& r : pending_) {
    if (r.decision.index == index) r.geotag = geotag;
  }
}

void DecisionLog::markGapFill(std::int64_t index) {
  for (Row& r : pending_) {
    Decision& p = r.decision;
    if (p.index == index) {
      p.kept = true;
      p.reason = Reason::GapFill;
      p.candidate = false;
    }
  }
}

bool DecisionLog::close(std::string& error) {
  if (file_ == nullptr) return true;
  bool ok = flushPending(error);
  if (std::fclose(file_) != 0 && ok) {
    error = "cannot close " + path_ + ": " + std::strerror(errno);
    ok = false;
  }
  file_ = nullptr;
  return ok;
}

}  // namespace keyframed
