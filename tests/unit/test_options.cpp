#include <gtest/gtest.h>

#include "app/options.h"

namespace keyframed {
namespace {

ParseResult parse(std::vector<std::string> a, SelectOptions& o) {
  return parseSelectOptions(a, o);
}

TEST(Options, ParsesEverySetting) {
  SelectOptions o;
  const auto r = parse({"v.avi",
                        "--out",
                        "d",
                        "--mode",
                        "paper",
                        "--target=0.65",
                        "--band",
                        "0.55,0.8",
                        "--blur-mode",
                        "absolute",
                        "--blur-threshold",
                        "80",
                        "--blur-step",
                        "3,3",
                        "--analysis-width",
                        "480",
                        "--orb-features",
                        "1000",
                        "--paper-threshold",
                        "40",
                        "--decisions",
                        "jsonl",
                        "--jpeg-quality",
                        "85",
                        "--blur-width",
                        "960"},
                       o);
  ASSERT_TRUE(r.ok) << r.error;
  EXPECT_EQ(o.video, "v.avi");
  EXPECT_EQ(o.outDir, "d");
  EXPECT_EQ(o.selector.overlap.mode, OverlapMode::Paper);
  EXPECT_DOUBLE_EQ(o.selector.target, 0.65);
  EXPECT_DOUBLE_EQ(o.selector.bandLow, 0.55);
  EXPECT_DOUBLE_EQ(o.selector.bandHigh, 0.8);
  EXPECT_EQ(o.selector.blur.mode, BlurMode::Absolute);
  EXPECT_DOUBLE_EQ(o.selector.blur.absoluteThreshold, 80.0);
  EXPECT_EQ(o.selector.blur.rowStep, 3);
  EXPECT_EQ(o.selector.blur.colStep, 3);
  EXPECT_DOUBLE_EQ(o.selector.overlap.paperThreshold, 40.0);
  EXPECT_EQ(o.selector.analysisWidth, 480);
  EXPECT_EQ(o.selector.overlap.orbFeatures, 1000);
  EXPECT_EQ(o.decisions, DecisionFormat::JsonLines);
  EXPECT_EQ(o.jpegQuality, 85);
  EXPECT_EQ(o.selector.blur.analysisWidth, 960);
}

TEST(Options, ABandOfOneValueIsAllowedAsInTheConfiguration) {
  // band_low = band_high = target passes check-config: the command line takes it too.
  SelectOptions o;
  const auto r = parse(
      {"v.avi", "--out", "d", "--target", "0.7", "--band", "0.7,0.7", "--min-overlap", "0.5"}, o);
  ASSERT_TRUE(r.ok) << r.error;
  EXPECT_DOUBLE_EQ(o.selector.bandLow, 0.7);
  EXPECT_DOUBLE_EQ(o.selector.bandHigh, 0.7);
  EXPECT_EQ(o.selector.validate(), "");
}

TEST(Options, RejectsBadInputWithOneLine) {
  const std::vector<std::vector<std::string>> bad = {
      {"v.avi"},                                      // no --out
      {"--out", "d"},                                 // no video
      {"v.avi", "--out", "d", "--bogus"},             // unknown option
      {"v.avi", "--out", "d", "--target", "1.5"},     // out of range
      {"v.avi", "--out", "d", "--target", "abc"},     // not a number
      {"v.avi", "--out", "d", "--mode", "magic"},     // unknown mode
      {"v.avi", "--out", "d", "--band", "0.9,0.1"},   // inverted band
      {"v.avi", "--out", "d", "--target", "0.5"},     // target under the band
      {"v.avi", "--out", "d", "--jpeg-quality"},      // missing value
      {"v.avi", "w.avi", "--out", "d"},               // two videos
      {"v.avi", "--out", "d", "--blur-step", "0,3"},  // bad step
  };
  // Each says which option, not only which rule of the core.
  SelectOptions named;
  const auto motion = parse({"v.avi", "--out", "d", "--motion-ratio", "0.5"}, named);
  EXPECT_FALSE(motion.ok);
  EXPECT_EQ(motion.error.rfind("--motion-ratio", 0), 0U) << motion.error;
  for (const auto& args : bad) {
    SelectOptions o;
    const auto r = parse(args, o);
    EXPECT_FALSE(r.ok);
    EXPECT_FALSE(r.error.empty());
    EXPECT_EQ(r.error.find('\n'), std::string::npos);
  }
}

TEST(Options, MavlinkIdsTakeTheConfigurationsRanges) {
  // --mavlink-sysid 0 is telemetry.mavlink_sysid = 0: the autopilot's system id.
  SelectOptions o, top;
  ASSERT_TRUE(parse({"v.avi", "--out", "d", "--mavlink-sysid", "0"}, o).ok);
  EXPECT_EQ(o.mavlinkSystemId, 0);
  ASSERT_TRUE(parse({"v.avi", "--out", "d", "--mavlink-sysid", "255"}, top).ok);
  EXPECT_EQ(top.mavlinkSystemId, 255);
  for (const char* bad : {"256", "-1", "x"}) {
    SelectOptions b;
    const auto r = parse({"v.avi", "--out", "d", "--mavlink-sysid", bad}, b);
    EXPECT_FALSE(r.ok) << bad;
    EXPECT_EQ(r.error.rfind("--mavlink-sysid", 0), 0U) << r.error;
  }
}

TEST(Options, EveryGeometricAndBlurSettingHasAnOption) {
  SelectOptions o;
  const auto r = parse({"v.avi", "--out",
                        "d",     "--min-tracks",
                        "50",    "--min-inliers",
                        "12",    "--ransac-px",
                        "2.5",   "--fast-threshold",
                        "30",    "--lk-window",
                        "15",    "--lk-levels",
                        "2",     "--paper-min-matches",
                        "30",    "--blur-warmup",
                        "7",     "--motion-min-fraction",
                        "0.02",  "--motion-window",
                        "90",    "--blur-floor",
                        "15",    "--blur-ratio",
                        "0.6",   "--blur-quantile",
                        "0.8",   "--blur-window",
                        "120",   "--motion-ratio",
                        "5",     "--capture-wait-ms",
                        "500",   "--min-overlap",
                        "0.45",  "--max-tracks",
                        "250",   "--max-frames",
                        "77",    "--overwrite"},
                       o);
  ASSERT_TRUE(r.ok) << r.error;
  const SelectorConfig& c = o.selector;
  EXPECT_DOUBLE_EQ(c.blur.floor, 15.0);
  EXPECT_DOUBLE_EQ(c.blur.ratio, 0.6);
  EXPECT_DOUBLE_EQ(c.blur.quantile, 0.8);
  EXPECT_EQ(c.blur.window, 120);
  EXPECT_DOUBLE_EQ(c.motionRatio, 5.0);
  EXPECT_EQ(c.captureWaitMs, 500);
  EXPECT_DOUBLE_EQ(c.minOverlap, 0.45);
  EXPECT_EQ(c.overlap.maxTracks, 250);
  EXPECT_EQ(o.maxFrames, 77);
  EXPECT_TRUE(o.overwrite);
  EXPECT_EQ(c.overlap.minTracks, 50);
  EXPECT_EQ(c.overlap.minInliers, 12);
  EXPECT_DOUBLE_EQ(c.overlap.ransacPixels, 2.5);
  EXPECT_EQ(c.overlap.fastThreshold, 30);
  EXPECT_EQ(c.overlap.lkWindow, 15);
  EXPECT_EQ(c.overlap.lkLevels, 2);
  EXPECT_EQ(c.overlap.paperMinMatches, 30);
  EXPECT_EQ(c.blur.warmup, 7);
  EXPECT_DOUBLE_EQ(c.motionMinFraction, 0.02);
  EXPECT_EQ(c.motionWindow, 90);
}

TEST(Options, SmallValuesLowerTheDefaultsThatDependOnThem) {
  // Every value in the advertised range of --max-tracks and --blur-window works alone.
  SelectOptions o;
  auto r = parse({"v.avi", "--out", "d", "--max-tracks", "20", "--blur-window", "1"}, o);
  ASSERT_TRUE(r.ok) << r.error;
  // 2/5 of it would be 8, under --min-inliers (15): tracks are replenished only below
  // --min-tracks, and fewer than 15 would lose the track before they are.
  EXPECT_EQ(o.selector.overlap.minTracks, 15);
  EXPECT_EQ(o.selector.blur.warmup, 1);
  SelectOptions o2;
  r = parse({"v.avi", "--out", "d", "--max-tracks", "60"}, o2);
  ASSERT_TRUE(r.ok) << r.error;
  EXPECT_EQ(o2.selector.overlap.minTracks, 24);
  // An explicit conflicting value is an error, not silently changed.
  SelectOptions o3;
  r = parse({"v.avi", "--out", "d", "--max-tracks", "60", "--min-tracks", "70"}, o3);
  EXPECT_FALSE(r.ok);
  SelectOptions o4;
  r = parse({"v.avi", "--out", "d", "--blur-window", "3", "--blur-warmup", "4"}, o4);
  EXPECT_FALSE(r.ok);
}

TEST(Options, OverflowIsOutOfRangeNotGarbage) {
  SelectOptions o;
  const auto r = parse({"v.avi", "--out", "d", "--max-frames", "99999999999999999999"}, o);
  EXPECT_FALSE(r.ok);
  EXPECT_NE(r.error.find("out of range"), std::string::npos) << r.error;
}

}  // namespace
}  // namespace keyframed
