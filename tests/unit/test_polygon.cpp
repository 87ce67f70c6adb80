#include <gtest/gtest.h>

#include <string>

#include <opencv2/core.hpp>

#include "core/polygon.h"

namespace keyframed {
namespace {

cv::Matx33d translate(double tx, double ty) {
  return {1, 0, tx, 0, 1, ty, 0, 0, 1};
}

TEST(Polygon, IdentityIsFullOverlap) {
  EXPECT_NEAR(visibleFraction(cv::Matx33d::eye(), 640, 360), 1.0, 1e-12);
}

TEST(Polygon, TranslationLeavesTheExpectedFraction) {
  EXPECT_NEAR(visibleFraction(translate(0.3 * 640, 0), 640, 360), 0.7, 1e-9);
  EXPECT_NEAR(visibleFraction(translate(-0.2 * 640, 0.5 * 360), 640, 360), 0.8 * 0.5, 1e-9);
  EXPECT_NEAR(visibleFraction(translate(700, 0), 640, 360), 0.0, 1e-12);
}

TEST(Polygon, ZoomOutShowsAllOfTheReference) {
  // Current frame covers twice the ground: maps into a bigger rectangle in the
  // reference, which is then fully visible.
  const cv::Matx33d s(2, 0, -320, 0, 2, -180, 0, 0, 1);
  EXPECT_NEAR(visibleFraction(s, 640, 360), 1.0, 1e-9);
  // Zoom in by 2: a quarter of the reference remains visible.
  const cv::Matx33d z(0.5, 0, 160, 0, 0.5, 90, 0, 0, 1);
  EXPECT_NEAR(visibleFraction(z, 640, 360), 0.25, 1e-9);
}

TEST(Polygon, RotationAboutTheCentre) {
  const double a = CV_PI / 2;
  const double c = std::cos(a), s = std::sin(a);
  // 90 degrees about the centre of a square: full overlap.
  const cv::Matx33d r(c, -s, 50 - c * 50 + s * 50, s, c, 50 - s * 50 - c * 50, 0, 0, 1);
  EXPECT_NEAR(visibleFraction(r, 100, 100), 1.0, 1e-9);
}

TEST(Polygon, DegenerateMappingsAreRejected) {
  EXPECT_LT(visibleFraction(cv::Matx33d(1, 0, 0, 0, 1, 0, 0, 0, 0), 640, 360), 0.0);  // at infinity
  EXPECT_LT(visibleFraction(cv::Matx33d(-1, 0, 640, 0, 1, 0, 0, 0, 1), 640, 360), 0.0);  // mirrored
}

// A matrix for a failure message (cv::Matx's operator<< is not in the headers the
// core builds with).
std::string text(const cv::Matx33d& m) {
  std::string out;
  for (int i = 0; i < 9; ++i) out += (i > 0 ? " " : "") + std::to_string(m.val[i]);
  return out;
}

// The fraction of reference pixels (a fine grid) that land in front of the current
// camera and inside its image: what visibleFraction computes exactly.
double sampledFraction(const cv::Matx33d& curToRef, double w, double h) {
  const cv::Matx33d refToCur = curToRef.inv();
  int in = 0, all = 0;
  for (double y = 0.5; y < h; y += 1.0) {
    for (double x = 0.5; x < w; x += 1.0) {
      ++all;
      const cv::Vec3d v = refToCur * cv::Vec3d(x, y, 1.0);
      if (!(v[2] > 0.0)) continue;
      const double u = v[0] / v[2], t = v[1] / v[2];
      if (u >= 0 && u < w && t >= 0 && t < h) ++in;
    }
  }
  return static_cast<double>(in) / all;
}

TEST(Polygon, PartOfTheCurrentImagePastTheReferencesHorizon) {
  // Corners of the current image that map behind the reference (a camera tilted up
  // from a nadir keyframe) are no reason to call the overlap lost: the whole
  // reference is in view here, and part of it in the others.
  const cv::Matx33d behind(1, 0, 0, 0, 1, 0, -0.01, 0, 1);
  EXPECT_NEAR(visibleFraction(behind, 640, 360), 1.0, 1e-9);
  EXPECT_NEAR(sampledFraction(behind, 640, 360), 1.0, 1e-9);
  const cv::Matx33d tilted[] = {
      {1, 0, 60, 0, 1, 20, -0.008, 0, 1},
      {0.9, 0.1, 10, -0.05, 1.1, -8, 0, -0.015, 1},
      {1, 0, 30, 0, 1, 10, 0.002, -0.014, 1},
  };
  for (const cv::Matx33d& m : tilted) {
    Polygon corners;
    const std::string name = text(m);
    ASSERT_FALSE(mapRectangle(m, 160, 90, corners)) << name;  // a corner past the horizon
    const double exact = visibleFraction(m, 160, 90);
    const double sampled = sampledFraction(m, 160, 90);
    EXPECT_GT(sampled, 0.05) << name;
    EXPECT_LT(sampled, 0.999) << name;
    EXPECT_NEAR(exact, sampled, 0.01) << name;
  }
}

}  // namespace
}  // namespace keyframed
