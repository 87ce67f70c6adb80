#include "alloc_counter.h"

#include <atomic>
#include <cstddef>

// glibc's real allocator entry points.
extern "C" {
void* __libc_malloc(std::size_t);
void* __libc_calloc(std::size_t, std::size_t);
void* __libc_realloc(void*, std::size_t);
void* __libc_memalign(std::size_t, std::size_t);
void __libc_free(void*);
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

// Definitions in the executable take precedence over libc's for every shared
// library (symbol interposition); they forward to glibc.
extern "C" {
void* malloc(std::size_t n) {
  note();
  return __libc_malloc(n);
}
void* calloc(std::size_t a, std::size_t b) {
  note();
  return __libc_calloc(a, b);
}
void* realloc(void* p, std::size_t n) {
  note();
  return __libc_realloc(p, n);
}
void free(void* p) {
  __libc_free(p);
}
void* memalign(std::size_t align, std::size_t n) {
  note();
  return __libc_memalign(align, n);
}
void* aligned_alloc(std::size_t align, std::size_t n) {
  note();
  return __libc_memalign(align, n);
}
int posix_memalign(void** out, std::size_t align, std::size_t n) {
  note();
  void* p = __libc_memalign(align, n);
  if (p == nullptr) return 12;  // ENOMEM
  *out = p;
  return 0;
}
}
