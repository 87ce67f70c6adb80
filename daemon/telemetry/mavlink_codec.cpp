#include "telemetry/mavlink_codec.h"

namespace keyframed {

MavlinkParser::MavlinkParser() = default;

MavlinkParser::Frame MavlinkParser::parseByte(std::uint8_t byte) {
  ++stats_.bytes;
  const std::uint8_t stateBefore = status_.parse_state;
  const std::uint8_t result =
      mavlink_frame_char_buffer(&rx_, &status_, byte, &message_, &messageStatus_);
  // A signed frame whose checksum is bad, or cannot be checked (an unknown id), is
  // reported at the checksum too, with the previous frame still in message_, and
  // again, as itself, once the signature has been read: only the last counts.
  if (result == MAVLINK_FRAMING_BAD_CRC &&
      status_.parse_state == MAVLINK_PARSE_STATE_SIGNATURE_WAIT_BAD_CRC) {
    return Frame::None;
  }
  if (result == MAVLINK_FRAMING_OK) {
    ++stats_.messages;
    if (message_.magic == MAVLINK_STX_MAVLINK1) ++stats_.mavlink1;
    return Frame::Good;
  }
  if (result == MAVLINK_FRAMING_BAD_CRC && mavlink_get_msg_entry(message_.msgid) == nullptr) {
    ++stats_.unknownIds;
    return Frame::UnknownId;
  }
  if (result == MAVLINK_FRAMING_BAD_CRC || result == MAVLINK_FRAMING_BAD_SIGNATURE) {
    ++stats_.rejected;
  } else if (stateBefore == MAVLINK_PARSE_STATE_IDLE &&
             status_.parse_state == MAVLINK_PARSE_STATE_IDLE) {
    ++stats_.skippedBytes;  // not a start byte: noise between frames
  }
  return Frame::None;
}

void MavlinkParser::reset() {
  if (status_.parse_state != MAVLINK_PARSE_STATE_UNINIT &&
      status_.parse_state != MAVLINK_PARSE_STATE_IDLE) {
    ++stats_.rejected;
  }
  rx_ = {};
  status_ = {};
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

}  // namespace keyframed
