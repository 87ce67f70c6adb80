#include "app/decision_log.h"

#include <algorithm>
#include <cmath>

#include "app/text_io.h"

namespace keyframed {
namespace {

void appendMs(std::string& s, std::int64_t ns) {
  appendFixed(s, static_cast<double>(ns) / 1e6, 3);
}

// A JSON member: `,"name":` then the number, or null for NaN or infinity.
void jsonNumber(std::string& s, std::string_view name, double v, int decimals) {
  s += ",\"";
  s += name;
  s += "\":";
  appendFixed(s, v, decimals, "null");
}

void jsonBool(std::string& s, std::string_view name, bool v) {
  s += ",\"";
  s += name;
  s += "\":";
  s += v ? "true" : "false";
}

void jsonInt(std::string& s, std::string_view name, std::int64_t v) {
  s += ",\"";
  s += name;
  s += "\":";
  appendInt(s, v);
}

void jsonMs(std::string& s, std::string_view name, std::int64_t ns) {
  s += ",\"";
  s += name;
  s += "\":";
  appendMs(s, ns);
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

void DecisionLog::appendCsvRow(std::string& s, const Decision& d, std::string_view geotag) {
  const auto flag = [&](bool v) { s += v ? "1," : "0,"; };
  const auto fixed = [&](double v, int decimals) {
    appendFixed(s, v, decimals);
    s += ',';
  };
  const auto integer = [&](std::int64_t v) {
    appendInt(s, v);
    s += ',';
  };
  integer(d.index);
  integer(d.timestampNs);
  flag(d.kept);
  s += toString(d.reason);
  s += ',';
  flag(d.candidate);
  if (d.promotedIndex >= 0) appendInt(s, d.promotedIndex);
  s += ',';
  fixed(d.sharpness, 3);
  fixed(d.threshold, 3);
  flag(d.sharp);
  fixed(d.overlap, 4);
  fixed(d.paperDistance, 3);
  flag(d.tracking);
  fixed(d.motionPx, 2);
  flag(d.fastMotion);
  integer(d.features);
  integer(d.matches);
  integer(d.inliers);
  for (const std::int64_t ns :
       {d.times.lumaNs, d.times.blurNs, d.times.resizeNs, d.times.overlapNs, d.times.totalNs}) {
    appendMs(s, ns);
    s += ',';
  }
  // The note is free text: quote it, doubling quotes, as CSV does.
  if (!geotag.empty()) {
    s += '"';
    for (char c : geotag) {
      if (c == '"') s += '"';
      s += c;
    }
    s += '"';
  }
}

void DecisionLog::appendJsonRow(std::string& s, const Decision& d, std::string_view geotag) {
  s += "{\"index\":";
  appendInt(s, d.index);
  jsonInt(s, "timestamp_ns", d.timestampNs);
  jsonBool(s, "kept", d.kept);
  s += ",\"reason\":\"";
  s += toString(d.reason);
  s += '"';
  jsonBool(s, "candidate", d.candidate);
  s += ",\"promoted\":";
  if (d.promotedIndex >= 0) {
    appendInt(s, d.promotedIndex);
  } else {
    s += "null";
  }
  jsonNumber(s, "sharpness", d.sharpness, 3);
  jsonNumber(s, "threshold", d.threshold, 3);
  jsonBool(s, "sharp", d.sharp);
  jsonNumber(s, "overlap", d.overlap, 4);
  jsonNumber(s, "paper_distance", d.paperDistance, 3);
  jsonBool(s, "tracking", d.tracking);
  jsonNumber(s, "motion_px", d.motionPx, 2);
  jsonBool(s, "fast_motion", d.fastMotion);
  jsonInt(s, "features", d.features);
  jsonInt(s, "matches", d.matches);
  jsonInt(s, "inliers", d.inliers);
  jsonMs(s, "luma_ms", d.times.lumaNs);
  jsonMs(s, "blur_ms", d.times.blurNs);
  jsonMs(s, "resize_ms", d.times.resizeNs);
  jsonMs(s, "overlap_ms", d.times.overlapNs);
  jsonMs(s, "total_ms", d.times.totalNs);
  s += ",\"geotag\":";
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
  s += '}';
}

std::string DecisionLog::csvRow(const Decision& d, const std::string& geotag) {
  std::string s;
  appendCsvRow(s, d, geotag);
  return s;
}

std::string DecisionLog::jsonRow(const Decision& d, const std::string& geotag) {
  std::string s;
  appendJsonRow(s, d, geotag);
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
  // takes that part. The rows written leave pending_ at once at the end (one move of
  // those that stay, not one per chunk). text_ keeps its room: no allocation per row.
  std::size_t written = 0;
  bool ok = true;
  while (written < n) {
    const std::size_t chunk = std::min<std::size_t>(n - written, 256);
    text_.clear();
    for (std::size_t i = written; i < written + chunk; ++i) {
      const Row& r = pending_[i];
      if (format_ == DecisionFormat::Csv) {
        appendCsvRow(text_, r.decision, r.geotag);
      } else {
        appendJsonRow(text_, r.decision, r.geotag);
      }
      text_ += '\n';
    }
    if (!file_.append(text_, error)) {
      ok = false;
      break;
    }
    written += chunk;
  }
  pending_.erase(pending_.begin(), pending_.begin() + static_cast<std::ptrdiff_t>(written));
  if (!ok) {
    // The file is cut back to its last whole row; the rows stay, to be written
    // whole when there is room.
    if (pending_.size() > kMaxUnwrittenRows) {
      const std::size_t lost = pending_.size() - kMaxUnwrittenRows;
      pending_.erase(pending_.begin(), pending_.begin() + static_cast<std::ptrdiff_t>(lost));
      rowsLost_ += static_cast<std::int64_t>(lost);
    }
    lastError_ = error;
    retryIn_ = kRetryEvery;
    return false;
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
