// keyframed-mavlink-bench: the MAVLink parser's throughput on three kinds of input,
// made here with the encoder: flight telemetry as an autopilot sends it (attitude,
// quaternion, position, GPS), the same with 3 bytes lost from every 10th packet (a
// serial line that drops bytes), and random bytes a quarter of which are start bytes.
// usage: keyframed-mavlink-bench [PACKETS]
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <vector>

#include "telemetry/mavlink_codec.h"

namespace {

using keyframed::MavlinkEncoder;
using keyframed::MavlinkParser;

std::vector<std::uint8_t> packet(MavlinkEncoder& enc, int i, std::mt19937& rng) {
  std::uniform_real_distribution<float> any(-3.0F, 3.0F);
  const auto boot = static_cast<std::uint32_t>(i * 10);
  const auto& bytes = enc.encode([&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st,
                                     mavlink_message_t* m) {
    switch (i % 4) {
      case 0:
        mavlink_msg_attitude_pack_status(s, c, st, m, boot, any(rng), any(rng), any(rng), any(rng),
                                         any(rng), any(rng));
        break;
      case 1: {
        const float q[4] = {any(rng), any(rng), any(rng), any(rng)};
        mavlink_msg_attitude_quaternion_pack_status(s, c, st, m, boot, q[0], q[1], q[2], q[3],
                                                    any(rng), any(rng), any(rng), nullptr);
        break;
      }
      case 2:
        mavlink_msg_global_position_int_pack_status(
            s, c, st, m, boot, static_cast<std::int32_t>(rng()), static_cast<std::int32_t>(rng()),
            static_cast<std::int32_t>(rng() % 200000), static_cast<std::int32_t>(rng() % 100000), 0,
            0, 0, static_cast<std::uint16_t>(rng() % 36000));
        break;
      default:
        mavlink_msg_gps_raw_int_pack_status(
            s, c, st, m, boot * 1000ULL, 3, static_cast<std::int32_t>(rng()),
            static_cast<std::int32_t>(rng()), 100000, 80, 120, 500, 9000, 14, 0, 0, 0, 0, 0, 0);
        break;
    }
  });
  return bytes;
}

struct Result {
  double mbPerS = 0;
  std::uint64_t messages = 0;
  std::uint64_t rejected = 0;
};

Result parse(const std::vector<std::uint8_t>& data) {
  Result r;
  double best = 1e9;
  for (int run = 0; run < 5; ++run) {
    MavlinkParser parser;
    std::uint64_t n = 0;
    const auto t0 = std::chrono::steady_clock::now();
    parser.feed(data.data(), data.size(), [&n](const mavlink_message_t&) { ++n; });
    best = std::min(best,
                    std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    r.messages = n;
    r.rejected = parser.stats().rejected;
  }
  r.mbPerS = static_cast<double>(data.size()) / best / 1e6;
  return r;
}

}  // namespace

int main(int argc, char** argv) {
  const int packets = argc > 1 ? std::atoi(argv[1]) : 200'000;
  if (packets <= 0) {
    std::fprintf(stderr, "usage: keyframed-mavlink-bench [PACKETS]\n");
    return 2;
  }
  MavlinkEncoder enc(1, 1);
  std::mt19937 rng(3);
  std::vector<std::uint8_t> clean;
  std::vector<std::uint8_t> lossy;
  int whole = 0;
  for (int i = 0; i < packets; ++i) {
    auto p = packet(enc, i, rng);
    clean.insert(clean.end(), p.begin(), p.end());
    if (i % 10 == 0) {
      p.erase(p.begin() + static_cast<std::ptrdiff_t>(p.size() / 2),
              p.begin() + static_cast<std::ptrdiff_t>(p.size() / 2 + 3));
    } else {
      ++whole;
    }
    lossy.insert(lossy.end(), p.begin(), p.end());
  }
  std::vector<std::uint8_t> junk(clean.size());
  for (auto& b : junk) b = static_cast<std::uint8_t>(rng() % 4 == 0 ? 0xFD : rng());

  std::printf("MAVLink parser, best of 5 runs, one thread\n");
  std::printf("%-34s %10s %12s %10s\n", "input", "MB/s", "messages", "rejected");
  const auto line = [](const char* what, const Result& r, long long of) {
    std::printf("%-34s %10.1f %6llu/%-5lld %10llu\n", what, r.mbPerS,
                static_cast<unsigned long long>(r.messages), of,
                static_cast<unsigned long long>(r.rejected));
  };
  line("telemetry", parse(clean), packets);
  line("telemetry, 3 bytes lost in 1 of 10", parse(lossy), whole);
  line("random bytes, 1/4 start bytes", parse(junk), 0);
  return 0;
}
