#pragma once

namespace keyframed {

// The answer to a capture asked for over MAVLink (MAV_CMD_IMAGE_START_CAPTURE), from
// the analysis to the telemetry side, which acknowledges it accordingly.
enum class CaptureAnswer {
  Taken,  // the next usable frame is a keyframe (MAV_RESULT_ACCEPTED)
  Busy,   // too many wait already: try again (MAV_RESULT_TEMPORARILY_REJECTED)
  Ended,  // the source has ended: no frame will come (MAV_RESULT_DENIED)
};

}  // namespace keyframed
