#include "core/motion_sync.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>

namespace keyframed {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// Mean of the known values of each run of `factor` samples (NaN when fewer than
// half of them are known).
std::vector<double> blockMeans(const std::vector<double>& v, int factor) {
  std::vector<double> out((v.size() + static_cast<std::size_t>(factor) - 1) /
                          static_cast<std::size_t>(factor));
  for (std::size_t b = 0; b < out.size(); ++b) {
    double sum = 0.0;
    int known = 0;
    int total = 0;
    for (std::size_t i = b * static_cast<std::size_t>(factor);
         i < v.size() && i < (b + 1) * static_cast<std::size_t>(factor); ++i) {
      ++total;
      if (std::isfinite(v[i])) {
        sum += v[i];
        ++known;
      }
    }
    out[b] = 2 * known >= total && known > 0 ? sum / known : kNaN;
  }
  return out;
}

struct Score {
  double ncc = kNaN;  // NaN: too few pairs, or a flat stretch
  int pairs = 0;
};

// Normalised cross-correlation of video[j] with tel[j + k] over the pairs both know.
Score correlate(const std::vector<double>& video, const std::vector<double>& tel, long k,
                int minPairs) {
  const long nv = static_cast<long>(video.size());
  const long nt = static_cast<long>(tel.size());
  const long j0 = std::max(0L, -k);
  const long j1 = std::min(nv, nt - k);
  Score s;
  if (j1 - j0 < minPairs) return s;
  double sx = 0, sy = 0, sxx = 0, syy = 0, sxy = 0;
  int n = 0;
  for (long j = j0; j < j1; ++j) {
    const double x = video[static_cast<std::size_t>(j)];
    const double y = tel[static_cast<std::size_t>(j + k)];
    if (!std::isfinite(x) || !std::isfinite(y)) continue;
    sx += x;
    sy += y;
    sxx += x * x;
    syy += y * y;
    sxy += x * y;
    ++n;
  }
  s.pairs = n;
  if (n < minPairs) return s;
  const double cxx = sxx - sx * sx / n;
  const double cyy = syy - sy * sy / n;
  const double cxy = sxy - sx * sy / n;
  if (!(cxx > 0) || !(cyy > 0)) return s;
  const double d = std::sqrt(cxx * cyy);
  if (!(d > 1e-12 * n)) return s;
  s.ncc = cxy / d;
  return s;
}

int known(const std::vector<double>& v) {
  return static_cast<int>(
      std::count_if(v.begin(), v.end(), [](double x) { return std::isfinite(x); }));
}

std::string format(const char* fmt, double a, double b = 0.0, double c = 0.0) {
  char buf[256];
  std::snprintf(buf, sizeof buf, fmt, a, b, c);
  return buf;
}

}  // namespace

RateSeries resampleRates(const std::vector<double>& timesS, const std::vector<double>& values,
                         double stepS, double maxGapS) {
  RateSeries out;
  out.stepS = stepS;
  const std::size_t n = std::min(timesS.size(), values.size());
  if (n == 0 || !(stepS > 0)) return out;
  out.startS = timesS[0];
  const double span = timesS[n - 1] - timesS[0];
  if (!(span >= 0)) return out;
  const auto count = static_cast<std::size_t>(std::floor(span / stepS + 1e-9)) + 1;
  out.values.assign(count, kNaN);
  std::size_t i = 0;  // the segment [i, i + 1] holding the grid time
  for (std::size_t g = 0; g < count; ++g) {
    const double t = out.startS + static_cast<double>(g) * stepS;
    while (i + 1 < n && timesS[i + 1] < t) ++i;
    if (i + 1 >= n) {
      if (std::abs(t - timesS[n - 1]) < 1e-9) out.values[g] = values[n - 1];
      continue;
    }
    const double ta = timesS[i];
    const double tb = timesS[i + 1];
    if (std::abs(t - ta) < 1e-9) {  // on a sample (to rounding): its value
      out.values[g] = values[i];
    } else if (std::abs(tb - t) < 1e-9) {
      out.values[g] = values[i + 1];
    } else if (tb - ta <= maxGapS && tb > ta) {
      const double w = (t - ta) / (tb - ta);
      out.values[g] = values[i] * (1.0 - w) + values[i + 1] * w;  // NaN stays NaN
    }
  }
  return out;
}

MotionSyncResult findMotionLag(const RateSeries& videoIn, const RateSeries& telemetryIn,
                               const MotionSyncConfig& config) {
  MotionSyncResult r;
  const auto plausible = [&](RateSeries s) {
    for (double& v : s.values)
      if (!(std::abs(v) <= config.maxRate)) v = kNaN;
    return s;
  };
  const RateSeries video = plausible(videoIn);
  const RateSeries telemetry = plausible(telemetryIn);
  const double step = video.stepS;
  if (!(step > 0) || std::abs(telemetry.stepS - step) > 1e-9 * step) {
    r.error = "the video's and the log's rates are not on one time step";
    return r;
  }
  const int videoKnown = known(video.values);
  if (videoKnown * step < 2.0) {
    r.error = format("the camera's turns are known for %.1f s of the video (tracking lost?)",
                     videoKnown * step);
    return r;
  }
  {
    double sum = 0, sum2 = 0;
    for (double v : video.values) {
      if (!std::isfinite(v)) continue;
      sum += v;
      sum2 += v * v;
    }
    const double mean = sum / videoKnown;
    r.videoRateStd = std::sqrt(std::max(0.0, sum2 / videoKnown - mean * mean));
  }
  if (r.videoRateStd < config.minRateStd) {
    r.error = format(
        "the camera hardly turns in the video (turn rate varies by %.2f deg/s): nothing to line "
        "up with the log",
        r.videoRateStd * 180.0 / M_PI);
    return r;
  }

  // Coarse: every lag at which the video overlaps the log enough.
  const int factor = std::max(1, static_cast<int>(std::lround(config.coarseStepS / step)));
  const std::vector<double> cv = blockMeans(video.values, factor);
  const std::vector<double> ct = blockMeans(telemetry.values, factor);
  const int coarseMin = std::max(3, static_cast<int>(std::ceil(config.minOverlap * known(cv))));
  const long kcFirst = -static_cast<long>(cv.size()) + 1;
  const long kcLast = static_cast<long>(ct.size()) - 1;
  std::vector<double> coarse;
  coarse.reserve(static_cast<std::size_t>(std::max(0L, kcLast - kcFirst + 1)));
  long best = 0;
  double bestScore = -2.0;
  for (long kc = kcFirst; kc <= kcLast; ++kc) {
    const Score s = correlate(cv, ct, kc, coarseMin);
    coarse.push_back(s.ncc);
    if (std::isfinite(s.ncc) && s.ncc > bestScore) {
      bestScore = s.ncc;
      best = kc;
    }
  }
  if (bestScore < -1.5) {
    r.error = "the video overlaps the log at no lag (is the log shorter than the video?)";
    return r;
  }
  // The peak's lobe: around the best lag while the correlation stays above half of
  // it. The best lag outside it is the runner-up.
  const auto at = [&](long kc) { return coarse[static_cast<std::size_t>(kc - kcFirst)]; };
  long lo = best;
  while (lo - 1 >= kcFirst && std::isfinite(at(lo - 1)) && at(lo - 1) > 0.5 * bestScore) --lo;
  long hi = best;
  while (hi + 1 <= kcLast && std::isfinite(at(hi + 1)) && at(hi + 1) > 0.5 * bestScore) ++hi;
  double runnerUp = -1.0;
  long runnerUpAt = best;
  for (long kc = kcFirst; kc <= kcLast; ++kc) {
    if (kc >= lo && kc <= hi) continue;
    if (std::isfinite(at(kc)) && at(kc) > runnerUp) {
      runnerUp = at(kc);
      runnerUpAt = kc;
    }
  }
  r.runnerUp = std::max(0.0, runnerUp);

  // Fine: the full-rate lags around the coarse best, then a parabola.
  const int fineMin = std::max(3, static_cast<int>(std::ceil(config.minOverlap * videoKnown)));
  const long center = best * factor;
  long fineBest = center;
  double fineScore = -2.0;
  std::vector<double> fine;
  const long kFirst = center - 2L * factor;
  const long kLast = center + 2L * factor;
  for (long k = kFirst; k <= kLast; ++k) {
    const Score s = correlate(video.values, telemetry.values, k, fineMin);
    fine.push_back(s.ncc);
    if (std::isfinite(s.ncc) && s.ncc > fineScore) {
      fineScore = s.ncc;
      fineBest = k;
      r.pairs = s.pairs;
    }
  }
  if (fineScore < -1.5) {  // the coarse overlap was enough, the fine one is not
    fineScore = bestScore;
  }
  double frac = 0.0;
  const auto fi = [&](long k) { return fine[static_cast<std::size_t>(k - kFirst)]; };
  if (fineBest > kFirst && fineBest < kLast && std::isfinite(fi(fineBest - 1)) &&
      std::isfinite(fi(fineBest + 1))) {
    const double a = fi(fineBest - 1);
    const double b = fi(fineBest);
    const double c = fi(fineBest + 1);
    const double den = a - 2 * b + c;
    if (den < 0) frac = std::clamp(0.5 * (a - c) / den, -0.5, 0.5);
  }
  r.correlation = fineScore;
  r.lagS = telemetry.startS - video.startS + (static_cast<double>(fineBest) + frac) * step;
  if (fineScore < config.minCorrelation) {
    r.error = format(
        "no lag lines the video's turns up with the log's (best correlation %.2f, %.2f needed)",
        fineScore, config.minCorrelation);
    return r;
  }
  if (runnerUp > config.maxRunnerUpRatio * bestScore) {
    r.error = format(
        "two lags %.1f s apart line the video up with the log about as well (correlation %.2f "
        "and %.2f)",
        std::abs(static_cast<double>(runnerUpAt - best)) * factor * step, bestScore, runnerUp);
    return r;
  }
  r.ok = true;
  return r;
}

}  // namespace keyframed
