// keyframed-mcap-bench: MCAP recorder throughput with keyframe-sized messages.
// usage: keyframed-mcap-bench [FILE] [MESSAGES] [BYTES] [zstd|lz4|none]
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include "output/foxglove_proto.h"
#include "output/mcap_recorder.h"

int main(int argc, char** argv) {
  using namespace keyframed;
  const std::string path = argc > 1 ? argv[1] : "/tmp/keyframed-mcap-bench.mcap";
  const int count = argc > 2 ? std::atoi(argv[2]) : 300;
  const auto bytes = static_cast<std::size_t>(argc > 3 ? std::atol(argv[3]) : 200'000);
  const std::string compression = argc > 4 ? argv[4] : "zstd";
  // Random bytes compress like JPEG data does: hardly at all. Each message is a
  // different window, so the compressor cannot match one against the last.
  std::vector<std::uint8_t> pool(bytes * 4);
  std::mt19937 rng(1);
  for (auto& b : pool) b = static_cast<std::uint8_t>(rng() >> 24);

  McapRecorder rec;
  McapRecorderOptions o;
  o.path = path;
  o.compression = compression;
  o.blockWhenFull = true;
  std::string error;
  if (!rec.open(o, error)) {
    std::fprintf(stderr, "%s\n", error.c_str());
    return 1;
  }
  const auto t0 = std::chrono::steady_clock::now();
  for (int i = 0; i < count; ++i) {
    rec.record(
        McapTopic::Keyframe, i * 33'000'000LL,
        proto::compressedImage(
            i * 33'000'000LL, "camera",
            std::span(pool).subspan(static_cast<std::size_t>(i % 4) * bytes, bytes), "jpeg"));
  }
  if (!rec.close(error)) {
    std::fprintf(stderr, "%s\n", error.c_str());
    return 1;
  }
  const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const double mb = static_cast<double>(count) * static_cast<double>(bytes) / 1e6;
  std::printf(
      "%s: %d messages of %zu bytes, %.1f MB in %.3f s: %.1f MB/s, %.0f msg/s; file %.1f MB\n",
      compression.c_str(), count, bytes, mb, s, mb / s, count / s,
      static_cast<double>(std::filesystem::file_size(path)) / 1e6);
  return 0;
}
