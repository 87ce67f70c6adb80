#pragma once

#include <cstdint>
#include <vector>

namespace keyframed {

// A MAVLink packet as a link received it (or a tlog recorded it), with its time.
struct TimedPacket {
  std::int64_t timeNs = 0;
  std::vector<std::uint8_t> bytes;
};

}  // namespace keyframed
