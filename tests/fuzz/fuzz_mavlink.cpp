// Fuzz target for what arrives from the autopilot's side: the MAVLink byte-stream
// parser and the telemetry decoder behind it, the camera component's handling of
// commands and TIMESYNC (TelemetryService on a link that delivers the input), and
// the tlog reader (the input as a file). Whatever arrives on a serial port, a UDP
// socket or in a tlog, the daemon must neither crash, nor account for a byte twice,
// nor send anything but well-formed MAVLink. Built two ways
// (tests/fuzz/CMakeLists.txt): with clang's libFuzzer (tools/fuzz.sh) and with a
// standalone driver that runs in every build of the unit tests.
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <vector>

#include "telemetry/link.h"
#include "telemetry/mavlink_codec.h"
#include "telemetry/telemetry_decoder.h"
#include "telemetry/telemetry_service.h"
#include "telemetry/tlog.h"

namespace {

using keyframed::MavlinkLink;

// Delivers the input in pieces, then ends; checks that every write is exactly one
// well-formed MAVLink frame.
class InputLink final : public MavlinkLink {
 public:
  InputLink(const std::uint8_t* data, std::size_t size, std::size_t piece)
      : data_(data), size_(size), piece_(piece) {}

  Status read(std::uint8_t* buffer, std::size_t capacity, std::size_t& size, std::int64_t& timeNs,
              int, std::string&) override {
    if (at_ >= size_) return Status::End;
    size = size_ - at_ < piece_ ? size_ - at_ : piece_;
    if (size > capacity) size = capacity;
    for (std::size_t i = 0; i < size; ++i) buffer[i] = data_[at_ + i];
    at_ += size;
    timeNs = keyframed::monotonicNowNs();
    return Status::Data;
  }

  bool write(const std::uint8_t* data, std::size_t size, std::string&) override {
    keyframed::MavlinkParser parser;
    std::size_t frames = 0;
    parser.feed(data, size, [&](const mavlink_message_t&) { ++frames; });
    if (frames != 1 || parser.stats().skippedBytes != 0 || parser.stats().rejected != 0) {
      std::abort();
    }
    return (++writes_ % 5) != 0;  // now and then the link refuses (a full radio buffer)
  }

  bool reopen(std::string&) override { return true; }
  [[nodiscard]] std::string describe() const override { return "fuzz"; }

 private:
  const std::uint8_t* data_;
  std::size_t size_;
  std::size_t piece_;
  std::size_t at_ = 0;
  std::size_t writes_ = 0;
};

void parserAndDecoder(const std::uint8_t* data, std::size_t size, std::size_t piece) {
  using keyframed::MavlinkParser;
  using keyframed::TelemetryDecoder;
  MavlinkParser parser;
  TelemetryDecoder decoder;
  std::int64_t now = 1'000'000'000;
  std::uint64_t seen = 0;
  for (std::size_t at = 0; at < size; at += piece) {
    const std::size_t n = size - at < piece ? size - at : piece;
    const auto onMessage = [&](const mavlink_message_t& msg) {
      ++seen;
      now += 7'000'000;
      decoder.handle(msg, now);
    };
    // Odd pieces as UDP datagrams (a frame left unfinished is searched and dropped),
    // even ones as a serial stream.
    if (piece % 2 == 1) {
      parser.feedDatagram(data + at, n, onMessage, [](const mavlink_message_t&) {});
    } else {
      parser.feed(data + at, n, onMessage);
    }
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
}

// The camera component: COMMAND_LONG (REQUEST_MESSAGE for CAMERA_INFORMATION and
// CAMERA_IMAGE_CAPTURED by index and range), TIMESYNC requests and answers, with
// three captures sent before (so that re-requests find some).
void cameraComponent(const std::uint8_t* data, std::size_t size, std::size_t piece, bool mavlink1) {
  keyframed::TelemetryServiceConfig config;
  config.mavlink1 = mavlink1;
  config.maxPendingCaptures = 2;
  config.captureHistory = 4;
  keyframed::TelemetryService service(config, keyframed::CameraDescription{});
  for (int i = 0; i < 3; ++i) {
    keyframed::CaptureReport r;
    r.imageIndex = i;
    r.timeNs = keyframed::monotonicNowNs();
    r.fileUrl = std::string(300, 'x');  // longer than file_url: cut, not overrun
    if (i == 1) r.cameraAttitude = keyframed::Quaternion{0.5, 0.5, 0.5, 0.5};
    service.reportCapture(r);
  }
  service.setLogSink([](keyframed::TelemetryLogLevel, const std::string&) {});
  std::string error;
  if (!service.start(std::make_unique<InputLink>(data, size, piece), error)) std::abort();
  service.stop();  // returns once the link has ended (or at once)
  const auto st = service.stats();
  if (st.capturesSent + st.capturesPending + st.capturesDropped != 3) std::abort();
  if (st.parser.bytes > size) std::abort();
}

// The input as a tlog file.
void tlogReader(const std::uint8_t* data, std::size_t size) {
  if (size == 0) return;
  std::FILE* f = fmemopen(const_cast<std::uint8_t*>(data), size, "rb");
  if (f == nullptr) return;
  keyframed::TlogReader reader;
  std::string error;
  if (!reader.open(f, "fuzz.tlog", error)) return;
  std::int64_t t = 0;
  std::vector<std::uint8_t> packet;
  std::size_t total = 0;
  while (reader.next(t, packet)) {
    // A record: 8 bytes of time, then a packet that starts with a MAVLink start byte.
    if (packet.size() < 2 || (packet[0] != 0xFD && packet[0] != 0xFE)) std::abort();
    total += 8 + packet.size();
    if (total > size) std::abort();
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  // Feed in uneven pieces, as a link would deliver them: the first byte picks the
  // piece size, so the parser's state machine is cut at every position.
  const std::size_t piece = size > 0 ? 1 + data[0] % 64 : 1;
  parserAndDecoder(data, size, piece);
  cameraComponent(data, size, piece, size > 0 && (data[0] & 0x80) != 0);
  tlogReader(data, size);
  return 0;
}
