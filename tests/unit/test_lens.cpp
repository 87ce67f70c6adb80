#include <cmath>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

#include "core/lens.h"
#include "core/overlap.h"
#include "photos.h"

namespace keyframed {
namespace {

LensModel fisheyeLens() {
  return {LensModel::Kind::Fisheye,
          480,
          270,
          220.0,
          221.5,
          241.25,
          133.75,
          {0.032, -0.0081, 0.0017, -0.0003, 0.0}};
}

LensModel pinholeLens() {
  return {LensModel::Kind::Pinhole,
          640,
          480,
          520.0,
          518.0,
          322.5,
          241.0,
          {-0.21, 0.06, 0.0012, -0.0009, -0.008}};  // k1 k2 p1 p2 k3
}

// Rays (camera frame, in front) spread over the field of view.
std::vector<cv::Point3d> rays(double maxDeg) {
  std::vector<cv::Point3d> out;
  for (int i = 0; i < 200; ++i) {
    const double theta = maxDeg * M_PI / 180.0 * std::sqrt((i % 20 + 0.5) / 20.0);
    const double phi = 2 * M_PI * (i / 20) / 10.0 + 0.3 * (i % 7);
    out.emplace_back(std::sin(theta) * std::cos(phi), std::sin(theta) * std::sin(phi),
                     std::cos(theta));
  }
  return out;
}

TEST(Lens, FisheyeAgreesWithOpenCvBothWays) {
  const LensModel l = fisheyeLens();
  const std::vector<cv::Point3d> r = rays(75.0);
  std::vector<cv::Point2d> px;
  const cv::Matx33d k(l.fx, 0, l.cx, 0, l.fy, l.cy, 0, 0, 1);
  cv::fisheye::projectPoints(r, px, cv::Vec3d(), cv::Vec3d(), k,
                             cv::Vec4d(l.k[0], l.k[1], l.k[2], l.k[3]));
  for (std::size_t i = 0; i < r.size(); ++i) {
    const cv::Point2d ideal(l.fx * r[i].x / r[i].z + l.cx, l.fy * r[i].y / r[i].z + l.cy);
    const cv::Point2d d = l.distort(ideal);
    EXPECT_NEAR(d.x, px[i].x, 1e-6) << i;
    EXPECT_NEAR(d.y, px[i].y, 1e-6) << i;
    cv::Point2d back;
    ASSERT_TRUE(l.undistort(px[i], back)) << i;
    EXPECT_NEAR(back.x, ideal.x, 1e-5 * std::max(1.0, std::abs(ideal.x - l.cx))) << i;
    EXPECT_NEAR(back.y, ideal.y, 1e-5 * std::max(1.0, std::abs(ideal.y - l.cy))) << i;
  }
  // Past 80 degrees there is no ideal pixel.
  cv::Point2d ideal;
  const double theta = 85.0 * M_PI / 180.0;
  const double thetaD = theta * (1 + 0.032 * theta * theta - 0.0081 * std::pow(theta, 4) +
                                 0.0017 * std::pow(theta, 6) - 0.0003 * std::pow(theta, 8));
  EXPECT_FALSE(l.undistort({l.cx + l.fx * thetaD, l.cy}, ideal));
}

TEST(Lens, PinholeAgreesWithOpenCvBothWays) {
  const LensModel l = pinholeLens();
  const std::vector<cv::Point3d> r = rays(30.0);
  std::vector<cv::Point2d> px;
  const cv::Matx33d k(l.fx, 0, l.cx, 0, l.fy, l.cy, 0, 0, 1);
  cv::projectPoints(r, cv::Vec3d(), cv::Vec3d(), k, std::vector<double>(l.k.begin(), l.k.end()),
                    px);
  for (std::size_t i = 0; i < r.size(); ++i) {
    const cv::Point2d ideal(l.fx * r[i].x / r[i].z + l.cx, l.fy * r[i].y / r[i].z + l.cy);
    const cv::Point2d d = l.distort(ideal);
    EXPECT_NEAR(d.x, px[i].x, 1e-6) << i;
    EXPECT_NEAR(d.y, px[i].y, 1e-6) << i;
    cv::Point2d back;
    ASSERT_TRUE(l.undistort(px[i], back)) << i;
    EXPECT_NEAR(back.x, ideal.x, 1e-3) << i;
    EXPECT_NEAR(back.y, ideal.y, 1e-3) << i;
  }
}

TEST(Lens, AStrongPincushionIsUndistortedWhereTheFixedPointWouldDiverge) {
  // k1 = 20 (a calibration may give tens): cv::undistortPoints' fixed-point iteration
  // overshoots further each step out here; every point of the image still comes back.
  LensModel l = pinholeLens();
  l.k = {20.0, 0.0, 0.001, -0.002, 0.0};
  int checked = 0;
  for (double u = 0.0; u <= l.width; u += l.width / 8.0) {
    for (double v = 0.0; v <= l.height; v += l.height / 6.0) {
      const cv::Point2d ideal(l.cx + (u - l.cx) * 0.3, l.cy + (v - l.cy) * 0.3);
      const cv::Point2d d = l.distort(ideal);
      cv::Point2d back;
      ASSERT_TRUE(l.undistort(d, back)) << u << "," << v;
      EXPECT_NEAR(back.x, ideal.x, 1e-3) << u << "," << v;
      EXPECT_NEAR(back.y, ideal.y, 1e-3) << u << "," << v;
      ++checked;
    }
  }
  EXPECT_EQ(checked, 9 * 7);
}

TEST(Lens, APixelPastABarrelLensFoldHasNoIdealPoint) {
  // r (1 - 0.3 r^2) is at most 0.703 (at r = 1.054): a pixel further out is no
  // point's image. Newton's method could land across the centre or past the fold
  // on a point the polynomial maps there too: not an answer.
  const LensModel l{LensModel::Kind::Pinhole,  640, 480, 400.0, 400.0, 320.0, 240.0,
                    {-0.3, 0.0, 0.0, 0.0, 0.0}};
  cv::Point2d back;
  for (const double rd : {0.72, 0.75, 0.8}) {
    const cv::Point2d px(320.0 + 400.0 * 0.8 * rd, 240.0 + 400.0 * 0.6 * rd);
    EXPECT_FALSE(l.undistort(px, back)) << rd << ": " << back;
  }
  // Inside the fold every pixel comes back.
  for (const double r : {0.2, 0.6, 1.0}) {
    const cv::Point2d ideal(320.0 + 400.0 * 0.8 * r, 240.0 + 400.0 * 0.6 * r);
    ASSERT_TRUE(l.undistort(l.distort(ideal), back)) << r;
    EXPECT_NEAR(back.x, ideal.x, 1e-3) << r;
    EXPECT_NEAR(back.y, ideal.y, 1e-3) << r;
  }
}

TEST(Lens, MonotonicRadiusIsWhereTheDistortionFoldsBack) {
  // A strong barrel lens: r (1 + k1 r^2) turns back at r = 1 / sqrt(-3 k1).
  LensModel l = pinholeLens();
  l.k = {-0.3, 0.0, 0.0, 0.0, 0.0};
  EXPECT_NEAR(l.monotonicRadius(), 1.0 / std::sqrt(0.9), 0.002);
  // Beyond it, a far ray distorts back inside the image, onto the pixel of a ray
  // inside the fold: the pixel cannot tell them apart, which is why the overlap
  // counts no sample past monotonicRadius() as seen.
  const double r = 1.6;  // normalised radius past the fold
  const cv::Point2d far = l.distort({l.cx + l.fx * r, l.cy});
  EXPECT_LT(far.x, l.cx + l.fx * 1.0);
  cv::Point2d back;
  ASSERT_TRUE(l.undistort(far, back));
  EXPECT_LT((back.x - l.cx) / l.fx, l.monotonicRadius());
  // A fisheye whose polynomial never turns back reaches the 80-degree limit.
  EXPECT_NEAR(fisheyeLens().monotonicRadius(), std::tan(80.0 * M_PI / 180.0), 0.01);
  EXPECT_TRUE(std::isinf(LensModel{}.monotonicRadius()));
}

TEST(Lens, ScalingAndValidation) {
  const LensModel l = fisheyeLens();
  const LensModel half = l.scaledTo(240, 135);
  EXPECT_DOUBLE_EQ(half.fx, 110.0);
  EXPECT_DOUBLE_EQ(half.cx, (241.25 + 0.5) / 2 - 0.5);
  EXPECT_STREQ(l.invalidReason(), "");
  LensModel bad = l;
  bad.fx = 0;
  EXPECT_STRNE(bad.invalidReason(), "");
  bad = l;
  bad.k[1] = NAN;
  EXPECT_STRNE(bad.invalidReason(), "");
  OverlapConfig c;
  c.lens = bad;
  EXPECT_NE(c.validate(), "");
  EXPECT_EQ(OverlapConfig{}.validate(), "");  // no lens: valid
}

// A nadir fisheye camera Z strip-pixels above a flat "ground" of real photographs,
// moving along it: each frame rendered through the lens, and the true share of the
// first frame's pixels still in view, from the geometry.
struct FisheyeFlight {
  LensModel lens = fisheyeLens();
  cv::Mat strip = test::photoStrip();
  double z = 300.0;  // height, strip pixels
  double y = 240.0;  // the camera's track across the strip

  cv::Point2d ground(cv::Point2d pixel, double x) const {
    cv::Point2d ideal;
    if (!lens.undistort(pixel, ideal)) return {NAN, NAN};
    return {x + z * (ideal.x - lens.cx) / lens.fx, y + z * (ideal.y - lens.cy) / lens.fy};
  }

  cv::Mat render(double x) const {
    cv::Mat mx(lens.height, lens.width, CV_32F), my(lens.height, lens.width, CV_32F);
    for (int v = 0; v < lens.height; ++v) {
      for (int u = 0; u < lens.width; ++u) {
        const cv::Point2d g = ground({double(u), double(v)}, x);
        mx.at<float>(v, u) = static_cast<float>(g.x);
        my.at<float>(v, u) = static_cast<float>(g.y);
      }
    }
    cv::Mat out;
    cv::remap(strip, out, mx, my, cv::INTER_LINEAR, cv::BORDER_REFLECT);
    return out;
  }

  double truth(double x0, double x) const {
    int seen = 0, all = 0;
    for (int v = 0; v < 54; ++v) {
      for (int u = 0; u < 96; ++u) {
        const cv::Point2d p((u + 0.5) * lens.width / 96.0 - 0.5,
                            (v + 0.5) * lens.height / 54.0 - 0.5);
        const cv::Point2d g = ground(p, x0);
        if (std::isnan(g.x)) continue;
        ++all;
        const cv::Point2d ideal(lens.cx + lens.fx * (g.x - x) / z,
                                lens.cy + lens.fy * (g.y - y) / z);
        const cv::Point2d q = lens.distort(ideal);
        seen += q.x >= -0.5 && q.y >= -0.5 && q.x < lens.width - 0.5 && q.y < lens.height - 0.5;
      }
    }
    return static_cast<double>(seen) / all;
  }
};

// Largest error of the geometric overlap against the truth over a flight.
// With `half`, the estimator sees the frames at half size (as the selector's analysis
// resolution would give them) and scales the lens itself.
double worstError(const FisheyeFlight& f, const OverlapConfig& config, int* validFrames,
                  bool half = false) {
  auto est = OverlapEstimator::create(config);
  const double x0 = 600.0, step = 8.0;
  double worst = 0.0;
  *validFrames = 0;
  for (int i = 0; i <= 50; ++i) {
    cv::Mat view = f.render(x0 + i * step);
    if (half) cv::resize(view, view, cv::Size(view.cols / 2, view.rows / 2), 0, 0, cv::INTER_AREA);
    const OverlapResult r = est->observe(GrayView::of(view));
    if (i == 0) {
      est->setReferenceToCurrent();
      continue;
    }
    if (!r.valid) continue;
    ++*validFrames;
    worst = std::max(worst, std::abs(r.overlap - f.truth(x0, x0 + i * step)));
  }
  return worst;
}

TEST(GeometricOverlap, FollowsAFisheyeFlightThroughTheLens) {
  const FisheyeFlight f;
  ASSERT_FALSE(f.strip.empty());
  // The flight parts as far as a keyframe's overlap band goes.
  EXPECT_LT(f.truth(600.0, 1000.0), 0.70);
  OverlapConfig through;
  through.lens = f.lens;
  int valid = 0;
  const double withLens = worstError(f, through, &valid);
  EXPECT_EQ(valid, 50);
  EXPECT_LT(withLens, 0.03);
  // The same flight taken as a distortion-free pinhole's: the homography cannot hold,
  // and the overlap is off by more.
  int validRaw = 0;
  const double raw = worstError(f, OverlapConfig{}, &validRaw);
  std::printf(
      "fisheye flight: worst overlap error %.3f through the lens, %.3f without "
      "(%d frames tracked)\n",
      withLens, raw, validRaw);
  EXPECT_GT(raw, withLens);
  // The same at half the size: the lens scaled to the frames it is given.
  int validHalf = 0;
  const double halfSize = worstError(f, through, &validHalf, true);
  std::printf("at half size: %.3f through the lens\n", halfSize);
  EXPECT_EQ(validHalf, 50);
  EXPECT_LT(halfSize, 0.03);
}

}  // namespace
}  // namespace keyframed
