#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

namespace keyframed {

// A byte link to the autopilot. One reader thread calls read(); write() may be
// called from the same thread only (the camera component runs on it).
class MavlinkLink {
 public:
  enum class Status { Data, Timeout, End, Error };

  virtual ~MavlinkLink() = default;

  // Waits up to timeoutMs for bytes. On Data, size holds the byte count and
  // timeNs the arrival time (CLOCK_MONOTONIC, or the tlog's record time).
  virtual Status read(std::uint8_t* buffer, std::size_t capacity, std::size_t& size,
                      std::int64_t& timeNs, int timeoutMs, std::string& error) = 0;
  // Sends a packet; false when there is no peer yet, no room (error empty: the packet
  // is dropped, nothing of it sent) or the link failed (error set).
  virtual bool write(const std::uint8_t* data, std::size_t size, std::string& error) = 0;
  // Reopens after an error (a serial device unplugged and plugged back in).
  virtual bool reopen(std::string& error) = 0;
  // Each read() returns one datagram, which starts on a frame boundary (UDP): a frame
  // cut short in one never goes on in the next. A byte stream (serial) can split a
  // frame anywhere.
  [[nodiscard]] virtual bool datagrams() const { return false; }
  // The bytes last read came from the autopilot: on a link that can hear several
  // senders (udpin), write() goes to that sender from now on, not to whoever spoke
  // last (a ground station or a second vehicle on the same port).
  virtual void pinPeerToLastSender() {}
  // Replay links deliver recorded times and have an end.
  [[nodiscard]] virtual bool isReplay() const { return false; }
  // A replay that ended inside a record.
  [[nodiscard]] virtual bool truncated() const { return false; }
  // Bytes of a replay that belonged to no record (garbage between records), skipped.
  [[nodiscard]] virtual std::uint64_t skippedBytes() const { return 0; }
  [[nodiscard]] virtual std::string describe() const = 0;
};

// Opens a link from a URL:
//   udpin:HOST:PORT       listen (answers the autopilot once known, else the last sender)
//   udpout:HOST:PORT      send to HOST:PORT (we speak first)
//   serial:DEVICE[:BAUD]  e.g. serial:/dev/ttyAMA0:921600 (default 57600)
//   tlog:PATH             a MAVLink tlog, replayed with its recorded timestamps
// (a bare path ending in .tlog means tlog:PATH, a bare /dev/... means serial).
// `serialMayBeAbsent`: a serial device that is not there (yet: a USB autopilot powered
// after the companion) is no failure: the link comes back unopened with `error` saying
// why, its reads fail with that reason, and reopen() opens it once it appears.
std::unique_ptr<MavlinkLink> openMavlinkLink(const std::string& url, std::string& error,
                                             bool serialMayBeAbsent = false);

// Validates a link URL without opening it (configuration checks).
bool parseMavlinkUrl(const std::string& url, std::string& error);

// True when the URL names a tlog (a recorded flight, replayed on its own clock).
bool isTlogUrl(const std::string& url);

std::int64_t monotonicNowNs();

}  // namespace keyframed
