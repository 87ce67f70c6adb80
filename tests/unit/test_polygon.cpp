#include <gtest/gtest.h>

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
  EXPECT_LT(visibleFraction(cv::Matx33d(1, 0, 0, 0, 1, 0, -0.01, 0, 1), 640, 360), 0.0);  // behind
}

}  // namespace
}  // namespace keyframed
