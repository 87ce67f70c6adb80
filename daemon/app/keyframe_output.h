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
// reports the capture to the autopilot. Events must arrive in frame order. Records every MAVLink
// packet a live link receives into the flight outputs (MCAP /mavlink/raw); nothing for a tlog,
// which is the raw record already.
void recordRawMavlink(TelemetryService& telemetry, FlightOutputs& outputs);

class KeyframeOutput {
 public:
  // A live link is silent when no attitude and position newer than `linkSilentNs`
  // have arrived; keyframes then do not wait for it.
  KeyframeOutput(KeyframeWriter& writer, DecisionLog& log, FlightOutputs& outputs,
                 TelemetryService* telemetry, int telemetryWaitMs,
                 std::int64_t linkSilentNs = silenceOf(PoseStore::Config{}));

  // How long a link that delivers stays quiet at most: the widest gap the pose
  // history accepts between samples, plus the time a pose is held past the newest.
  static std::int64_t silenceOf(const PoseStore::Config& store);

  // False with a one-line error when a keyframe or the decision log cannot be
  // written (the keyframes written so far stay complete).
  bool handle(const KeyframeEvent& event, std::string& error);

 private:
  bool writeKeyframe(const Frame& frame, std::string& note, std::string& error);

  KeyframeWriter& writer_;
  DecisionLog& log_;
  FlightOutputs& outputs_;
  TelemetryService* telemetry_;
  int telemetryWaitMs_;
  std::int64_t linkSilentNs_;
};

}  // namespace keyframed
