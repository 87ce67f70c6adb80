#include "alloc_counter.h"

#include <atomic>
#include <cstddef>

// glibc's real allocator entry points.
extern "C" {
void* __libc_malloc(std::size_t);
void* __libc_calloc(std::size_t, std::size_t);
void* __libc_realloc(void*, std::size_t);
void* __libc_memalign(std::size_t, std::size_t);
}

namespace {
std::atomic<bool> counting{false};
thread_local bool countingThisThread = false;  // initial-exec TLS: no allocation to reach
std::atomic<std::uint64_t> count{0};
inline void note() {
  if (counting.load(std::memory_order_relaxed) || countingThisThread)
    count.fetch_add(1, std::memory_order_relaxed);
}
}  // namespace

namespace keyframed::bench {
void setCounting(bool on) {
  counting.store(on);
}
std::uint64_t allocations() {
  return count.load();
}
void setCountingThisThread(bool on) {
  countingThisThread = on;
}
}  // namespace keyframed::bench

#include "alloc_interpose.inc"
