#include "telemetry/tlog.h"

#include <sys/stat.h>

#include <cstdlib>

namespace keyframed {

namespace {
constexpr int kStx1 = 0xFE;
constexpr int kStx2 = 0xFD;
// Plausible record times: 2000-01-01 .. 2100-01-01 in unix microseconds.
constexpr std::uint64_t kMinUs = 946684800ULL * 1000000ULL;
constexpr std::uint64_t kMaxUs = 4102444800ULL * 1000000ULL;
}  // namespace

TlogReader::~TlogReader() {
  if (file_ != nullptr) std::fclose(file_);
}

bool TlogReader::open(const std::string& path, std::string& error) {
  // A FIFO's open would wait for a writer (and no signal ends that wait), a
  // directory reads as "too short": a recorded log is a file.
  struct stat st {};
  if (::stat(path.c_str(), &st) == 0 && !S_ISREG(st.st_mode)) {
    error = "telemetry log " + path + " is not a regular file";
    return false;
  }
  std::FILE* file = std::fopen(path.c_str(), "rb");
  if (file == nullptr) {
    error = "cannot open telemetry log " + path;
    return false;
  }
  return open(file, path, error);
}

bool TlogReader::open(std::FILE* file, const std::string& path, std::string& error) {
  if (file_ != nullptr) std::fclose(file_);
  file_ = file;
  truncated_ = false;
  resyncedBytes_ = 0;
  if (file_ == nullptr) {
    error = "cannot open telemetry log " + path;
    return false;
  }
  // Check the first record looks like a tlog.
  std::uint8_t head[9];
  if (std::fread(head, 1, 9, file_) != 9) {
    error = path + " is not a MAVLink tlog (too short)";
    return false;
  }
  std::uint64_t us = 0;
  for (int i = 0; i < 8; ++i) us = (us << 8) | head[i];
  if (us < kMinUs || us > kMaxUs || (head[8] != kStx1 && head[8] != kStx2)) {
    error = path + " is not a MAVLink tlog (no timestamped packet at its start)";
    return false;
  }
  std::rewind(file_);
  return true;
}

bool TlogReader::next(std::int64_t& unixNs, std::vector<std::uint8_t>& packet) {
  if (file_ == nullptr) return false;
  std::uint8_t head[8];
  for (;;) {
    const std::size_t got = std::fread(head, 1, 8, file_);
    if (got < 8) {
      truncated_ = truncated_ || got > 0;
      return false;
    }
    std::uint64_t us = 0;
    for (std::uint8_t b : head) us = (us << 8) | b;
    const int stx = std::fgetc(file_);
    if (stx == EOF) {
      truncated_ = true;
      return false;
    }
    if (us < kMinUs || us > kMaxUs || (stx != kStx1 && stx != kStx2)) {
      // Not a record boundary: slide one byte and look again.
      ++resyncedBytes_;
      std::fseek(file_, -8, SEEK_CUR);
      continue;
    }
    const int len = std::fgetc(file_);
    if (len == EOF) {
      truncated_ = true;
      return false;
    }
    std::size_t rest = 0;  // bytes after STX and LEN
    if (stx == kStx1) {
      rest = 4 + static_cast<std::size_t>(len) + 2;
    } else {
      const int incompat = std::fgetc(file_);
      if (incompat == EOF) {
        truncated_ = true;
        return false;
      }
      std::ungetc(incompat, file_);
      rest = 8 + static_cast<std::size_t>(len) + 2 + ((incompat & 0x01) != 0 ? 13 : 0);
    }
    packet.resize(2 + rest);
    packet[0] = static_cast<std::uint8_t>(stx);
    packet[1] = static_cast<std::uint8_t>(len);
    if (std::fread(packet.data() + 2, 1, rest, file_) != rest) {
      truncated_ = true;
      return false;
    }
    unixNs = static_cast<std::int64_t>(us) * 1000;
    return true;
  }
}

std::size_t mendRecordTimes(std::vector<TimedPacket>& packets) {
  constexpr std::int64_t kJumpNs = 1'000'000'000;
  constexpr std::size_t kMaxRun = 3;
  const auto near = [](std::int64_t a, std::int64_t b) { return std::llabs(a - b) <= kJumpNs; };
  std::size_t mended = 0;
  const std::size_t n = packets.size();
  // The first record: out of line with the two after it, which agree.
  if (n >= 3 && !near(packets[0].timeNs, packets[1].timeNs) &&
      near(packets[1].timeNs, packets[2].timeNs)) {
    packets[0].timeNs = packets[1].timeNs;
    ++mended;
  }
  for (std::size_t i = 1; i < n; ++i) {
    const std::int64_t before = packets[i - 1].timeNs;
    if (near(packets[i].timeNs, before)) continue;
    // Back in line within kMaxRun records: those in between were the outliers.
    std::size_t back = i + 1;
    while (back < n && back <= i + kMaxRun && !near(packets[back].timeNs, before)) ++back;
    if (back >= n || back > i + kMaxRun) continue;  // a step, or the end: kept
    for (std::size_t j = i; j < back; ++j) packets[j].timeNs = before;
    mended += back - i;
    i = back - 1;
  }
  return mended;
}

}  // namespace keyframed
