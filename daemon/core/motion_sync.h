#pragma once

#include <string>
#include <vector>

namespace keyframed {

// Placing a video in a telemetry log by its motion: the camera's turn rate about its
// optical axis, seen in the images (frame-to-frame rotation) and reported by the
// autopilot (attitude), is the same signal on two clocks. The lag that best lines
// the two up is where the video sits in the log, as gyro-to-video synchronisation
// does it (normalised cross-correlation).

// A signal sampled every stepS from startS (seconds on its own clock); NaN: unknown.
struct RateSeries {
  double startS = 0.0;
  double stepS = 0.02;
  std::vector<double> values;
};

// Irregular samples (time in seconds, increasing; value) onto a grid of stepS from
// the first sample's time: linear between neighbours no more than maxGapS apart,
// NaN across longer gaps and where a sample is NaN.
RateSeries resampleRates(const std::vector<double>& timesS, const std::vector<double>& values,
                         double stepS, double maxGapS);

struct MotionSyncConfig {
  double coarseStepS = 0.1;  // the whole log is scanned at this resolution first
  // The best lag must correlate at least this well (normalised, -1..1) ...
  double minCorrelation = 0.6;
  // ... and the best lag elsewhere (outside the peak's lobe) at most this share of it.
  double maxRunnerUpRatio = 0.8;
  // The video must overlap the log by this share of its known samples.
  double minOverlap = 0.7;
  // The video's rate must vary at least this much (standard deviation, rad/s, about
  // half a degree/s): a camera that never turned cannot be placed by its turns.
  double minRateStd = 0.0087;
  // Rates beyond this (rad/s, about 570 degrees/s) are no turn a camera made: a step
  // homography fitted to the wrong corners, an attitude estimate reset. Left out of
  // both series, since one such spike would spoil the correlation at every lag near it.
  double maxRate = 10.0;
};

struct MotionSyncResult {
  bool ok = false;
  // video time t lies at telemetry time t + lagS
  double lagS = 0.0;
  double correlation = 0.0;   // at lagS
  double runnerUp = 0.0;      // the best correlation outside the peak's lobe
  double videoRateStd = 0.0;  // rad/s
  int pairs = 0;              // samples compared at lagS
  std::string error;          // why not, when !ok
};

// The lag (telemetry time minus video time) at which the two series agree best, to
// a fraction of their step: a coarse scan of every lag, then the fine step around
// the best, then a parabola through the top three. Both series must share stepS.
MotionSyncResult findMotionLag(const RateSeries& video, const RateSeries& telemetry,
                               const MotionSyncConfig& config = {});

}  // namespace keyframed
