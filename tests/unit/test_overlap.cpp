#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

#include "core/geometric_overlap.h"
#include "core/overlap.h"
#include "photos.h"

namespace keyframed {
namespace {

OverlapConfig geometric() {
  OverlapConfig c;
  c.mode = OverlapMode::Geometric;
  return c;
}

TEST(GeometricOverlap, FollowsAPanAcrossRealPhotos) {
  const cv::Mat strip = test::photoStrip();
  ASSERT_FALSE(strip.empty());
  auto est = OverlapEstimator::create(geometric());
  const double step = 6.0;  // px per frame
  const int w = 480;
  for (int i = 0; i <= 40; ++i) {
    const cv::Mat v = test::viewAt(strip, 200 + i * step, w);
    const OverlapResult r = est->observe(GrayView::of(v));
    if (i == 0) {
      EXPECT_FALSE(r.valid);  // no reference yet
      est->setReferenceToCurrent();
      continue;
    }
    ASSERT_TRUE(r.valid) << "frame " << i;
    const double truth = 1.0 - i * step / w;
    EXPECT_NEAR(r.overlap, truth, 0.02) << "frame " << i;
    EXPECT_GE(r.inliers, 15);
  }
}

TEST(GeometricOverlap, AStillCameraStaysAtFullOverlap) {
  const cv::Mat strip = test::photoStrip();
  auto est = OverlapEstimator::create(geometric());
  const cv::Mat v = test::viewAt(strip, 900);
  est->observe(GrayView::of(v));
  est->setReferenceToCurrent();
  cv::RNG rng(3);
  for (int i = 0; i < 150; ++i) {
    cv::Mat noise(v.size(), CV_8UC1), f;
    rng.fill(noise, cv::RNG::NORMAL, 0, 2);
    cv::add(v, noise, f);
    const OverlapResult r = est->observe(GrayView::of(f));
    ASSERT_TRUE(r.valid);
    EXPECT_GT(r.overlap, 0.97) << "drifted at frame " << i;
  }
}

TEST(GeometricOverlap, NewTracksSpreadOverTheWholeImage) {
  // Textured from top to bottom: each third of the image gets its share of the
  // tracks, or the homography is fitted on part of the image and guessed for the rest.
  const cv::Mat strip = test::photoStrip();
  ASSERT_FALSE(strip.empty());
  for (const int maxTracks : {200, 120, 400}) {
    OverlapConfig c = geometric();
    c.maxTracks = maxTracks;
    c.minTracks = std::min(c.minTracks, maxTracks);
    GeometricOverlap est(c);
    const cv::Mat v = test::viewAt(strip, 900);
    est.observe(GrayView::of(v));
    const auto tracks = est.tracks();
    ASSERT_GE(static_cast<int>(tracks.size()), maxTracks * 3 / 4) << maxTracks;
    int thirds[3] = {0, 0, 0};
    for (const cv::Point2f& p : tracks)
      ++thirds[std::clamp(static_cast<int>(p.y * 3 / v.rows), 0, 2)];
    for (int i = 0; i < 3; ++i) {
      EXPECT_GE(thirds[i], static_cast<int>(tracks.size()) / 5)
          << "third " << i << " of " << maxTracks << " tracks: " << thirds[0] << " " << thirds[1]
          << " " << thirds[2];
    }
  }
}

TEST(GeometricOverlap, CandidateBecomesTheReference) {
  const cv::Mat strip = test::photoStrip();
  auto est = OverlapEstimator::create(geometric());
  for (int i = 0; i <= 30; ++i) {
    const OverlapResult r = est->observe(GrayView::of(test::viewAt(strip, 300 + i * 5.0)));
    if (i == 0) est->setReferenceToCurrent();
    if (i == 10) {
      ASSERT_TRUE(r.valid);
      est->markCandidate();
    }
  }
  // The current frame (30) is 20 steps of 5 px from the candidate (10).
  const OverlapResult r = est->setReferenceToCandidate();
  ASSERT_TRUE(r.valid);
  EXPECT_NEAR(r.overlap, 1.0 - 100.0 / 480.0, 0.02);
}

TEST(GeometricOverlap, LosesTrackingOnAFeaturelessFrame) {
  const cv::Mat strip = test::photoStrip();
  auto est = OverlapEstimator::create(geometric());
  est->observe(GrayView::of(test::viewAt(strip, 500)));
  est->setReferenceToCurrent();
  const cv::Mat flat(270, 480, CV_8UC1, cv::Scalar(90));
  const OverlapResult r = est->observe(GrayView::of(flat));
  EXPECT_FALSE(r.valid);
}

TEST(GeometricOverlap, MeasuresHowFarTheImageTurnsEachStep) {
  // A view of a real photo turned about its centre a little more each frame, as a
  // nadir camera yawing would see it; each step's turn is reported, sign included.
  const cv::Mat strip = test::photoStrip();
  const cv::Mat view = test::viewAt(strip, 700, 640, 480);
  const cv::Rect inner(80, 60, 480, 360);  // inside every turned copy: no black corners
  auto est = OverlapEstimator::create(geometric());
  double angle = 0.0;
  for (int i = 0; i <= 12; ++i) {
    const double stepDeg = i % 2 == 0 ? 1.5 : -0.7;
    if (i > 0) angle += stepDeg;
    // getRotationMatrix2D turns by +angle anticlockwise on screen (y down), which
    // takes +x toward -y: the opposite of stepRotationRad's positive sense.
    cv::Mat turned;
    cv::warpAffine(view, turned, cv::getRotationMatrix2D(cv::Point2f(320, 240), angle, 1.0),
                   view.size(), cv::INTER_LINEAR);
    const OverlapResult r = est->observe(GrayView::of(turned(inner).clone()));
    if (i == 0) {
      EXPECT_TRUE(std::isnan(r.stepRotationRad));
      continue;
    }
    ASSERT_FALSE(std::isnan(r.stepRotationRad)) << "frame " << i;
    EXPECT_NEAR(r.stepRotationRad * 180.0 / M_PI, -stepDeg, 0.03) << "frame " << i;
  }
}

TEST(PaperOverlap, DistanceGrowsAsTheViewsPart) {
  const cv::Mat strip = test::photoStrip();
  OverlapConfig c;
  c.mode = OverlapMode::Paper;
  auto est = OverlapEstimator::create(c);
  est->observe(GrayView::of(test::viewAt(strip, 200)));
  est->setReferenceToCurrent();
  const double d10 = est->observe(GrayView::of(test::viewAt(strip, 200 + 0.1 * 480))).paperDistance;
  const double d50 = est->observe(GrayView::of(test::viewAt(strip, 200 + 0.5 * 480))).paperDistance;
  EXPECT_LT(d10, d50);
  EXPECT_GT(d50 - d10, 5.0);
}

TEST(Overlap, ConfigValidation) {
  OverlapConfig c;
  EXPECT_TRUE(c.validate().empty());
  c.minTracks = c.maxTracks + 1;
  EXPECT_FALSE(c.validate().empty());
  // Tracks are replenished below minTracks: fewer than minInliers would lose the track
  // first. And the paper mode cannot match more features than ORB finds.
  c = OverlapConfig{};
  c.minInliers = c.minTracks + 1;
  EXPECT_EQ(c.validate(), "min inliers must be 4..min tracks");
  c = OverlapConfig{};
  c.paperMinMatches = c.orbFeatures + 1;
  EXPECT_EQ(c.validate(), "paper minimum matches must be 4..ORB features");
}

}  // namespace
}  // namespace keyframed
