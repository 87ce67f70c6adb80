#pragma once

#include <cstdint>

namespace keyframed::bench {

// Counts heap allocations made by every library in the process (malloc and
// friends are interposed in this executable), so "no allocation per frame"
// is measured, not assumed.
void setCounting(bool on);
std::uint64_t allocations();

}  // namespace keyframed::bench
