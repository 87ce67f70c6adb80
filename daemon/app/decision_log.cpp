#include "app/decision_log.h"

#include <algorithm>
#include <cmath>

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
  return file_.open(path, format_ == DecisionFormat::Csv ? header() + "\n" : std::string(), error);
}

bool DecisionLog::flushPending(std::string& error, std::size_t n, bool now) {
  n = std::min(n, pending_.size());
  if (n == 0) return true;
  // After a write error, rows are tried again every kRetryEvery calls, not on every
  // frame: a full disk would otherwise have the whole backlog formatted 30 times a
  // second for nothing.
  if (retryIn_ > 0 && !now) {
    --retryIn_;
    error = lastError_;
    return false;
  }
  // In chunks, each whole or not at all: a disk with room for part of the backlog
  // takes that part.
  std::string text;
  while (n > 0) {
    const std::size_t chunk = std::min<std::size_t>(n, 256);
    text.clear();
    for (std::size_t i = 0; i < chunk; ++i) {
      const Row& r = pending_[i];
      text += format_ == DecisionFormat::Csv ? csvRow(r.decision, r.geotag)
                                             : jsonRow(r.decision, r.geotag);
      text += '\n';
    }
    if (!file_.append(text, error)) {
      // The file is cut back to its last whole row; the rows stay, to be written
      // whole when there is room.
      while (pending_.size() > kMaxUnwrittenRows) {
        pending_.pop_front();
        ++rowsLost_;
      }
      lastError_ = error;
      retryIn_ = kRetryEvery;
      return false;
    }
    pending_.erase(pending_.begin(), pending_.begin() + static_cast<std::ptrdiff_t>(chunk));
    n -= chunk;
  }
  retryIn_ = 0;
  return true;
}

bool DecisionLog::add(const Decision& d, std::string& error, const std::string& geotag) {
  if (!file_.isOpen()) return true;
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
  // A new candidate settles every row before it.
  if (d.candidate) {
    heldCandidate_ = true;
    heldRows_ = 1;
    return flushPending(error, pending_.size() - 1);
  }
  // A keyframe or a promotion settles every row up to here. Without a candidate held,
  // nothing can change this row. Held too long: every row is as final as it gets.
  if (d.kept || d.promotedIndex >= 0 || !heldCandidate_ || ++heldRows_ > kMaxHeldRows) {
    heldCandidate_ = false;
    return flushPending(error);
  }
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
  if (!file_.isOpen()) return true;
  bool ok = flushPending(error, SIZE_MAX, true);
  if (!ok) rowsLost_ += static_cast<std::int64_t>(pending_.size());
  pending_.clear();
  if (ok && rowsLost_ > 0) {
    error = std::to_string(rowsLost_) + " rows of " + path_ + " lost to write errors";
    ok = false;
  }
  std::string closeError;
  if (!file_.close(closeError) && ok) {
    error = closeError;
    ok = false;
  }
  return ok;
}

}  // namespace keyframed
