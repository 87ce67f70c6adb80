#pragma once

// Flight records a crash left unfinished (SIGKILL, a power cut: no summary and no
// footer, so seeking readers and `mcap doctor` refuse them) are rewritten complete
// at the next start.

#include <atomic>
#include <cstdint>
#include <string>
#include <vector>

namespace keyframed {

// True when the file ends with MCAP's closing magic, as a finished file does.
bool mcapComplete(const std::string& path);

// `src`, cut short, rewritten complete at `dst`: every message that reads back, with
// its channel and schema; `messages` gets their count. A non-zero `stop` ends it
// early (an error). On an error `dst` is removed.
bool recoverMcap(const std::string& src, const std::string& dst, std::uint64_t& messages,
                 std::string& error, const std::atomic<int>* stop = nullptr);

struct McapRepair {
  std::string path;
  std::uint64_t messages = 0;
  std::string error;     // empty: repaired in place (or removed)
  bool removed = false;  // created but never written (empty, or zeros): nothing to keep
};

// Every unfinished .mcap in the flight directories under `flightsDir` (but not in
// `skipDir`, the running flight's) rewritten complete in place, through
// <file>.recovering renamed over it; a .recovering left by an interrupted repair is
// removed first, and so is a part that was created but never written (no byte but
// zeros: a kill or power cut as it began). Stops once `stop` is set (non-zero), leaving the file it
// was on as it was. Files it could not repair keep their content. A file is repaired only while the
// disk has room for its copy and `reserveBytes` more: the running flight records on the same disk,
// and a record cut short by a full disk must not fill it again (it waits, named in the result, for
// a start with more room).
inline constexpr std::uint64_t kRepairReserveBytes = 256ULL << 20;
std::vector<McapRepair> repairFlightRecords(const std::string& flightsDir,
                                            const std::string& skipDir,
                                            const std::atomic<int>& stop,
                                            std::uint64_t reserveBytes = kRepairReserveBytes);

}  // namespace keyframed
