#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <utility>
#include <vector>

// Generated at build time by mavgen (see daemon/CMakeLists.txt); never committed.
#include <common/mavlink.h>

namespace keyframed {

// Counts of what a parser saw on a link. "Rejected" frames had a good start byte
// but a bad checksum (corruption, or a frame cut short and run into the next), a bad
// signature or an impossible header; "unknown" frames carry a message id the common
// dialect lacks (ArduPilot's or PX4's own messages: not corruption, but their
// CRC_EXTRA is unknown, so they cannot be checked and are skipped); bytes between
// frames are "skipped". A rejected frame's bytes are searched again: a false start
// found there is neither counted as rejected nor its bytes as skipped.
struct ParserStats {
  std::uint64_t bytes = 0;
  std::uint64_t messages = 0;
  std::uint64_t rejected = 0;
  std::uint64_t unknownIds = 0;
  std::uint64_t skippedBytes = 0;
  std::uint64_t mavlink1 = 0;  // of `messages`, how many were MAVLink 1 frames
};

// Byte-stream MAVLink 1/2 parser with its own state (no global channel table), so
// several links parse in parallel. Garbage never stops it: it resynchronises on the
// next start byte. A rejected frame's bytes after its start byte are parsed again:
// a frame cut short (a serial byte lost, a datagram cut) runs into the frame after
// it, which is then found there rather than lost with it. What starts in those bytes
// and reads as another dialect's frame is taken for a false start (payload bytes that
// look like a start byte) and searched in turn, so that it swallows nothing.
class MavlinkParser {
 public:
  MavlinkParser();

  // Feeds bytes; calls onMessage(const mavlink_message_t&) for each good frame.
  template <typename Fn>
  void feed(const std::uint8_t* data, std::size_t size, Fn&& onMessage) {
    feed(data, size, std::forward<Fn>(onMessage), [](const mavlink_message_t&) {});
  }

  // And onUnknown(const mavlink_message_t&) for each whole frame whose message id
  // the dialect lacks, as received (its checksum cannot be checked: to be recorded,
  // never decoded; line noise can look like one, so take it only from known senders).
  template <typename Fn, typename Gn>
  void feed(const std::uint8_t* data, std::size_t size, Fn&& onMessage, Gn&& onUnknown) {
    stats_.bytes += size;
    std::size_t i = 0;
    for (;;) {
      std::uint8_t byte = 0;
      bool again = false;
      if (replayPos_ < replayLen_) {
        byte = replay_[replayPos_++];
        again = true;
      } else if (i < size) {
        byte = data[i++];
      } else {
        break;
      }
      switch (parseByte(byte, again)) {
        case Frame::Good: onMessage(message_); break;
        case Frame::UnknownId: onUnknown(message_); break;
        case Frame::Rejected: parseAgain(); break;
        case Frame::None: break;
      }
    }
  }

  // One UDP datagram: it holds whole frames, so a frame it leaves unfinished was cut
  // short (counted as rejected) and the frames inside its bytes are searched for;
  // the next datagram starts afresh.
  template <typename Fn, typename Gn>
  void feedDatagram(const std::uint8_t* data, std::size_t size, Fn&& onMessage, Gn&& onUnknown) {
    feed(data, size, onMessage, onUnknown);
    while (cutShort()) feed(nullptr, 0, onMessage, onUnknown);
  }

  // Drops a frame half read (counted as rejected: a frame cut short): the next byte
  // is taken as the start of a new one. For a link reopened: the bytes before the
  // drop are gone.
  void reset();

  [[nodiscard]] const ParserStats& stats() const { return stats_; }

 private:
  enum class Frame : std::uint8_t { None, Good, UnknownId, Rejected };
  Frame parseByte(std::uint8_t byte, bool again);
  // After a rejected frame: its bytes after the start byte, then what was still to be
  // parsed again, are parsed before new input.
  void parseAgain();
  // A frame half read at the end of a datagram: rejected and parsed again, or false
  // when there is none.
  bool cutShort();

  mavlink_message_t rx_{};
  mavlink_status_t status_{};
  mavlink_message_t message_{};
  mavlink_status_t messageStatus_{};
  ParserStats stats_;
  // The frame being read, byte for byte (at most one whole frame).
  std::array<std::uint8_t, MAVLINK_MAX_PACKET_LEN> frame_{};
  std::size_t frameLen_ = 0;
  // It started in a rejected frame's bytes, where no good frame ended just before.
  bool insideRejected_ = false;
  bool afterFrame_ = false;  // the last byte ended a good (or another dialect's) frame
  // Bytes to parse again ahead of new input: never more than one frame's.
  std::array<std::uint8_t, MAVLINK_MAX_PACKET_LEN> replay_{};
  std::size_t replayLen_ = 0;
  std::size_t replayPos_ = 0;
};

// A received message's frame as it came on the wire: its length as received (a
// sender need not trim a MAVLink 2 payload's trailing zeros; mavlink_msg_to_send_buffer
// trims them and keeps the checksum of the untrimmed frame, which then fails), its
// checksum and signature. Returns the byte count written to `out`.
std::size_t wireBytes(const mavlink_message_t& msg,
                      std::array<std::uint8_t, MAVLINK_MAX_PACKET_LEN>& out);

// Encodes outgoing messages of one component with its own sequence counter.
class MavlinkEncoder {
 public:
  MavlinkEncoder(std::uint8_t systemId, std::uint8_t componentId, bool mavlink1 = false);
  // Frames from now on as MAVLink 1 (ids above 255 still as MAVLink 2) or 2.
  void setMavlink1(bool mavlink1);
  [[nodiscard]] bool mavlink1() const {
    return (status_.flags & MAVLINK_STATUS_FLAG_OUT_MAVLINK1) != 0;
  }

  // Fills `msg` via fn(systemId, componentId, status*, msg*) (a mavgen
  // *_encode_status/_pack_status function) and serialises it into `out`. In
  // MAVLink 1 mode, a message whose id does not fit in MAVLink 1's 8-bit id field
  // (CAMERA_INFORMATION 259, CAMERA_IMAGE_CAPTURED 263, ...) still goes out as
  // MAVLink 2: as MAVLink 1 its id would be cut to the low byte.
  template <typename Fn>
  const std::vector<std::uint8_t>& encode(Fn&& fn) {
    mavlink_message_t msg{};
    const mavlink_status_t before = status_;
    fn(systemId_, componentId_, &status_, &msg);
    if (msg.msgid > 255 && (status_.flags & MAVLINK_STATUS_FLAG_OUT_MAVLINK1) != 0) {
      status_ = before;  // same sequence number, framed again as MAVLink 2
      status_.flags &= static_cast<std::uint8_t>(~MAVLINK_STATUS_FLAG_OUT_MAVLINK1);
      msg = mavlink_message_t{};
      fn(systemId_, componentId_, &status_, &msg);
      status_.flags |= MAVLINK_STATUS_FLAG_OUT_MAVLINK1;
    }
    out_.resize(MAVLINK_MAX_PACKET_LEN);
    out_.resize(mavlink_msg_to_send_buffer(out_.data(), &msg));
    return out_;
  }

  [[nodiscard]] std::uint8_t systemId() const { return systemId_; }
  [[nodiscard]] std::uint8_t componentId() const { return componentId_; }

 private:
  std::uint8_t systemId_;
  std::uint8_t componentId_;
  mavlink_status_t status_{};
  std::vector<std::uint8_t> out_;
};

}  // namespace keyframed
