#include <gtest/gtest.h>
#include <opencv2/calib3d.hpp>

#include "core/homography.h"
#include "geometry.h"

namespace keyframed {
namespace {

TEST(Homography, RecoversAProjectiveMapDespiteOutliers) {
  const cv::Matx33d truth(1.02, 0.03, 12.5, -0.02, 0.99, -7.0, 1e-4, -5e-5, 1.0);
  cv::RNG rng(5);
  std::vector<cv::Point2f> src, dst;
  for (int i = 0; i < 300; ++i) {
    const cv::Point2f p(rng.uniform(0.f, 640.f), rng.uniform(0.f, 360.f));
    cv::Point2f q = test::applyHomography(truth, p);
    q += cv::Point2f(static_cast<float>(rng.gaussian(0.3)), static_cast<float>(rng.gaussian(0.3)));
    if (i % 5 == 0) q = {rng.uniform(0.f, 640.f), rng.uniform(0.f, 360.f)};  // 20 % outliers
    src.push_back(p);
    dst.push_back(q);
  }
  RansacHomography r;
  std::vector<unsigned char> mask;
  const HomographyFit fit = r.fit(src, dst, 1.5, mask);
  ASSERT_TRUE(fit.ok);
  EXPECT_GE(fit.inliers, 230);
  EXPECT_LE(fit.inliers, 245);
  for (int i = 0; i < 300; i += 5) EXPECT_EQ(mask[static_cast<std::size_t>(i)], 0) << i;
  for (const cv::Point2f p : {cv::Point2f(0, 0), cv::Point2f(640, 360), cv::Point2f(320, 10)}) {
    const cv::Point2f a = test::applyHomography(fit.h, p), b = test::applyHomography(truth, p);
    EXPECT_NEAR(a.x, b.x, 0.3);
    EXPECT_NEAR(a.y, b.y, 0.3);
  }
  // Agrees with OpenCV's estimator on the same data.
  const cv::Matx33d cvH(cv::findHomography(src, dst, cv::RANSAC, 1.5));
  const cv::Point2f a = test::applyHomography(fit.h, {500, 300}),
                    b = test::applyHomography(cvH, {500, 300});
  EXPECT_NEAR(a.x, b.x, 0.3);
  EXPECT_NEAR(a.y, b.y, 0.3);
}

TEST(Homography, APoorFirstSampleAmongManyPointsDoesNotEndTheSearch) {
  // 800 points, 60 % outliers: the first sample almost surely holds an outlier
  // and explains only itself, an inlier ratio that asks for ~10^10 samples. The
  // search must go on to its cap (the ratio once made an int overflow and stop it:
  // a lost track on a sharp frame of the nadir flight).
  const cv::Matx33d truth(0.998, -0.004, 0.5, 0.0, 0.997, 4.0, -5e-7, -1.7e-5, 1.0);
  cv::RNG rng(11);
  std::vector<cv::Point2f> src, dst;
  for (int i = 0; i < 800; ++i) {
    const cv::Point2f p(rng.uniform(0.f, 480.f), rng.uniform(0.f, 270.f));
    src.push_back(p);
    dst.push_back(i % 5 < 2 ? test::applyHomography(truth, p)
                            : cv::Point2f(rng.uniform(0.f, 480.f), rng.uniform(0.f, 270.f)));
  }
  RansacHomography r;
  std::vector<unsigned char> mask;
  const HomographyFit fit = r.fit(src, dst, 1.5, mask);
  ASSERT_TRUE(fit.ok);
  EXPECT_GE(fit.inliers, 320);
  EXPECT_LE(fit.inliers, 330);
  const cv::Point2f a = test::applyHomography(fit.h, {400, 200}),
                    b = test::applyHomography(truth, {400, 200});
  EXPECT_NEAR(a.x, b.x, 0.05);
  EXPECT_NEAR(a.y, b.y, 0.05);
}

TEST(Homography, IsDeterministic) {
  std::vector<cv::Point2f> src, dst;
  cv::RNG rng(9);
  for (int i = 0; i < 100; ++i) {
    src.emplace_back(rng.uniform(0.f, 100.f), rng.uniform(0.f, 100.f));
    dst.push_back(src.back() + cv::Point2f(3, 4));
  }
  RansacHomography r;
  std::vector<unsigned char> m;
  const auto a = r.fit(src, dst, 1.0, m);
  const auto b = r.fit(src, dst, 1.0, m);
  EXPECT_EQ(a.h, b.h);
  EXPECT_NEAR(a.h(0, 2), 3.0, 1e-6);
}

TEST(Homography, DegenerateInputFails) {
  std::vector<cv::Point2f> line, same;
  for (int i = 0; i < 20; ++i) line.emplace_back(static_cast<float>(i), static_cast<float>(2 * i));
  RansacHomography r;
  std::vector<unsigned char> m;
  EXPECT_FALSE(r.fit(line, line, 1.0, m).ok);
  EXPECT_FALSE(r.fit({{0, 0}, {1, 1}}, {{0, 0}, {1, 1}}, 1.0, m).ok);
}

TEST(Homography, PointsNearlyOnALineGiveNoFit) {
  // Tracks along one road or field edge, with tracking noise: any homography fits
  // them (the mapping across the line is free), so none is to be trusted.
  cv::RNG rng(3);
  for (int trial = 0; trial < 5; ++trial) {
    std::vector<cv::Point2f> src, dst;
    for (int i = 0; i < 40; ++i) {
      const float t = static_cast<float>(i) * 12.0f;
      const cv::Point2f p(20.0f + t, 40.0f + 0.5f * t);
      src.push_back(p + cv::Point2f(rng.gaussian(0.3), rng.gaussian(0.3)));
      dst.push_back(p + cv::Point2f(5.0f, -3.0f) +
                    cv::Point2f(rng.gaussian(0.3), rng.gaussian(0.3)));
    }
    RansacHomography r;
    std::vector<unsigned char> m;
    EXPECT_FALSE(r.fit(src, dst, 1.5, m).ok) << "trial " << trial;
  }
  // The same line with a second one across it: a fit, the true shift.
  std::vector<cv::Point2f> src, dst;
  for (int i = 0; i < 40; ++i) {
    const float t = static_cast<float>(i) * 12.0f;
    for (const cv::Point2f p :
         {cv::Point2f(20.0f + t, 40.0f + 0.5f * t), cv::Point2f(300.0f - 0.4f * t, 20.0f + t)}) {
      src.push_back(p);
      dst.push_back(p + cv::Point2f(5.0f, -3.0f));
    }
  }
  RansacHomography r;
  std::vector<unsigned char> m;
  const HomographyFit fit = r.fit(src, dst, 1.5, m);
  ASSERT_TRUE(fit.ok);
  EXPECT_NEAR(fit.h(0, 2), 5.0, 1e-3);
  EXPECT_NEAR(fit.h(1, 2), -3.0, 1e-3);
}

}  // namespace
}  // namespace keyframed
