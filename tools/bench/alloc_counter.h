#pragma once

#include <cstdint>

namespace keyframed::bench {

// Counts heap allocations made by every library in the process (malloc and
// friends are interposed in this executable), so "no allocation per frame"
// is measured, not assumed.
void setCounting(bool on);
std::uint64_t allocations();
// Counts only this thread's allocations while on (with setCounting(false)): a test of
// one stage that other threads (a writer thread, a library's worker) run beside.
void setCountingThisThread(bool on);

}  // namespace keyframed::bench
