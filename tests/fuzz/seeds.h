#pragma once

#include <cstdint>
#include <vector>

namespace keyframed::fuzz {

// Well-formed MAVLink 1 and 2 frames of every message the telemetry decoder reads
// (and a few it ignores), one autopilot plus a second system: the seed corpus.
std::vector<std::vector<std::uint8_t>> mavlinkSeeds();

}  // namespace keyframed::fuzz
