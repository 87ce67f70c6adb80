// Fuzz target for the MAVLink byte-stream parser and the telemetry decoder behind
// it: whatever arrives on a serial port or a UDP socket, the daemon must neither
// crash nor account for a byte twice. Built two ways (tests/fuzz/CMakeLists.txt):
// with clang's libFuzzer (tools/fuzz.sh) and with a standalone driver that runs in
// every build of the unit tests.
#include <cstddef>
#include <cstdint>
#include <cstdlib>

#include "telemetry/mavlink_codec.h"
#include "telemetry/telemetry_decoder.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using keyframed::MavlinkParser;
  using keyframed::TelemetryDecoder;
  MavlinkParser parser;
  TelemetryDecoder decoder;
  std::int64_t now = 1'000'000'000;
  std::uint64_t seen = 0;
  // Feed in uneven pieces, as a link would deliver them: the first byte picks the
  // piece size, so the parser's state machine is cut at every position.
  const std::size_t piece = size > 0 ? 1 + data[0] % 64 : 1;
  for (std::size_t at = 0; at < size; at += piece) {
    const std::size_t n = size - at < piece ? size - at : piece;
    parser.feed(data + at, n, [&](const mavlink_message_t& msg) {
      ++seen;
      now += 7'000'000;
      decoder.handle(msg, now);
    });
  }
  const auto& stats = parser.stats();
  // Every byte is counted once; a frame counted as a message is one we delivered.
  if (stats.bytes != size || stats.messages != seen || stats.mavlink1 > stats.messages) {
    std::abort();
  }
  if (stats.skippedBytes > size) std::abort();
  // Queries on whatever history the bytes produced must be safe at any time.
  (void)decoder.poseAt(now / 2);
  (void)decoder.poseAt(now + 1'000'000'000);
  (void)decoder.covers(now);
  (void)decoder.hasPose();
  (void)decoder.stats();
  return 0;
}
