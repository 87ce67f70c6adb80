#include "telemetry/mavlink_codec.h"

#include <algorithm>
#include <cstring>

namespace keyframed {

MavlinkParser::MavlinkParser() = default;

namespace {

bool between(std::uint8_t state) {
  return state == MAVLINK_PARSE_STATE_UNINIT || state == MAVLINK_PARSE_STATE_IDLE;
}

}  // namespace

MavlinkParser::Frame MavlinkParser::parseByte(std::uint8_t byte, bool again) {
  const std::uint8_t stateBefore = status_.parse_state;
  const std::uint8_t result =
      mavlink_frame_char_buffer(&rx_, &status_, byte, &message_, &messageStatus_);
  const bool inFrame = !between(status_.parse_state);
  if (between(stateBefore)) {  // a start byte, or noise
    frameLen_ = 0;
    // Parsed again, but right after a good frame found there: in step again.
    insideRejected_ = again && !afterFrame_;
  }
  afterFrame_ = false;
  if ((!between(stateBefore) || inFrame) && frameLen_ < frame_.size()) frame_[frameLen_++] = byte;
  // A signed frame whose checksum is bad, or cannot be checked (an unknown id), is
  // reported at the checksum too, with the previous frame still in message_, and
  // again, as itself, once the signature has been read: only the last counts.
  if (result == MAVLINK_FRAMING_BAD_CRC &&
      status_.parse_state == MAVLINK_PARSE_STATE_SIGNATURE_WAIT_BAD_CRC) {
    return Frame::None;
  }
  if (result == MAVLINK_FRAMING_OK) {
    afterFrame_ = true;
    ++stats_.messages;
    if (message_.magic == MAVLINK_STX_MAVLINK1) ++stats_.mavlink1;
    return Frame::Good;
  }
  if (result == MAVLINK_FRAMING_BAD_CRC && mavlink_get_msg_entry(message_.msgid) == nullptr) {
    // One that started inside a rejected frame is more likely a false start in its
    // bytes, which would swallow the good frames after it, than a frame of its own.
    if (insideRejected_) return Frame::Rejected;
    afterFrame_ = true;
    ++stats_.unknownIds;
    return Frame::UnknownId;
  }
  if (result == MAVLINK_FRAMING_BAD_CRC || result == MAVLINK_FRAMING_BAD_SIGNATURE ||
      (!between(stateBefore) && !inFrame)) {  // or a header no frame can have
    if (!insideRejected_) ++stats_.rejected;  // once, not each false start in it
    return Frame::Rejected;
  }
  if (!again && between(stateBefore) && !inFrame) {
    ++stats_.skippedBytes;  // not a start byte: noise between frames
  }
  return Frame::None;
}

void MavlinkParser::parseAgain() {
  // The bytes still to be parsed again follow this frame's, which came before them.
  const std::size_t tail = frameLen_ > 0 ? frameLen_ - 1 : 0;
  const std::size_t rest = replayLen_ - replayPos_;
  if (tail + rest > replay_.size()) {  // cannot happen: both are parts of one frame
    replayLen_ = replayPos_ = 0;
  } else {
    std::memmove(replay_.data() + tail, replay_.data() + replayPos_, rest);
    std::memcpy(replay_.data(), frame_.data() + 1, tail);
    replayPos_ = 0;
    replayLen_ = tail + rest;
  }
  frameLen_ = 0;
  rx_ = {};
  status_ = {};
}

bool MavlinkParser::cutShort() {
  if (between(status_.parse_state)) return false;
  if (!insideRejected_) ++stats_.rejected;
  parseAgain();
  return true;
}

void MavlinkParser::reset() {
  if (!between(status_.parse_state)) ++stats_.rejected;
  rx_ = {};
  status_ = {};
  frameLen_ = 0;
  replayLen_ = replayPos_ = 0;
}

MavlinkEncoder::MavlinkEncoder(std::uint8_t systemId, std::uint8_t componentId, bool mavlink1)
    : systemId_(systemId), componentId_(componentId) {
  setMavlink1(mavlink1);
  out_.reserve(MAVLINK_MAX_PACKET_LEN);
}

void MavlinkEncoder::setMavlink1(bool mavlink1) {
  if (mavlink1) {
    status_.flags |= MAVLINK_STATUS_FLAG_OUT_MAVLINK1;
  } else {
    status_.flags &= static_cast<std::uint8_t>(~MAVLINK_STATUS_FLAG_OUT_MAVLINK1);
  }
}

std::size_t wireBytes(const mavlink_message_t& msg,
                      std::array<std::uint8_t, MAVLINK_MAX_PACKET_LEN>& out) {
  std::size_t n = 0;
  out[n++] = msg.magic;
  out[n++] = msg.len;
  if (msg.magic == MAVLINK_STX) {  // MAVLink 2
    out[n++] = msg.incompat_flags;
    out[n++] = msg.compat_flags;
    out[n++] = msg.seq;
    out[n++] = msg.sysid;
    out[n++] = msg.compid;
    out[n++] = static_cast<std::uint8_t>(msg.msgid & 0xFF);
    out[n++] = static_cast<std::uint8_t>((msg.msgid >> 8) & 0xFF);
    out[n++] = static_cast<std::uint8_t>((msg.msgid >> 16) & 0xFF);
  } else {
    out[n++] = msg.seq;
    out[n++] = msg.sysid;
    out[n++] = msg.compid;
    out[n++] = static_cast<std::uint8_t>(msg.msgid & 0xFF);
  }
  const auto* payload = reinterpret_cast<const std::uint8_t*>(msg.payload64);
  std::copy_n(payload, msg.len, out.begin() + static_cast<std::ptrdiff_t>(n));
  n += msg.len;
  out[n++] = static_cast<std::uint8_t>(msg.checksum & 0xFF);
  out[n++] = static_cast<std::uint8_t>(msg.checksum >> 8);
  if (msg.magic == MAVLINK_STX && (msg.incompat_flags & MAVLINK_IFLAG_SIGNED) != 0) {
    std::copy_n(msg.signature, MAVLINK_SIGNATURE_BLOCK_LEN,
                out.begin() + static_cast<std::ptrdiff_t>(n));
    n += MAVLINK_SIGNATURE_BLOCK_LEN;
  }
  return n;
}

}  // namespace keyframed
