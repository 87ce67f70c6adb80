#pragma once

#include <cstdint>
#include <string>

#include "app/decision_log.h"
#include "app/keyframe_stage.h"
#include "app/keyframe_writer.h"
#include "output/flight_outputs.h"
#include "telemetry/pose_store.h"
#include "telemetry/telemetry_service.h"

namespace keyframed {

// The output end of the data path, shared by `select` (inline) and `run` (on the
// output thread): for each KeyframeEvent, tags and writes the keyframes it carries
// (pose at the frame's time, waiting briefly on a live link for telemetry newer
// than the frame while the link delivers), logs the decision, feeds the MCAP/Zenoh outputs and
// reports the capture to the autopilot. Events must arrive in frame order.

class KeyframeOutput {
 public:
  // `limits`: the pose history's (telemetry.attitude_gap_ms, position_gap_ms,
  // stale_ms). A live link that has been quieter than they allow is silent, and
  // keyframes do not wait for it. `timeOffsetMs` (camera.time_offset_ms): a
  // keyframe's pose, UTC time and recorded time are its frame time plus this.
  KeyframeOutput(KeyframeWriter& writer, DecisionLog& log, FlightOutputs& outputs,
                 TelemetryService* telemetry, int telemetryWaitMs,
                 const PoseStore::Config& limits = {}, double timeOffsetMs = 0.0);

  // False with a one-line error when a keyframe or the decision log cannot be
  // written (the keyframes written so far stay complete).
  bool handle(const KeyframeEvent& event, std::string& error);

 private:
  bool writeKeyframe(const Frame& frame, std::int64_t decidedNs, std::string& note,
                     std::string& error);
  // The link still delivers at `nowNs`: attitude within attitude_gap + stale, and
  // attitude and position within the wider gap + stale.
  [[nodiscard]] bool linkDelivers(std::int64_t nowNs, bool gimbal) const;

  KeyframeWriter& writer_;
  DecisionLog& log_;
  FlightOutputs& outputs_;
  TelemetryService* telemetry_;
  int telemetryWaitMs_;
  PoseStore::Config limits_;
  std::int64_t timeOffsetNs_;
  // The link fell silent and stayed so through a keyframe's whole wait (or was never
  // heard): keyframes do not wait for it until it delivers again.
  bool linkLost_ = true;
  std::string decisionJson_;  // the record's row of the frame at hand
};

}  // namespace keyframed
