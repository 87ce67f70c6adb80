// Heap allocations of a running process, by thread name, for the daemon benchmark
// (tools/bench/daemon_bench.sh --allocs): LD_PRELOAD=libkeyframed-alloc-count.so.
//   KEYFRAMED_ALLOC_FROM_S, KEYFRAMED_ALLOC_TO_S: the window counted, in seconds
//     after the process started (default 3 .. forever): past the start-up.
//   KEYFRAMED_ALLOC_REPORT: the file the counts go to at exit, one line per thread
//     ("NAME COUNT", threads of one name summed; default stderr).
// The daemon names its threads (kf-capture, kf-analysis, kf-output, kf-mcap, ...).
#include <sys/prctl.h>
#include <time.h>
#include <unistd.h>

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>

extern "C" {
void* __libc_malloc(std::size_t);
void* __libc_calloc(std::size_t, std::size_t);
void* __libc_realloc(void*, std::size_t);
void* __libc_memalign(std::size_t, std::size_t);
}

namespace {

struct Slot {
  std::atomic<std::uint64_t> count{0};
  char name[16] = {};
  bool named = false;
};
constexpr int kSlots = 128;  // threads seen in the window; more are counted as "other"
Slot slots[kSlots];
std::atomic<int> used{0};
Slot other;
// Initial-exec: reaching it never calls the allocator (as a dynamic TLS block would).
__attribute__((tls_model("initial-exec"))) thread_local Slot* mine = nullptr;

double fromS = 3.0, toS = 1e300;
double startS = 0.0;

double nowS() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<double>(ts.tv_sec) + static_cast<double>(ts.tv_nsec) * 1e-9;
}

__attribute__((constructor)) void start() {
  startS = nowS();
  if (const char* v = std::getenv("KEYFRAMED_ALLOC_FROM_S")) fromS = std::atof(v);
  if (const char* v = std::getenv("KEYFRAMED_ALLOC_TO_S")) toS = std::atof(v);
}

inline void note() {
  // Libraries' constructors that ran before this one's (start-up) are not counted.
  if (startS == 0.0) return;
  const double t = nowS() - startS;
  if (t < fromS || t >= toS) return;
  if (mine == nullptr) {
    const int i = used.fetch_add(1);
    mine = i < kSlots ? &slots[i] : &other;
  }
  if (!mine->named && mine != &other) {
    prctl(PR_GET_NAME, mine->name);  // no allocation: the kernel's copy
    mine->named = true;
  }
  mine->count.fetch_add(1, std::memory_order_relaxed);
}

__attribute__((destructor)) void report() {
  FILE* out = stderr;
  if (const char* path = std::getenv("KEYFRAMED_ALLOC_REPORT")) {
    if (FILE* f = std::fopen(path, "w")) out = f;
  }
  const int n = used.load() < kSlots ? used.load() : kSlots;
  // Threads of one name summed (a thread that ran twice, e.g. after a reload).
  for (int i = 0; i < n; ++i) {
    if (slots[i].name[0] == '\0' && slots[i].count.load() == 0) continue;
    std::uint64_t total = slots[i].count.load();
    for (int j = i + 1; j < n; ++j) {
      if (std::strncmp(slots[i].name, slots[j].name, sizeof slots[i].name) == 0) {
        total += slots[j].count.load();
        slots[j].count.store(0);
        slots[j].name[0] = '\0';
      }
    }
    std::fprintf(out, "%s %llu\n", slots[i].name[0] != '\0' ? slots[i].name : "?",
                 static_cast<unsigned long long>(total));
  }
  if (other.count.load() > 0)
    std::fprintf(out, "other %llu\n", static_cast<unsigned long long>(other.count.load()));
  if (out != stderr) std::fclose(out);
}

}  // namespace

#include "alloc_interpose.inc"
