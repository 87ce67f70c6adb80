#include <cmath>

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include "core/sharpness.h"
#include "photos.h"

namespace keyframed {
namespace {

// Textbook Welford, one sample at a time, to check the row-batched version.
LaplacianStats welfordPerSample(const cv::Mat& g, int rs, int cs) {
  LaplacianStats s;
  double m2 = 0;
  for (int y = 1; y < g.rows - 1; y += rs)
    for (int x = 1; x < g.cols - 1; x += cs) {
      const double l = g.at<uchar>(y - 1, x) + g.at<uchar>(y + 1, x) + g.at<uchar>(y, x - 1) +
                       g.at<uchar>(y, x + 1) - 4.0 * g.at<uchar>(y, x);
      ++s.count;
      const double d = l - s.mean;
      s.mean += d / static_cast<double>(s.count);
      m2 += d * (l - s.mean);
    }
  s.variance = m2 / static_cast<double>(s.count);
  return s;
}

TEST(Sharpness, SampledS9IsWithinThePapersBoundOfTheFullVariance) {
  // The paper reports S9 (every 2nd row, 3rd column) within 2.7 % of the exact
  // two-pass variance. Here: every photograph within 4 %, 2.7 % on average.
  double sumErr = 0;
  for (const std::string& name : test::photoNames()) {
    const cv::Mat g = test::photo(name);
    ASSERT_FALSE(g.empty());
    const double ref = referenceLaplacianVariance(GrayView::of(g)).variance;
    const double s9 = sampledLaplacianVariance(GrayView::of(g), 2, 3).variance;
    EXPECT_GT(ref, 0.0) << name;
    EXPECT_NEAR(s9 / ref, 1.0, 0.04) << name << " ref " << ref << " s9 " << s9;
    sumErr += std::fabs(s9 / ref - 1.0);
    std::printf("  %-14s S9/full = %.4f\n", name.c_str(), s9 / ref);
  }
  EXPECT_LT(sumErr / static_cast<double>(test::photoNames().size()), 0.027);
}

TEST(Sharpness, FullGridEqualsTheTwoPassReference) {
  const cv::Mat g = test::photo("building.jpg");
  const auto ref = referenceLaplacianVariance(GrayView::of(g));
  const auto full = sampledLaplacianVariance(GrayView::of(g), 1, 1);
  EXPECT_EQ(full.count, ref.count);
  EXPECT_NEAR(full.mean, ref.mean, 1e-9);
  EXPECT_NEAR(full.variance / ref.variance, 1.0, 1e-9);
}

TEST(Sharpness, RowBatchedUpdateMatchesPerSampleWelford) {
  const cv::Mat g = test::photo("aero1.jpg");
  for (auto [rs, cs] : {std::pair{2, 3}, std::pair{3, 3}, std::pair{1, 4}}) {
    const auto a = sampledLaplacianVariance(GrayView::of(g), rs, cs);
    const auto b = welfordPerSample(g, rs, cs);
    EXPECT_EQ(a.count, b.count);
    EXPECT_NEAR(a.variance / b.variance, 1.0, 1e-9);
  }
}

TEST(Sharpness, VectorisedRowsMatchTheScalarDefinitionAtEveryWidth) {
  cv::RNG rng(3);
  for (int w = 3; w < 260; w += 7) {
    cv::Mat g(9, w, CV_8UC1);
    rng.fill(g, cv::RNG::UNIFORM, 0, 256);
    const auto a = sampledLaplacianVariance(GrayView::of(g), 2, 3);
    const auto b = welfordPerSample(g, 2, 3);
    ASSERT_EQ(a.count, b.count) << w;
    EXPECT_NEAR(a.mean, b.mean, 1e-9) << w;
    EXPECT_NEAR(a.variance, b.variance, 1e-6 * b.variance) << w;
  }
  // Extreme values: a checkerboard of 0 and 255 (|L| = 1020) over a wide row.
  cv::Mat c(5, 8000, CV_8UC1);
  for (int y = 0; y < c.rows; ++y)
    for (int x = 0; x < c.cols; ++x) c.at<uchar>(y, x) = ((x + y) % 2) ? 255 : 0;
  const auto a = sampledLaplacianVariance(GrayView::of(c), 2, 3);
  const auto b = welfordPerSample(c, 2, 3);
  EXPECT_NEAR(a.variance, b.variance, 1e-6 * b.variance);
}

TEST(Sharpness, BlurLowersTheScoreMonotonically) {
  const cv::Mat g = test::photo("aero3.jpg");
  double last = sampledLaplacianVariance(GrayView::of(g), 2, 3).variance;
  for (double sigma : {0.8, 1.5, 3.0}) {
    cv::Mat b;
    cv::GaussianBlur(g, b, cv::Size(), sigma);
    const double v = sampledLaplacianVariance(GrayView::of(b), 2, 3).variance;
    EXPECT_LT(v, 0.7 * last) << "sigma " << sigma;
    last = v;
  }
}

TEST(Sharpness, TinyAndEmptyImagesScoreZero) {
  const cv::Mat tiny(2, 2, CV_8UC1, cv::Scalar(7));
  EXPECT_EQ(sampledLaplacianVariance(GrayView::of(tiny), 2, 3).count, 0);
  EXPECT_EQ(sampledLaplacianVariance(GrayView{}, 2, 3).variance, 0.0);
}

TEST(Sharpness, AUniformFrameIsNeverSharpWhateverTheThreshold) {
  // A lens cap or a black frame scores 0: with a floor (adaptive) or a threshold
  // (absolute) of 0 it would pass 0 >= 0, and count in the adaptive statistic.
  const cv::Mat black(270, 480, CV_8UC1, cv::Scalar(0));
  const cv::Mat photo = test::photo("baboon.jpg");
  for (const BlurMode mode : {BlurMode::Adaptive, BlurMode::Absolute}) {
    SharpnessConfig c;
    c.mode = mode;
    c.floor = 0.0;
    c.absoluteThreshold = 0.0;
    c.warmup = 1;
    SharpnessScorer s(c);
    for (int i = 0; i < 3; ++i) {
      const auto r = s.evaluate(GrayView::of(black));
      EXPECT_EQ(r.score, 0.0);
      EXPECT_FALSE(r.sharp) << static_cast<int>(mode);
    }
    // and counted no frame towards the warm-up: still warming up
    if (mode == BlurMode::Adaptive) {
      EXPECT_TRUE(s.warmingUp());
    }
    EXPECT_TRUE(s.evaluate(GrayView::of(photo)).sharp);
  }
}

TEST(Sharpness, AbsoluteModeUsesTheFixedThreshold) {
  SharpnessConfig c;
  c.mode = BlurMode::Absolute;
  c.absoluteThreshold = 1e9;
  SharpnessScorer s(c);
  const cv::Mat g = test::photo("baboon.jpg");
  const auto r = s.evaluate(GrayView::of(g));
  EXPECT_FALSE(r.sharp);
  EXPECT_EQ(r.threshold, 1e9);
}

TEST(Sharpness, AdaptiveThresholdFollowsTheSourceAndRejectsBlurredFrames) {
  // Two sources of very different texture: one setting must work for both.
  for (const char* name : {"aero1.jpg", "fruits.jpg"}) {
    SharpnessScorer s{SharpnessConfig{}};
    const cv::Mat g = test::photo(name);
    cv::Mat blurred;
    cv::GaussianBlur(g, blurred, cv::Size(), 2.5);
    // Warm up on sharp frames with slight variation (noise).
    cv::RNG rng(1);
    for (int i = 0; i < 30; ++i) {
      cv::Mat n(g.size(), CV_8UC1);
      rng.fill(n, cv::RNG::NORMAL, 0, 2);
      cv::Mat f;
      cv::add(g, n, f);
      EXPECT_TRUE(s.evaluate(GrayView::of(f)).sharp) << name << " frame " << i;
    }
    const auto r = s.evaluate(GrayView::of(blurred));
    EXPECT_FALSE(r.sharp) << name << " blurred score " << r.score << " thr " << r.threshold;
    EXPECT_GT(r.threshold, SharpnessConfig{}.floor);
  }
}

TEST(Sharpness, AStretchOfBlurIsNotLearntButAPlainerGroundIs) {
  // The statistic follows what it sees, blurred frames too: a long stretch of blur
  // would become the new normal. The threshold falls by half over half a window at
  // most, so blur a third as sharp stays rejected for the window and more; a ground
  // with half the contrast (a quarter of the score, every frame sharp) is taken
  // again within two windows.
  const cv::Mat g = test::photo("aero1.jpg");
  cv::Mat small;
  cv::resize(g, small, cv::Size(480, 270), 0, 0, cv::INTER_AREA);
  cv::Mat blurred, plain;
  cv::GaussianBlur(small, blurred, cv::Size(), 1.5);
  small.convertTo(plain, -1, 0.5, 64);
  const SharpnessConfig cfg;
  for (const bool blur : {true, false}) {
    SCOPED_TRACE(blur ? "blur" : "plainer ground");
    SharpnessScorer s{cfg};
    cv::RNG rng(7);
    const auto frame = [&rng](const cv::Mat& base) {
      cv::Mat n(base.size(), CV_8UC1), f;
      rng.fill(n, cv::RNG::NORMAL, 0, 1.0);
      cv::add(base, n, f);
      return f;
    };
    double sharpScore = 0;
    for (int i = 0; i < cfg.window; ++i) sharpScore = s.evaluate(GrayView::of(frame(small))).score;
    int firstTaken = -1;
    for (int i = 0; i < 3 * cfg.window && firstTaken < 0; ++i) {
      const auto r = s.evaluate(GrayView::of(frame(blur ? blurred : plain)));
      if (i == 0) {
        EXPECT_FALSE(r.sharp);
        EXPECT_LT(r.score, (blur ? 0.35 : 0.3) * sharpScore) << r.score << " vs " << sharpScore;
      }
      if (r.sharp) firstTaken = i;
    }
    if (blur) {
      EXPECT_TRUE(firstTaken < 0 || firstTaken > cfg.window) << firstTaken;
    } else {
      EXPECT_GE(firstTaken, 0);
      EXPECT_LE(firstTaken, 2 * cfg.window);
    }
  }
}

TEST(Sharpness, FramesUnderTheFloorNeitherEndTheWarmUpNorLowerTheStatistic) {
  // A dark start (auto-exposure settling, a lens cap): black frames score 0.
  SharpnessScorer s{SharpnessConfig{}};
  const cv::Mat black = cv::Mat::zeros(270, 480, CV_8UC1);
  for (int i = 0; i < 20; ++i) EXPECT_FALSE(s.evaluate(GrayView::of(black)).sharp);
  EXPECT_TRUE(s.warmingUp());
  EXPECT_EQ(s.threshold(), SharpnessConfig{}.floor);
}

TEST(Sharpness, OneAdaptiveSettingWorksAcrossResolutions) {
  // The same scene at 1/4, 1/2 and full size: the Laplacian's variance changes
  // several-fold with the scale, so no absolute threshold fits all three; the
  // adaptive one, with default settings, follows each and rejects its blur.
  const cv::Mat full = test::photo("aero3.jpg");
  std::vector<double> sharpScores;
  for (const double scale : {0.25, 0.5, 1.0}) {
    cv::Mat g;
    cv::resize(full, g, cv::Size(), scale, scale, cv::INTER_AREA);
    cv::Mat blurred;
    cv::GaussianBlur(g, blurred, cv::Size(), 2.0 * scale + 0.8);
    SharpnessScorer s{SharpnessConfig{}};
    cv::RNG rng(3);
    for (int i = 0; i < 30; ++i) {
      cv::Mat n(g.size(), CV_8UC1);
      rng.fill(n, cv::RNG::NORMAL, 0, 2);
      cv::Mat f;
      cv::add(g, n, f);
      const auto r = s.evaluate(GrayView::of(f));
      EXPECT_TRUE(r.sharp) << "scale " << scale << " frame " << i;
      if (i == 29) sharpScores.push_back(r.score);
    }
    const auto r = s.evaluate(GrayView::of(blurred));
    EXPECT_FALSE(r.sharp) << "scale " << scale << " blurred " << r.score << " thr " << r.threshold;
  }
  ASSERT_EQ(sharpScores.size(), 3u);
  EXPECT_GT(sharpScores[0], 2.0 * sharpScores[2]);  // no single absolute threshold fits
}

TEST(Sharpness, AdaptiveFloorHoldsOnAFeaturelessSource) {
  SharpnessScorer s{SharpnessConfig{}};
  const cv::Mat flat(480, 640, CV_8UC1, cv::Scalar(128));
  for (int i = 0; i < 20; ++i) EXPECT_FALSE(s.evaluate(GrayView::of(flat)).sharp);
  EXPECT_EQ(s.threshold(), SharpnessConfig{}.floor);
}

TEST(Sharpness, ReducedResolutionAnalysisStillSeparatesBlur) {
  SharpnessConfig c;
  c.analysisWidth = 320;
  SharpnessScorer s(c);
  const cv::Mat g = test::photo("building.jpg");
  cv::Mat b;
  cv::GaussianBlur(g, b, cv::Size(), 4.0);
  EXPECT_GT(s.score(GrayView::of(g)), 2.0 * s.score(GrayView::of(b)));
}

TEST(Sharpness, ConfigValidationNamesTheBadSetting) {
  SharpnessConfig c;
  EXPECT_TRUE(c.validate().empty());
  c.rowStep = 0;
  EXPECT_NE(c.validate().find("row step"), std::string::npos);
  c = {};
  c.quantile = 1.5;
  EXPECT_NE(c.validate().find("quantile"), std::string::npos);
}

}  // namespace
}  // namespace keyframed
