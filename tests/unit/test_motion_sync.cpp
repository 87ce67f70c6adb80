#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>

#include "core/motion_sync.h"

namespace keyframed {
namespace {

constexpr double kStep = 0.02;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// A flight's turn rate about the optical axis: gusty wobble (smoothed noise) and a few
// turns of a few seconds, sampled every kStep for `seconds`.
RateSeries flightRates(double seconds, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> noise(0.0, 0.05);
  RateSeries s;
  s.stepS = kStep;
  const auto n = static_cast<std::size_t>(seconds / kStep);
  s.values.resize(n);
  double wobble = 0.0;
  for (std::size_t i = 0; i < n; ++i) {
    const double t = static_cast<double>(i) * kStep;
    wobble = 0.95 * wobble + noise(rng);
    double turn = 0.0;
    for (const double at : {12.0, 31.0, 47.5, 70.0}) {
      const double x = (t - at) / 1.5;
      turn += 0.8 * std::exp(-x * x) * (at == 31.0 ? -1.0 : 1.0);
    }
    s.values[i] = turn + wobble;
  }
  return s;
}

// The part of `log` from `fromS` lasting `seconds`, on the video's own clock (0 at
// its start), with noise of its own and some frames where tracking was lost.
RateSeries videoOf(const RateSeries& log, double fromS, double seconds, double noiseStd,
                   unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> noise(0.0, noiseStd);
  RateSeries v;
  v.stepS = kStep;
  const auto first = static_cast<std::size_t>(std::lround(fromS / kStep));
  const auto n = static_cast<std::size_t>(seconds / kStep);
  for (std::size_t i = 0; i < n; ++i) {
    const bool lost = i % 97 < 4;
    v.values.push_back(lost ? kNaN : log.values[first + i] + noise(rng));
  }
  return v;
}

TEST(ResampleRates, InterpolatesAndLeavesGapsUnknown) {
  const std::vector<double> t = {1.0, 1.1, 1.2, 1.8, 1.9};
  const std::vector<double> v = {0.0, 1.0, 2.0, 5.0, kNaN};
  const RateSeries s = resampleRates(t, v, 0.05, 0.15);
  EXPECT_DOUBLE_EQ(s.startS, 1.0);
  ASSERT_EQ(s.values.size(), 19U);  // 1.0 .. 1.9
  EXPECT_NEAR(s.values[1], 0.5, 1e-9);
  EXPECT_NEAR(s.values[3], 1.5, 1e-9);
  EXPECT_NEAR(s.values[4], 2.0, 1e-9);
  EXPECT_TRUE(std::isnan(s.values[6]));   // 1.3: inside the 0.6 s gap
  EXPECT_NEAR(s.values[16], 5.0, 1e-9);   // 1.8
  EXPECT_TRUE(std::isnan(s.values[17]));  // toward an unknown sample
  EXPECT_TRUE(resampleRates({}, {}, 0.05, 0.1).values.empty());
}

TEST(MotionLag, FindsWhereAClipSitsInALongLog) {
  RateSeries log = flightRates(90.0, 1);
  log.startS = 1000.0;  // the log's own clock
  RateSeries video = videoOf(log, 23.36, 40.0, 0.05, 2);
  video.startS = 0.01;  // the first rate lies between the first two frames
  const MotionSyncResult r = findMotionLag(video, log);
  ASSERT_TRUE(r.ok) << r.error;
  // video time 0.01 is log time 1000 + 23.36, so video time 0 is 1000 + 23.35
  EXPECT_NEAR(r.lagS, 1000.0 + 23.35, 0.004);
  EXPECT_GT(r.correlation, 0.9);
  EXPECT_LT(r.runnerUp, 0.5);
  EXPECT_GT(r.pairs, 1800);
}

TEST(MotionLag, PlacesAClipBetweenTwoSamplesOfTheLog) {
  // The clip's samples fall 0.4 of a step after the log's: the lag found is a whole
  // number of steps plus the parabola's fraction, within a tenth of a step.
  const RateSeries log = flightRates(90.0, 14);
  RateSeries video;
  video.stepS = kStep;
  const double from = 30.0 + 0.4 * kStep;
  for (int i = 0; i < 1500; ++i) {
    const double x = (from + i * kStep) / kStep;
    const auto k = static_cast<std::size_t>(x);
    const double w = x - static_cast<double>(k);
    video.values.push_back(log.values[k] * (1.0 - w) + log.values[k + 1] * w);
  }
  const MotionSyncResult r = findMotionLag(video, log);
  ASSERT_TRUE(r.ok) << r.error;
  EXPECT_NEAR(r.lagS, from, 0.1 * kStep);
  EXPECT_GT(std::abs(r.lagS - std::round(r.lagS / kStep) * kStep), 0.1 * kStep)
      << "a whole step: the parabola did nothing";
}

TEST(MotionLag, ASpikeInEitherSeriesIsLeftOut) {
  // A step homography fitted to the wrong corners (a half turn in a frame) and an
  // attitude estimate reset: no camera turns at 50 rad/s; without the limit these
  // two samples would outweigh the whole flight's turns.
  RateSeries log = flightRates(90.0, 15);
  RateSeries video = videoOf(log, 40.0, 30.0, 0.05, 16);
  video.values[700] = 150.0;
  log.values[1000] = -50.0;
  const MotionSyncResult r = findMotionLag(video, log);
  ASSERT_TRUE(r.ok) << r.error;
  EXPECT_NEAR(r.lagS, 40.0, 0.004);
  MotionSyncConfig unlimited;
  unlimited.maxRate = 1e9;
  EXPECT_FALSE(findMotionLag(video, log, unlimited).ok);
}

TEST(MotionLag, ToleratesAVideoStartingBeforeTheLog) {
  const RateSeries log = flightRates(90.0, 3);
  RateSeries head = videoOf(log, 0.0, 30.0, 0.02, 4);
  // 5 s of video before the log began: unknown to the log, 14 % of the video
  RateSeries video;
  video.stepS = kStep;
  video.values.assign(250, 0.0);
  for (std::size_t i = 0; i < video.values.size(); ++i)
    video.values[i] = 0.3 * std::sin(static_cast<double>(i) * 0.05);
  video.values.insert(video.values.end(), head.values.begin(), head.values.end());
  const MotionSyncResult r = findMotionLag(video, log);
  ASSERT_TRUE(r.ok) << r.error;
  EXPECT_NEAR(r.lagS, -5.0, 0.004);
}

TEST(MotionLag, RefusesACameraThatNeverTurns) {
  const RateSeries log = flightRates(60.0, 5);
  RateSeries video;
  video.stepS = kStep;
  video.values.assign(1500, 0.0);
  std::mt19937 rng(6);
  std::normal_distribution<double> tiny(0.0, 0.002);
  for (double& v : video.values) v = tiny(rng);
  const MotionSyncResult r = findMotionLag(video, log);
  EXPECT_FALSE(r.ok);
  EXPECT_NE(r.error.find("hardly turns"), std::string::npos) << r.error;
}

TEST(MotionLag, RefusesARepeatingMotion) {
  // A steady back-and-forth (a sweeping gimbal): every period lines up as well.
  RateSeries log;
  log.stepS = kStep;
  for (int i = 0; i < 3000; ++i) log.values.push_back(std::sin(i * kStep * 2 * M_PI / 4.0));
  RateSeries video;
  video.stepS = kStep;
  video.values.assign(log.values.begin() + 700, log.values.begin() + 1700);
  const MotionSyncResult r = findMotionLag(video, log);
  EXPECT_FALSE(r.ok);
  EXPECT_NE(r.error.find("about as well"), std::string::npos) << r.error;
}

TEST(MotionLag, RefusesAnotherFlightsLog) {
  const RateSeries log = flightRates(90.0, 7);
  const RateSeries other = flightRates(90.0, 8);
  RateSeries video = videoOf(other, 40.0, 20.0, 0.05, 9);
  // Its own turns, unlike any of the log's (at 12, 31, 47.5 and 70 s)
  for (std::size_t i = 0; i < video.values.size(); ++i)
    video.values[i] = std::isnan(video.values[i])
                          ? video.values[i]
                          : video.values[i] + std::sin(static_cast<double>(i) * 0.011);
  const MotionSyncResult r = findMotionLag(video, log);
  EXPECT_FALSE(r.ok) << "placed at " << r.lagS << " with " << r.correlation;
  EXPECT_TRUE(r.error.find("no lag lines") != std::string::npos ||
              r.error.find("about as well") != std::string::npos)
      << r.error;
}

TEST(MotionLag, RefusesAVideoLongerThanTheLog) {
  const RateSeries log = flightRates(10.0, 10);
  const RateSeries video = videoOf(flightRates(40.0, 10), 0.0, 30.0, 0.01, 11);
  const MotionSyncResult r = findMotionLag(video, log);
  EXPECT_FALSE(r.ok);
  EXPECT_NE(r.error.find("overlaps the log at no lag"), std::string::npos) << r.error;
}

TEST(MotionLag, RefusesSeriesOnDifferentSteps) {
  const RateSeries log = flightRates(30.0, 12);
  RateSeries video = videoOf(log, 5.0, 10.0, 0.01, 13);
  video.stepS = 0.04;
  EXPECT_FALSE(findMotionLag(video, log).ok);
}

}  // namespace
}  // namespace keyframed
