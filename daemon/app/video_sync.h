#pragma once

#include <atomic>
#include <cstdint>
#include <optional>
#include <string>

#include "core/motion_sync.h"
#include "tagging/camera_model.h"
#include "tagging/camera_mount.h"
#include "telemetry/telemetry_service.h"

namespace keyframed {

// `select VIDEO --telemetry FLIGHT.tlog --video-start auto`: where the video starts
// in the tlog, found from the motion both recorded. One pass over the video measures
// the camera's turn rate about its optical axis frame to frame (the geometric overlap
// estimator's step homographies); the tlog's attitudes, through the camera mount (or
// the gimbal's reports), give the same rate on the tlog's clock; findMotionLag() lines
// the two up.
struct VideoSyncRequest {
  std::string video;
  TelemetryServiceConfig link;        // link.url: the tlog
  std::optional<CameraModel> camera;  // its lens, when calibrated
  CameraMount mount;
  int analysisWidth = 640;
  double stepS = 0.02;  // both rates are compared on this grid
  MotionSyncConfig match;
  std::string hint = "give --video-start TIME";  // ends the error when the motion fails
};

struct VideoSync {
  bool ok = false;
  // The unix time of the video's container time 0: what --video-start would be.
  std::int64_t videoStartUnixNs = 0;
  MotionSyncResult match;
  std::int64_t frames = 0;      // read
  std::int64_t turnsKnown = 0;  // frames whose turn rate was measured
  double seconds = 0.0;         // wall time of the pass
  std::string error;            // one line, when !ok
};

VideoSync syncVideoWithTlog(const VideoSyncRequest& request,
                            const std::atomic<bool>* stop = nullptr);

}  // namespace keyframed
