#include "output/mcap_repair.h"

#include <algorithm>
#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>

#include "output/dir_sync.h"
#include "output/io_ffi.h"

namespace keyframed {

namespace fs = std::filesystem;

namespace {
constexpr std::array<char, 8> kMagic = {'\x89', 'M', 'C', 'A', 'P', '0', '\r', '\n'};
}  // namespace

bool mcapComplete(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return false;
  in.seekg(0, std::ios::end);
  const std::streamoff size = in.tellg();
  if (size < static_cast<std::streamoff>(2 * kMagic.size())) return false;
  std::array<char, 8> tail{};
  in.seekg(size - static_cast<std::streamoff>(tail.size()));
  in.read(tail.data(), static_cast<std::streamsize>(tail.size()));
  return in.good() && tail == kMagic;
}

namespace {

// A file created but never written: empty, or (a power cut after the file system
// allocated its first block, before the data reached it) zeros only.
bool neverWritten(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return false;
  std::array<char, 4096> block{};
  std::uint64_t seen = 0;
  while (in.read(block.data(), block.size()) || in.gcount() > 0) {
    const auto n = static_cast<std::size_t>(in.gcount());
    if (std::any_of(block.begin(), block.begin() + static_cast<std::ptrdiff_t>(n),
                    [](char c) { return c != 0; }))
      return false;
    seen += n;
    if (seen > (1U << 20)) return false;  // a megabyte of zeros was written by someone
  }
  return true;
}

}  // namespace

bool recoverMcap(const std::string& src, const std::string& dst, std::uint64_t& messages,
                 std::string& error, const std::atomic<int>* stop) {
  static_assert(
      sizeof(std::atomic<int>) == sizeof(std::int32_t) && std::atomic<int>::is_always_lock_free,
      "the flag is read by Rust as an AtomicI32");
  std::array<char, 512> e{};
  messages = 0;
  // The Rust side reads the flag as an AtomicI32: same size, lock-free.
  const auto* flag = reinterpret_cast<const std::int32_t*>(stop);
  if (kfio_mcap_recover(src.c_str(), dst.c_str(), "same", &messages, flag, e.data(), e.size()) !=
      0) {
    error = e.data();
    std::error_code ec;
    fs::remove(dst, ec);  // half a file is no use to anyone
    return false;
  }
  return true;
}

std::vector<McapRepair> repairFlightRecords(const std::string& flightsDir,
                                            const std::string& skipDir,
                                            const std::atomic<int>& stop,
                                            std::uint64_t reserveBytes) {
  std::vector<McapRepair> out;
  std::error_code ec;
  std::vector<fs::path> files;
  const fs::path skip = skipDir.empty() ? fs::path() : fs::weakly_canonical(skipDir, ec);
  for (const auto& flight : fs::directory_iterator(flightsDir, ec)) {
    std::error_code e2;
    if (!flight.is_directory(e2) || flight.is_symlink(e2)) continue;
    if (!skip.empty() && fs::weakly_canonical(flight.path(), e2) == skip) continue;
    for (const auto& f : fs::directory_iterator(flight.path(), e2)) {
      const fs::path& p = f.path();
      if (p.extension() == ".recovering") {
        fs::remove(p, e2);  // an earlier repair was stopped half-way
      } else if (p.extension() == ".mcap" && f.is_regular_file(e2) && !mcapComplete(p.string())) {
        files.push_back(p);
      }
    }
  }
  std::sort(files.begin(), files.end());
  for (const fs::path& p : files) {
    if (stop.load()) break;
    McapRepair r;
    r.path = p.string();
    if (neverWritten(r.path)) {
      std::error_code e1;
      r.removed = fs::remove(p, e1);
      if (e1) r.error = "cannot remove " + r.path + " (never written): " + e1.message();
      out.push_back(std::move(r));
      continue;
    }
    const std::string tmp = r.path + ".recovering";
    std::error_code e1;
    const std::uint64_t size = fs::file_size(p, e1);
    const fs::space_info room = fs::space(p.parent_path(), e1);
    if (!e1 && (room.available < reserveBytes || room.available - reserveBytes < size)) {
      r.error = "not repaired now: its copy needs " + std::to_string(size >> 20) + " MiB and " +
                std::to_string(reserveBytes >> 20) + " MiB to spare, the disk has " +
                std::to_string(room.available >> 20) + " MiB free";
      out.push_back(std::move(r));
      continue;
    }
    if (recoverMcap(r.path, tmp, r.messages, r.error, &stop)) {
      std::error_code e2;
      fs::rename(tmp, p, e2);
      if (e2) {
        r.error = "cannot replace " + r.path + ": " + e2.message();
      } else {
        syncParentDirectory(r.path);  // the repaired file under its name, through a power cut
      }
    }
    out.push_back(std::move(r));
  }
  return out;
}

}  // namespace keyframed
