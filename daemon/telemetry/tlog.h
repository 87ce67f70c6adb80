#pragma once

#include <cstdint>
#include <cstdio>
#include <string>
#include <vector>

#include "telemetry/timed_packet.h"

namespace keyframed {

// A MAVLink telemetry log (.tlog) as QGroundControl and MAVProxy write it: each
// record is an 8-byte big-endian UNIX time in microseconds followed by one packet.
// Packets are framed by their own length field; a record cut short at the end of
// the file is reported as truncated, not as an error.
class TlogReader {
 public:
  TlogReader() = default;
  ~TlogReader();
  TlogReader(const TlogReader&) = delete;
  TlogReader& operator=(const TlogReader&) = delete;

  bool open(const std::string& path, std::string& error);
  // Reads from an open stream (e.g. fmemopen), which it then owns; name is for errors.
  bool open(std::FILE* file, const std::string& name, std::string& error);
  // Next record: its time (unix ns) and packet bytes. False at the end.
  bool next(std::int64_t& unixNs, std::vector<std::uint8_t>& packet);
  [[nodiscard]] bool truncated() const { return truncated_; }
  [[nodiscard]] std::uint64_t resyncedBytes() const { return resyncedBytes_; }

 private:
  std::FILE* file_ = nullptr;
  bool truncated_ = false;
  std::uint64_t resyncedBytes_ = 0;
};

// Record times out of line with the records around them (one to three records whose
// time jumps by more than a second and then returns: a corrupt timestamp, a ground
// station's clock hiccup) set to the time of the record before them; returns how
// many. A step that stays (the station's clock set) is kept. One such time would
// otherwise hold back every packet after it (fed in record order, as time passes)
// or pull the clock estimate seconds away.
std::size_t mendRecordTimes(std::vector<TimedPacket>& packets);

}  // namespace keyframed
