#pragma once

#include <sys/types.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <span>
#include <string>
#include <string_view>

// Small text and file helpers shared by the files keyframed writes.
namespace keyframed {

// Fixed-point text of v; "" for NaN or infinity (an empty CSV field, "unknown").
inline std::string formatFixed(double v, int decimals) {
  if (!std::isfinite(v)) return "";
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, v);
  return buf;
}

// formatFixed() appended to out, or `otherwise` for NaN or infinity: no allocation
// where out has the room (the per-frame rows are built this way).
inline void appendFixed(std::string& out, double v, int decimals, std::string_view otherwise = {}) {
  if (!std::isfinite(v)) {
    out += otherwise;
    return;
  }
  char buf[64];
  const int n = std::snprintf(buf, sizeof buf, "%.*f", decimals, v);
  if (n > 0)
    out.append(buf, static_cast<std::size_t>(std::min(n, static_cast<int>(sizeof buf) - 1)));
}

// The decimal text of v appended to out.
inline void appendInt(std::string& out, std::int64_t v) {
  char buf[24];
  const auto r = std::to_chars(buf, buf + sizeof buf, v);
  out.append(buf, r.ptr);
}

// s for the inside of a JSON string: quotes and backslashes escaped, newlines as
// \n, other control characters dropped.
inline std::string jsonEscape(std::string_view s) {
  std::string out;
  out.reserve(s.size());
  for (char ch : s) {
    if (ch == '\n') {
      out += "\\n";
      continue;
    }
    if (static_cast<unsigned char>(ch) < 0x20) continue;
    if (ch == '"' || ch == '\\') out += '\\';
    out += ch;
  }
  return out;
}

// s on one line: newline, carriage return and tab as \n, \r, \t, other control
// characters as \xNN, so that an error echoing what was typed stays one line.
inline std::string oneLine(std::string_view s) {
  std::string out;
  out.reserve(s.size());
  for (const char ch : s) {
    const auto u = static_cast<unsigned char>(ch);
    if (u >= 0x20 && u != 0x7f) {
      out += ch;
    } else if (ch == '\n') {
      out += "\\n";
    } else if (ch == '\r') {
      out += "\\r";
    } else if (ch == '\t') {
      out += "\\t";
    } else {
      constexpr const char* kHex = "0123456789abcdef";
      out += "\\x";
      out += kHex[u >> 4];
      out += kHex[u & 0xf];
    }
  }
  return out;
}

// printf into a std::string of whatever length it takes (no fixed buffer to cut a
// long path short).
std::string formatText(const char* format, ...) __attribute__((format(printf, 1, 2)));

// "2026-06-01T10:00:00.012Z": a unix time in ns as ISO 8601 UTC, to the millisecond.
std::string formatUtcIso(std::int64_t unixNs);
// "20260601T100000Z" (or "20260601T100000.012Z" with millis): the same, as flight ids
// and file names have it.
std::string formatUtcCompact(std::int64_t unixNs, bool millis);
// The system clock now, unix ns.
std::int64_t unixNowNs();

// Writes path.tmp, syncs it to the disk and renames it to path (syncing the
// directory too), so a reader never sees a partial file, nor a power cut an empty
// one. False with a one-line error.
bool writeFileAtomically(const std::string& path, std::span<const std::uint8_t> bytes,
                         std::string& error);
bool writeFileAtomically(const std::string& path, std::string_view text, std::string& error);
// fsync of the directory holding path (best effort).
void syncDirectoryOf(const std::string& path);
// write() until all of bytes is written; false with errno on an error (EINTR retried).
bool writeAll(int fd, std::string_view bytes);

// A file written in whole rows (keyframes.csv, the decisions file). A write the disk
// takes only part of (a full disk) is cut back, so the file always ends at the end of
// a row and the caller can write the same rows again, whole, once there is room.
class RowFile {
 public:
  RowFile() = default;
  RowFile(const RowFile&) = delete;
  RowFile& operator=(const RowFile&) = delete;
  ~RowFile();

  // Creates (or empties) path and writes header (may be empty); false with a line.
  bool open(const std::string& path, std::string_view header, std::string& error);
  // Appends rows whole or not at all; false with a line ("cannot write PATH: ...").
  bool append(std::string_view rows, std::string& error);
  // fdatasync: what is written survives a power cut. False with a line when the disk
  // says it could not (EIO): the rows may then be lost in a power cut, though they
  // read back now (a file system that cannot sync a file, EINVAL, is not an error).
  bool sync(std::string& error) const;
  bool close(std::string& error);
  [[nodiscard]] bool isOpen() const { return fd_ >= 0; }
  [[nodiscard]] const std::string& path() const { return path_; }

 private:
  int fd_ = -1;
  off_t good_ = 0;  // the file's length up to the last whole row
  std::string path_;
};

}  // namespace keyframed
