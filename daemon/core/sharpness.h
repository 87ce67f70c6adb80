#pragma once

#include <cstdint>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "core/frame.h"
#include "core/resize.h"
#include "core/running_quantile.h"

namespace keyframed {

// Mean and variance of the 4-neighbour Laplacian [0 1 0; 1 -4 1; 0 1 0].
struct LaplacianStats {
  double mean = 0.0;
  double variance = 0.0;
  std::int64_t count = 0;
};

// The paper's method: one pass, on-line (Welford/Chan) variance of the Laplacian
// evaluated only on a grid of every rowStep-th row and colStep-th column
// (2, 3 = the paper's "S9"). Interior pixels only (no border extrapolation).
[[nodiscard]] LaplacianStats sampledLaplacianVariance(GrayView gray, int rowStep, int colStep);

// Exact two-pass variance over every interior pixel: the reference the sampled
// method is checked against.
[[nodiscard]] LaplacianStats referenceLaplacianVariance(GrayView gray);

enum class BlurMode {
  Absolute,  // the paper's: sharp when score >= absoluteThreshold
  Adaptive,  // sharp when score >= max(floor, ratio * quantile(recent scores))
};

struct SharpnessConfig {
  BlurMode mode = BlurMode::Adaptive;
  int rowStep = 2;
  int colStep = 3;
  double absoluteThreshold = 100.0;  // Absolute mode
  double floor = 10.0;               // Adaptive mode: never accept below this
  double ratio = 0.7;                // Adaptive: fraction of the running statistic
  double quantile = 0.75;            // Adaptive: which quantile of recent scores
  int window = 150;                  // Adaptive: how many recent frames (5 s at 30 fps)
  int warmup = 5;                    // Adaptive: frames before the statistic is trusted
  int analysisWidth = 0;             // 0: score at full resolution; else downscale first

  bool operator==(const SharpnessConfig&) const = default;
  // Empty when valid; otherwise a one-line description of the bad setting.
  [[nodiscard]] std::string validate() const;
};

// Scores frames by variance of the Laplacian and decides whether each is sharp.
class SharpnessScorer {
 public:
  explicit SharpnessScorer(const SharpnessConfig& config = {});

  struct Result {
    double score = 0.0;
    double threshold = 0.0;
    bool sharp = false;
  };

  // Scores one frame, judges it against the current threshold and then adds it
  // to the running statistic. Frames must come in capture order.
  Result evaluate(GrayView gray);

  // Score only, without judging or updating the statistic.
  [[nodiscard]] double score(GrayView gray);

  // The threshold the next frame will be judged against.
  [[nodiscard]] double threshold() const;
  // Adaptive mode, before `warmup` frames at or above the floor were seen (dark or
  // blank frames do not end it): the threshold is only the floor.
  [[nodiscard]] bool warmingUp() const;

  void reset();
  [[nodiscard]] const SharpnessConfig& config() const { return config_; }

 private:
  void observe(double score);

  SharpnessConfig config_;
  RunningQuantile history_;  // recent scores, those under the floor left out
  // Adaptive: the threshold the last frame was judged against once warmed up (0
  // before). The next one is at least this times fallPerFrame_: the threshold falls
  // by half over half a `window` at most, so that a stretch of blur (vibration, a
  // long exposure) is not learnt as the new normal within the window, while a plainer
  // ground still brings it down in seconds.
  double applied_ = 0.0;
  double fallPerFrame_ = 1.0;
  DownScaler scaler_;
};

}  // namespace keyframed
