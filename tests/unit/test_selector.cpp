#include <algorithm>
#include <map>

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include "app/keyframe_stage.h"
#include "core/selector.h"
#include "photos.h"

namespace keyframed {
namespace {

struct PanRun {
  std::vector<Decision> decisions;
  std::vector<std::int64_t> keyframes;  // in the order they became keyframes
};

// Pans a camera along the photo strip with the given per-frame positions; frames
// listed in `blurred` get a Gaussian blur.
// `requests`: capture requests made just before that frame (how many).
// `times`: each frame's timestamp (default: 30 fps from 0).
PanRun pan(const std::vector<double>& xs, const std::map<int, double>& blurred = {},
           SelectorConfig cfg = {}, const std::map<int, int>& requests = {},
           const std::vector<std::int64_t>& times = {}) {
  const cv::Mat strip = test::photoStrip();
  cfg.analysisWidth = 0;
  KeyframeSelector sel(cfg);
  PanRun run;
  cv::RNG rng(11);
  for (std::size_t i = 0; i < xs.size(); ++i) {
    cv::Mat v = test::viewAt(strip, xs[i]);
    cv::Mat noise(v.size(), CV_8UC1);
    rng.fill(noise, cv::RNG::NORMAL, 0, 1.5);
    cv::add(v, noise, v);
    if (auto it = blurred.find(static_cast<int>(i)); it != blurred.end())
      cv::GaussianBlur(v, v, cv::Size(), it->second);
    if (auto it = requests.find(static_cast<int>(i)); it != requests.end()) {
      for (int k = 0; k < it->second; ++k) EXPECT_TRUE(sel.requestCapture());
    }
    const std::int64_t t = times.empty() ? static_cast<std::int64_t>(i) * 33333333 : times[i];
    Decision d = sel.process(Frame::ofGray(v, static_cast<std::int64_t>(i), t));
    if (d.promotedIndex >= 0) run.keyframes.push_back(d.promotedIndex);
    if (d.kept) run.keyframes.push_back(d.index);
    run.decisions.push_back(d);
  }
  return run;
}

std::vector<double> linear(int n, double x0, double step) {
  std::vector<double> xs;
  for (int i = 0; i < n; ++i) xs.push_back(x0 + i * step);
  return xs;
}

TEST(Selector, FirstSharpFrameIsAKeyframe) {
  const PanRun r = pan(linear(5, 100, 0), {{0, 5.0}, {1, 5.0}});
  ASSERT_FALSE(r.keyframes.empty());
  EXPECT_EQ(r.keyframes[0], 2);
  EXPECT_EQ(r.decisions[2].reason, Reason::First);
}

TEST(Selector, ACameraThatOpensOutOfFocusGetsASharpFirstKeyframeToo) {
  // A camera's noise comes after its optics: defocus, then sensor noise. Such frames
  // score far above the blur floor, so the first (taken while the statistic warms
  // up) counts as sharp. Once the lens has focused, the same view in focus becomes
  // the reference and a keyframe, once (Refocus; a defocus so strong that nothing
  // tracks from it loses the chain and starts a new one there), and standing still
  // adds nothing more.
  const cv::Mat strip = test::photoStrip();
  for (const auto& [sigma, reason] :
       {std::pair{1.2, Reason::Refocus}, {2.0, Reason::Refocus}, {3.0, Reason::First}}) {
    SCOPED_TRACE(sigma);
    SelectorConfig cfg;
    cfg.analysisWidth = 0;
    KeyframeSelector sel(cfg);
    cv::RNG rng(5);
    std::vector<Decision> ds;
    for (int i = 0; i < 60; ++i) {
      cv::Mat v = test::viewAt(strip, 100.0);
      if (i < 15) cv::GaussianBlur(v, v, cv::Size(), sigma);
      cv::Mat noise(v.size(), CV_8UC1);
      rng.fill(noise, cv::RNG::NORMAL, 0, 2.0);
      cv::add(v, noise, v);
      ds.push_back(sel.process(Frame::ofGray(v, i, i * 33'333'333LL)));
    }
    ASSERT_TRUE(ds[0].kept);
    EXPECT_EQ(ds[0].reason, Reason::First);
    EXPECT_GT(ds[0].sharpness, cfg.blur.floor);  // the floor alone cannot tell
    std::vector<int> kept;
    for (const Decision& d : ds)
      if (d.kept) kept.push_back(static_cast<int>(d.index));
    ASSERT_EQ(kept.size(), 2U);
    EXPECT_EQ(kept[1], 15);
    EXPECT_EQ(ds[15].reason, reason) << toString(ds[15].reason);
    EXPECT_GE(ds[15].sharpness, KeyframeSelector::kRefocusRatio * ds[0].sharpness);
  }
  EXPECT_STREQ(toString(Reason::Refocus), "refocus");
}

TEST(Selector, ADarkStartDoesNotEndTheRefocusWindow) {
  // Black frames first (score 0: under the floor, no say in the statistic), then
  // the camera opens out of focus, then focuses: the in-focus view still replaces
  // the first keyframe as the reference.
  const cv::Mat strip = test::photoStrip();
  SelectorConfig cfg;
  cfg.analysisWidth = 0;
  KeyframeSelector sel(cfg);
  cv::RNG rng(5);
  std::vector<Decision> ds;
  for (int i = 0; i < 50; ++i) {
    cv::Mat v = test::viewAt(strip, 100.0);
    if (i < 8) v.setTo(0);
    if (i >= 8 && i < 20) cv::GaussianBlur(v, v, cv::Size(), 1.5);
    if (i >= 8) {
      cv::Mat noise(v.size(), CV_8UC1);
      rng.fill(noise, cv::RNG::NORMAL, 0, 2.0);
      cv::add(v, noise, v);
    }
    ds.push_back(sel.process(Frame::ofGray(v, i, i * 33'333'333LL)));
  }
  std::vector<int> kept;
  for (const Decision& d : ds)
    if (d.kept) kept.push_back(static_cast<int>(d.index));
  ASSERT_EQ(kept.size(), 2U);
  EXPECT_EQ(kept[0], 8);
  EXPECT_EQ(kept[1], 20);
  EXPECT_EQ(ds[20].reason, Reason::Refocus) << toString(ds[20].reason);
}

TEST(Selector, ANewTargetGoesOnFromTheLastKeyframeWithTheBlurStatisticItHad) {
  // A reload that changes only the target: the chain and the blur statistic carry
  // on, so a blurred frame right after it is rejected (a fresh statistic would judge
  // it against the floor alone and start a new chain with it), and the next keyframe
  // is at the new target from the last one. A new overlap mode starts a new chain.
  const cv::Mat strip = test::photoStrip();
  SelectorConfig cfg;
  cfg.analysisWidth = 0;
  KeyframeSelector sel(cfg);
  cv::RNG rng(3);
  cv::Mat v;  // a Frame is a view: the pixels stay here while it is decided
  const auto view = [&](int i, double sigma) {
    v = test::viewAt(strip, 100.0 + 8.0 * i);
    if (sigma > 0) cv::GaussianBlur(v, v, cv::Size(), sigma);
    cv::Mat noise(v.size(), CV_8UC1);
    rng.fill(noise, cv::RNG::NORMAL, 0, 1.5);
    cv::add(v, noise, v);
    return Frame::ofGray(v, i, i * 33'333'333LL);
  };
  int i = 0;
  std::int64_t last = -1;
  for (; i < 40; ++i) {
    const Decision d = sel.process(view(i, 0.0));
    if (d.kept) last = d.index;
  }
  SelectorConfig tighter = cfg;
  tighter.target = 0.8;
  tighter.bandHigh = 0.9;
  EXPECT_FALSE(sel.reconfigureRestartsChain(tighter));
  sel.reconfigure(tighter);
  for (; i < 45; ++i) {
    const Decision d = sel.process(view(i, 3.0));
    EXPECT_FALSE(d.kept) << i << " " << toString(d.reason) << " score " << d.sharpness
                         << " threshold " << d.threshold;
    EXPECT_EQ(d.reason, Reason::Blurry) << i;
  }
  Decision next;
  for (; i < 80 && !next.kept; ++i) next = sel.process(view(i, 0.0));
  ASSERT_TRUE(next.kept);
  EXPECT_EQ(next.reason, Reason::OverlapTarget) << toString(next.reason);
  // 0.8 of 480 px at 8 px a frame: 12 frames on from the last keyframe, not 18.
  EXPECT_LE(next.index - last, 13) << last << " -> " << next.index;
  SelectorConfig paper = tighter;
  paper.overlap.mode = OverlapMode::Paper;
  EXPECT_TRUE(sel.reconfigureRestartsChain(paper));
}

TEST(Selector, ASpeedUpTheMotionGateHasNotLearntKeepsKeyframesInTheBand) {
  // 2 px a frame for 5 s, then 14: for a while every frame counts as too fast for
  // the old reference, although each measures sharp. Those are fallen back on at
  // the band's low edge, as sharp frames are, not only at the minimum overlap.
  std::vector<double> xs = linear(150, 100, 2.0);
  for (int k = 0; k < 110; ++k) xs.push_back(xs.back() + 14.0);
  const PanRun r = pan(xs);
  int fast = 0;
  for (const Decision& d : r.decisions) fast += d.fastMotion ? 1 : 0;
  EXPECT_GT(fast, 20);  // the gate does flag them (the case under test)
  ASSERT_GE(r.keyframes.size(), 6U);
  for (std::size_t k = 1; k < r.keyframes.size(); ++k) {
    const double dx = xs[static_cast<std::size_t>(r.keyframes[k])] -
                      xs[static_cast<std::size_t>(r.keyframes[k - 1])];
    EXPECT_GE(1.0 - dx / 480.0, 0.58) << r.keyframes[k - 1] << " -> " << r.keyframes[k];
  }
}

TEST(Selector, ACameraSharpFromTheStartIsNeverRefocused) {
  const PanRun r = pan(linear(120, 100, 8.0));
  for (const Decision& d : r.decisions) EXPECT_NE(d.reason, Reason::Refocus) << d.index;
  // A first keyframe after the warm-up (blurred frames at the start) neither.
  const PanRun late = pan(linear(60, 100, 0.0),
                          {{0, 5.0}, {1, 5.0}, {2, 5.0}, {3, 5.0}, {4, 5.0}, {5, 5.0}, {6, 5.0}});
  for (const Decision& d : late.decisions) EXPECT_NE(d.reason, Reason::Refocus) << d.index;
}

TEST(Selector, KeepsFramesAtTheTargetOverlap) {
  // 8 px a frame over a 480 px view: 0.70 overlap every 18 frames.
  const PanRun r = pan(linear(120, 100, 8.0));
  ASSERT_GE(r.keyframes.size(), 5u);
  for (std::size_t k = 1; k < r.keyframes.size(); ++k) {
    const double dx = 8.0 * static_cast<double>(r.keyframes[k] - r.keyframes[k - 1]);
    const double overlap = 1.0 - dx / 480.0;
    EXPECT_GE(overlap, 0.60) << "pair " << k;
    EXPECT_LE(overlap, 0.75) << "pair " << k;
  }
}

TEST(Selector, HoveringAddsNoKeyframes) {
  std::vector<double> xs = linear(30, 100, 8.0);
  for (int i = 0; i < 120; ++i) xs.push_back(xs.back() + (i % 2 ? 0.3 : -0.3));
  const PanRun r = pan(xs);
  const std::int64_t kfBefore =
      std::count_if(r.keyframes.begin(), r.keyframes.end(), [](std::int64_t k) { return k < 30; });
  EXPECT_EQ(static_cast<std::int64_t>(r.keyframes.size()), kfBefore)
      << "keyframes added while hovering";
}

std::vector<double> hover(int n, double x) {
  std::vector<double> xs;
  for (int i = 0; i < n; ++i) xs.push_back(x + (i % 2 ? 0.3 : -0.3));
  return xs;
}

TEST(Selector, ARequestedCaptureKeepsTheNextSharpFrameWhileHovering) {
  // Hovering: no keyframe but the first, except the two asked for; the second
  // request comes on blurred frames and waits for a sharp one.
  // (blurred enough to fail the blur gate, not so much that tracking is lost)
  const std::map<int, double> blurred{{60, 2.0}, {61, 2.0}, {62, 2.0}};
  const PanRun r = pan(hover(100, 100), blurred, {}, {{20, 1}, {60, 1}});
  ASSERT_EQ(r.keyframes, (std::vector<std::int64_t>{0, 20, 63}));
  EXPECT_EQ(r.decisions[20].reason, Reason::Commanded);
  EXPECT_EQ(r.decisions[63].reason, Reason::Commanded);
  EXPECT_EQ(r.decisions[61].reason, Reason::Blurry);
  EXPECT_TRUE(r.decisions[61].tracking);
  // Selection goes on from the commanded keyframe: overlap is measured against it.
  EXPECT_GT(r.decisions[64].overlap, 0.95);
  EXPECT_EQ(r.decisions[64].reason, Reason::Redundant);
}

TEST(Selector, RequestsAreCountedAndAKeyframeDueAnywayServesOne) {
  // Two requests at once: two keyframes in a row. The first frame (a keyframe
  // anyway) serves a request made before it.
  const PanRun r = pan(hover(40, 100), {}, {}, {{0, 1}, {10, 2}});
  ASSERT_EQ(r.keyframes, (std::vector<std::int64_t>{0, 10, 11}));
  EXPECT_EQ(r.decisions[0].reason, Reason::First);
  EXPECT_EQ(r.decisions[11].reason, Reason::Commanded);
}

// A hover blurred from frame 10 on, every frame still above the blur floor, and
// the absolute threshold that makes those frames blurry: a capture request made
// there can only be served by waiting.
struct BlurredHover {
  std::map<int, double> blurred;
  SelectorConfig cfg;
  BlurredHover() {
    for (int i = 10; i < 80; ++i) blurred[i] = 2.5;
    cfg.blur.mode = BlurMode::Absolute;
    const PanRun sharpRun = pan(hover(12, 100), {}, cfg);
    cfg.blur.absoluteThreshold = sharpRun.decisions[5].sharpness * 0.8;
    cfg.blur.floor = 1.0;
  }
};

TEST(Selector, ARequestedCaptureTakesABlurredFrameAfterWaitingASecond) {
  // Every frame blurred from 10 on (yet above the floor): the request made at frame
  // 10 is served at the first frame a second later (frame 41: 30 frame intervals of
  // 33333333 ns fall just short of it).
  const BlurredHover h;
  const PanRun r = pan(hover(80, 100), h.blurred, h.cfg, {{10, 1}});
  ASSERT_EQ(r.keyframes, (std::vector<std::int64_t>{0, 41}));
  EXPECT_FALSE(r.decisions[41].sharp);
  EXPECT_EQ(r.decisions[41].reason, Reason::Commanded);
  EXPECT_EQ(r.decisions[40].reason, Reason::Blurry);
}

TEST(Selector, ACaptureWaitStartsAgainWhenTheClockGoesBack) {
  // The request is made at 10.3 s; from frame 20 the clock starts again at 0 (a
  // source restarted). The wait counts from there, not from a time that will not
  // come round again for 10 s: served a second after the jump, at frame 51.
  const BlurredHover h;
  std::vector<std::int64_t> times;
  for (int i = 0; i < 80; ++i)
    times.push_back(i < 20 ? 10'000'000'000 + i * 33333333LL : (i - 20) * 33333333LL);
  const PanRun r = pan(hover(80, 100), h.blurred, h.cfg, {{10, 1}}, times);
  ASSERT_EQ(r.keyframes, (std::vector<std::int64_t>{0, 51}));
  EXPECT_EQ(r.decisions[51].reason, Reason::Commanded);
}

TEST(Selector, AtMostSixteenRequestsWait) {
  KeyframeSelector sel;
  for (int i = 0; i < KeyframeSelector::kMaxCaptureRequests; ++i) EXPECT_TRUE(sel.requestCapture());
  EXPECT_FALSE(sel.requestCapture());
  EXPECT_EQ(sel.pendingCaptures(), KeyframeSelector::kMaxCaptureRequests);
}

TEST(CaptureRequests, OneLimitForThoseOnTheirWayAndThoseWaitingAndIntervalTicksWait) {
  std::vector<std::int64_t> kept;
  KeyframeStage stage({}, nullptr, [&](KeyframeEvent&& ev) {
    if (ev.decision.kept) kept.push_back(ev.decision.index);
  });
  CaptureRequests requests;
  // Nothing waits: an interval tick goes; one waits: the next tick is skipped.
  EXPECT_EQ(requests.add(/*onlyIfIdle=*/true), CaptureAnswer::Taken);
  EXPECT_EQ(requests.add(/*onlyIfIdle=*/true), CaptureAnswer::Busy);
  for (int i = 1; i < KeyframeSelector::kMaxCaptureRequests; ++i)
    EXPECT_EQ(requests.add(), CaptureAnswer::Taken);
  EXPECT_EQ(requests.add(), CaptureAnswer::Busy);  // 16 on their way
  EXPECT_EQ(requests.drainInto(stage), 0);
  EXPECT_EQ(stage.pendingCaptures(), KeyframeSelector::kMaxCaptureRequests);
  // 16 waiting in the selector: still refused, not dropped.
  EXPECT_EQ(requests.add(), CaptureAnswer::Busy);
  // Frames serve them, one a frame; the room comes back as they are served.
  const cv::Mat view = test::viewAt(test::photoStrip(), 100);
  for (int i = 0; i < 3; ++i) {
    stage.process(Frame::ofGray(view, i, i * 33333333LL));
    requests.noteServed(stage);
  }
  EXPECT_EQ(kept, (std::vector<std::int64_t>{0, 1, 2}));
  EXPECT_EQ(stage.pendingCaptures(), KeyframeSelector::kMaxCaptureRequests - 3);
  EXPECT_EQ(requests.add(), CaptureAnswer::Taken);
  EXPECT_EQ(requests.add(/*onlyIfIdle=*/true), CaptureAnswer::Busy);
}

TEST(CaptureRequests, OnceTheSourceHasEndedCapturesAreDeniedAndThoseNotServedAreCounted) {
  KeyframeStage stage({}, nullptr, [](KeyframeEvent&&) {});
  CaptureRequests requests;
  // Two handed to the stage, one more still on its way, and no frame after them.
  EXPECT_EQ(requests.add(), CaptureAnswer::Taken);
  EXPECT_EQ(requests.add(), CaptureAnswer::Taken);
  EXPECT_EQ(requests.drainInto(stage), 0);
  EXPECT_EQ(requests.add(), CaptureAnswer::Taken);
  stage.finish();
  EXPECT_EQ(requests.close(stage), 3);
  EXPECT_EQ(requests.add(), CaptureAnswer::Ended);
  EXPECT_EQ(requests.add(/*onlyIfIdle=*/true), CaptureAnswer::Ended);
  // Draining a closed one hands nothing over and does not open it again.
  EXPECT_EQ(requests.drainInto(stage), 0);
  EXPECT_EQ(stage.pendingCaptures(), 2);
  EXPECT_EQ(requests.add(), CaptureAnswer::Ended);
}

TEST(KeyframeStage, SharpFramesDroppedWhileTrackingIsLostAreNotCountedAsBlurred) {
  // A keyframe, then views that jump across the strip every frame: nothing can be
  // tracked, so each sharp frame is dropped as `lost` (no chain to start from) until
  // the camera moves smoothly again. Those frames were sharp: the summary must not
  // call them blurred.
  std::vector<Decision> decisions;
  KeyframeStage stage({}, nullptr, [&](KeyframeEvent&& ev) {
    if (!ev.endOfStream) decisions.push_back(ev.decision);
  });
  const cv::Mat strip = test::photoStrip();
  ASSERT_FALSE(strip.empty());
  std::vector<double> xs = {100, 1700, 500, 2100, 900, 1300};
  for (int i = 0; i < 10; ++i) xs.push_back(1300 + 2.0 * i);
  for (std::size_t i = 0; i < xs.size(); ++i) {
    const cv::Mat view = test::viewAt(strip, xs[i]);
    stage.process(
        Frame::ofGray(view, static_cast<std::int64_t>(i), static_cast<std::int64_t>(i) * 33333333));
  }
  ASSERT_EQ(decisions.size(), xs.size());
  std::int64_t blurred = 0, sharpLost = 0;
  for (const Decision& d : decisions) {
    if (d.kept) continue;
    if (d.reason == Reason::Blurry || (d.reason == Reason::Lost && !d.sharp)) ++blurred;
    if (d.reason == Reason::Lost && d.sharp) ++sharpLost;
  }
  ASSERT_GE(sharpLost, 1) << "the jumps should leave sharp frames without a chain";
  const StageCounts& c = stage.counts();
  EXPECT_EQ(c.rejectedBlur, blurred);
  EXPECT_EQ(c.kept + c.rejectedBlur + c.rejectedOverlap, c.framesRead);
  EXPECT_EQ(c.framesRead, static_cast<std::int64_t>(xs.size()));
}

TEST(Selector, BlurryFramesAreNeverKept) {
  std::map<int, double> blur;
  for (int i = 10; i < 120; i += 4) blur[i] = 3.0;
  const PanRun r = pan(linear(120, 100, 8.0), blur);
  for (std::int64_t k : r.keyframes)
    EXPECT_EQ(blur.count(static_cast<int>(k)), 0u) << "kept blurry frame " << k;
  for (int i : {10, 14, 50})
    EXPECT_EQ(r.decisions[static_cast<std::size_t>(i)].reason, Reason::Blurry);
}

TEST(Selector, BlurAroundTheTargetFallsBackToTheSharpestCandidate) {
  // Frames 12..40 are blurred: the target (frame 18) passes while blurred, and
  // the band's lower edge (frame 24) comes before any sharp frame, so the
  // sharpest candidate seen since the keyframe must be promoted.
  std::map<int, double> blur;
  for (int i = 12; i <= 40; ++i) blur[i] = 3.0;
  const PanRun r = pan(linear(60, 100, 8.0), blur);
  ASSERT_GE(r.keyframes.size(), 2u);
  EXPECT_EQ(r.keyframes[0], 0);
  const std::int64_t second = r.keyframes[1];
  EXPECT_LT(second, 12);
  const double overlap = 1.0 - 8.0 * static_cast<double>(second) / 480.0;
  EXPECT_GE(overlap, 0.60);
  EXPECT_LE(overlap, 0.86);
  bool promoted = false;
  for (const Decision& d : r.decisions) promoted |= d.promotedIndex == second;
  EXPECT_TRUE(promoted);
  for (std::int64_t k : r.keyframes) EXPECT_EQ(blur.count(static_cast<int>(k)), 0u);
}

TEST(Selector, AFallbackEndsTheRefocusWindowOfAFirstKeyframeTakenWhileWarmingUp) {
  // The first keyframe is taken while the blur statistic warms up, on a slightly
  // defocused view; the pan then blurs past the target and the best candidate is
  // promoted. When the camera comes back over the promoted frame's view, now in
  // focus, that view is already a keyframe: no second one of it ("refocus").
  std::vector<double> xs = linear(26, 100, 8.0);
  std::map<int, double> blur;
  for (int i = 0; i < 12; ++i) blur[i] = 1.2;
  for (int i = 12; i < 26; ++i) blur[i] = 3.0;
  for (int i = 0; i < 40; ++i) xs.push_back(std::max(180.0, xs.back() - 8.0));
  const PanRun r = pan(xs, blur);
  ASSERT_TRUE(r.decisions[0].kept);
  ASSERT_EQ(r.decisions[0].reason, Reason::First);
  std::int64_t promoted = -1;
  for (const Decision& d : r.decisions)
    if (d.promotedIndex >= 0) promoted = d.promotedIndex;
  ASSERT_GE(promoted, 9);
  ASSERT_LE(promoted, 11);
  // The focused view is sharper than the first keyframe by the refocus ratio, so
  // only the promotion stands between it and a duplicate.
  const Decision& back = r.decisions.back();
  ASSERT_GE(back.sharpness, KeyframeSelector::kRefocusRatio * r.decisions[0].sharpness);
  ASSERT_GT(back.overlap, SelectorConfig{}.bandHigh);
  EXPECT_EQ(r.keyframes, (std::vector<std::int64_t>{0, promoted}));
  for (std::size_t i = 26; i < r.decisions.size(); ++i)
    EXPECT_EQ(r.decisions[i].reason, Reason::Redundant) << i;
}

TEST(Selector, PaperModeFallsBackToASharpFrameWhenTIsReachedOnABlurredOne) {
  // Where a steady pan reaches t, frames are blurred from just before it for over a
  // second: the paper's rule alone would wait for the next sharp frame, far past t (a
  // gap). The sharpest frame seen before the blur is kept instead.
  SelectorConfig c;
  c.overlap.mode = OverlapMode::Paper;
  c.overlap.orbFeatures = 800;
  const PanRun clean = pan(linear(100, 100, 8.0), {}, c);
  ASSERT_GE(clean.keyframes.size(), 2u);
  const int reached = static_cast<int>(clean.keyframes[1]);
  ASSERT_GE(reached, 8);
  std::map<int, double> blur;
  for (int i = reached - 2; i <= reached + 40 && i < 100; ++i) blur[i] = 3.0;
  const PanRun r = pan(linear(100, 100, 8.0), blur, c);
  ASSERT_GE(r.keyframes.size(), 2u);
  const std::int64_t second = r.keyframes[1];
  EXPECT_LT(second, reached - 2) << "t reached at " << reached << " without blur";
  // The sharp frame nearest t, as far on as a sharp frame goes (the blur starts at
  // reached - 2), not the sharpest near copy of the keyframe.
  EXPECT_GE(second, reached - 5) << "t reached at " << reached << " without blur";
  bool promoted = false;
  for (const Decision& d : r.decisions) promoted |= d.promotedIndex == second;
  EXPECT_TRUE(promoted);
  for (std::int64_t k : r.keyframes) EXPECT_EQ(blur.count(static_cast<int>(k)), 0u) << k;
}

TEST(Selector, PaperModeKeepsFramesAsTheDistanceGrows) {
  SelectorConfig c;
  c.overlap.mode = OverlapMode::Paper;
  c.overlap.orbFeatures = 800;
  const PanRun r = pan(linear(100, 100, 8.0), {}, c);
  ASSERT_GE(r.keyframes.size(), 3u);
  // Every keyframe after the first is kept by the distance statistic, when it
  // reaches t; the frames between are redundant, with their distance under t.
  int byDistance = 0;
  for (const Decision& d : r.decisions) {
    if (d.kept && d.reason == Reason::PaperDistance) {
      ++byDistance;
      EXPECT_GE(d.paperDistance, c.overlap.paperThreshold) << "frame " << d.index;
    } else if (d.reason == Reason::Redundant) {
      EXPECT_LT(d.paperDistance, c.overlap.paperThreshold) << "frame " << d.index;
    }
  }
  EXPECT_EQ(byDistance, static_cast<int>(r.keyframes.size()) - 1);
  // On a steady pan the distance grows with the shift, so keyframes come at a
  // steady spacing: no spacing more than twice another.
  std::vector<std::int64_t> gaps;
  for (std::size_t k = 1; k < r.keyframes.size(); ++k)
    gaps.push_back(r.keyframes[k] - r.keyframes[k - 1]);
  const auto [lo, hi] = std::minmax_element(gaps.begin(), gaps.end());
  EXPECT_GT(*lo, 1);
  EXPECT_LE(*hi, 2 * *lo);
}

TEST(Selector, EveryFrameGetsADecisionWithScoresAndTimings) {
  struct FakeClock final : Clock {
    mutable std::int64_t t = 0;
    std::int64_t nowNs() const override { return t += 1000; }
  } clock;
  const cv::Mat strip = test::photoStrip();
  KeyframeSelector sel(SelectorConfig{}, &clock);
  const cv::Mat v = test::viewAt(strip, 100);
  const Decision d = sel.process(Frame::ofGray(v, 7, 42));
  EXPECT_EQ(d.index, 7);
  EXPECT_EQ(d.timestampNs, 42);
  EXPECT_GT(d.sharpness, 0.0);
  EXPECT_GT(d.features, 0);
  EXPECT_EQ(d.times.totalNs, 4000);
}

TEST(Selector, ConfigValidation) {
  SelectorConfig c;
  EXPECT_TRUE(c.validate().empty());
  c.bandLow = 0.8;  // above the target
  EXPECT_NE(c.validate().find("band low"), std::string::npos);
}

}  // namespace
}  // namespace keyframed

namespace keyframed {
namespace {

TEST(Selector, FinishKeepsThePendingCandidateSoTheEndIsCovered) {
  const cv::Mat strip = test::photoStrip();
  SelectorConfig cfg;
  cfg.analysisWidth = 0;
  KeyframeSelector sel(cfg);
  std::int64_t lastCandidate = -1;
  // 8 px a frame: the target is 18 frames away; stop at frame 12 (overlap 0.78).
  for (int i = 0; i <= 12; ++i) {
    const Decision d = sel.process(Frame::ofGray(test::viewAt(strip, 100 + 8.0 * i), i, i));
    if (d.candidate) lastCandidate = d.index;
  }
  ASSERT_GE(lastCandidate, 0);
  EXPECT_EQ(sel.finish(), lastCandidate);
  EXPECT_EQ(sel.finish(), -1);  // only once
}

}  // namespace
}  // namespace keyframed

namespace keyframed {
namespace {

TEST(Selector, ASharpSceneWithoutTextureGivesOneKeyframeNotOneAFrame) {
  // Vertical stripes (like the colour bars of libcamera's virtual camera): strong
  // edges, so sharp, but no corners to track or ORB features to match. Seen in the
  // libcamera VM test: every frame became a keyframe ("first" again after each "lost").
  cv::Mat bars(270, 480, CV_8UC1);
  for (int x = 0; x < bars.cols; ++x) bars.col(x).setTo(cv::Scalar((x / 25) % 2 == 0 ? 235 : 16));
  const cv::Mat strip = test::photoStrip();
  for (const OverlapMode mode : {OverlapMode::Geometric, OverlapMode::Paper}) {
    SCOPED_TRACE(mode == OverlapMode::Paper ? "paper" : "geometric");
    SelectorConfig cfg;
    cfg.analysisWidth = 0;
    cfg.overlap.mode = mode;
    // (The adaptive threshold would stay at the stripes' level for its whole window.)
    cfg.blur.mode = BlurMode::Absolute;
    KeyframeSelector sel(cfg);
    std::vector<Decision> ds;
    auto feed = [&](const cv::Mat& v) {
      const auto i = static_cast<std::int64_t>(ds.size());
      ds.push_back(sel.process(Frame::ofGray(v, i, i * 33333333)));
    };
    for (int i = 0; i < 30; ++i) feed(bars);
    ASSERT_TRUE(ds[0].kept) << toString(ds[0].reason) << " sharpness " << ds[0].sharpness;
    EXPECT_EQ(ds[0].reason, Reason::First);
    for (int i = 1; i < 30; ++i) {
      EXPECT_TRUE(ds[i].sharp) << i;
      EXPECT_FALSE(ds[i].kept) << i;
      EXPECT_EQ(ds[i].reason, Reason::Featureless) << i;
    }
    EXPECT_EQ(sel.keyframes(), 1);
    // Texture comes into view (a slow pan): a new chain starts at its first sharp
    // frame and is tracked on from there.
    for (int i = 0; i < 10; ++i) feed(test::viewAt(strip, 100 + 2.0 * i));
    std::size_t k = 30;
    while (k < ds.size() && !ds[k].kept) ++k;
    ASSERT_LT(k, ds.size() - 1);
    EXPECT_EQ(ds[k].reason, Reason::First);
    EXPECT_TRUE(ds[k + 1].tracking);
    EXPECT_EQ(sel.keyframes(), 2);
  }
}

TEST(Selector, ASharpSceneNothingCanBeTrackedInGivesOneKeyframeNotOneAFrame) {
  // Glinting water, high-gain noise at dusk: every frame sharp and full of corners,
  // none of which is there in the next frame. Each frame was a new "first" keyframe.
  SelectorConfig cfg;
  cfg.analysisWidth = 0;
  KeyframeSelector sel(cfg);
  std::vector<Decision> ds;
  auto feed = [&](const cv::Mat& v) {
    const auto i = static_cast<std::int64_t>(ds.size());
    ds.push_back(sel.process(Frame::ofGray(v, i, i * 33333333)));
  };
  cv::RNG rng(5);
  for (int i = 0; i < 60; ++i) {
    cv::Mat noise(270, 480, CV_8UC1);
    rng.fill(noise, cv::RNG::UNIFORM, 0, 256);
    cv::GaussianBlur(noise, noise, cv::Size(), 1.0);
    feed(noise);
  }
  EXPECT_GE(ds[5].features, cfg.overlap.minInliers) << "the scene has corners";
  EXPECT_LE(sel.keyframes(), 2);
  for (int i = 2; i < 60; ++i) {
    EXPECT_FALSE(ds[i].tracking) << i;
    EXPECT_EQ(ds[i].reason, Reason::Lost) << i;
  }
  // Ground comes into view: a new chain starts as soon as a frame is tracked from the
  // one before it, and goes on from there.
  const cv::Mat strip = test::photoStrip();
  const int before = sel.keyframes();
  for (int i = 0; i < 10; ++i) feed(test::viewAt(strip, 100 + 2.0 * i));
  EXPECT_FALSE(ds[60].kept);  // not tracked from the noise before it
  EXPECT_TRUE(ds[61].kept);
  EXPECT_EQ(ds[61].reason, Reason::First);
  EXPECT_TRUE(ds[62].tracking);
  EXPECT_EQ(sel.keyframes(), before + 1);
}

TEST(Selector, AFrameOneRowHighIsAnalysedNotHung) {
  // A malformed source: 640 px analysis of a 1920x1 frame is 0 rows by rounding.
  KeyframeSelector sel;
  for (const int h : {1, 2, 3}) {
    const cv::Mat thin(h, 1920, CV_8UC1, cv::Scalar(90));
    for (int i = 0; i < 3; ++i) {
      const Decision d = sel.process(Frame::ofGray(thin, i, i * 33333333));
      EXPECT_FALSE(d.tracking);
    }
  }
}

TEST(Selector, LostTrackingKeepsTheCandidateAndRestartsAtTheNextSharpFrame) {
  // A pan inside the band, then a featureless frame (lens covered, a cloud), then
  // the camera sees a different place: the best frame before the loss is kept so
  // that the stretch up to it is covered, and a new chain starts.
  const cv::Mat strip = test::photoStrip();
  SelectorConfig cfg;
  cfg.analysisWidth = 0;
  KeyframeSelector sel(cfg);
  std::vector<Decision> ds;
  auto feed = [&](const cv::Mat& v) {
    const auto i = static_cast<std::int64_t>(ds.size());
    ds.push_back(sel.process(Frame::ofGray(v, i, i * 33333333)));
  };
  for (int i = 0; i < 12; ++i) feed(test::viewAt(strip, 100 + 8.0 * i));  // overlap to 0.82
  ASSERT_TRUE(ds[0].kept);
  for (int i = 1; i < 12; ++i) ASSERT_FALSE(ds[i].kept) << i;
  feed(cv::Mat(270, 480, CV_8UC1, cv::Scalar(128)));  // frame 12: nothing to track
  const Decision lost = ds[12];
  EXPECT_FALSE(lost.tracking);
  EXPECT_FALSE(lost.kept);
  EXPECT_EQ(lost.reason, Reason::Lost);
  // the promoted frame is one of the band's candidates (overlap <= 0.85: frames 9-11)
  EXPECT_GE(lost.promotedIndex, 9);
  EXPECT_LE(lost.promotedIndex, 11);
  EXPECT_EQ(sel.keyframes(), 2);
  for (int i = 0; i < 3; ++i) feed(test::viewAt(strip, 700 + 8.0 * i));  // elsewhere
  EXPECT_TRUE(ds[13].kept);
  EXPECT_EQ(ds[13].reason, Reason::First);
  EXPECT_FALSE(ds[14].kept);
  EXPECT_TRUE(ds[14].tracking);
  EXPECT_EQ(sel.keyframes(), 3);
}

TEST(Selector, LostTrackingOrTheEndKeepsNoBlurredCandidate) {
  // As above, but every frame after the keyframe blurred (a defocus, a vibration):
  // the band's best frame is a blurred one. At the loss, and at the end of a stream,
  // none is kept: where no overlap says a gap would open, a blurred frame between
  // two views adds little but trouble for matching.
  const BlurredHover bh;  // the absolute threshold that makes sigma 2.5 blurry
  const cv::Mat strip = test::photoStrip();
  SelectorConfig cfg = bh.cfg;
  cfg.analysisWidth = 0;
  KeyframeSelector sel(cfg);
  cv::RNG rng(5);
  std::vector<Decision> ds;
  auto feed = [&](cv::Mat v, bool blur) {
    cv::Mat noise(v.size(), CV_8UC1);
    rng.fill(noise, cv::RNG::NORMAL, 0, 1.5);
    cv::add(v, noise, v);
    if (blur) cv::GaussianBlur(v, v, cv::Size(), 2.5);
    const auto i = static_cast<std::int64_t>(ds.size());
    ds.push_back(sel.process(Frame::ofGray(v, i, i * 33333333)));
  };
  for (int i = 0; i < 12; ++i) feed(test::viewAt(strip, 100 + 8.0 * i), i > 0);
  ASSERT_TRUE(ds[0].kept);
  for (int i = 1; i < 12; ++i) {
    ASSERT_FALSE(ds[i].kept) << i;
    ASSERT_FALSE(ds[i].sharp) << i;
    ASSERT_TRUE(ds[i].tracking) << i;
  }
  ASSERT_GE(sel.candidateIndex(), 9);                        // a blurred candidate in the band
  feed(cv::Mat(270, 480, CV_8UC1, cv::Scalar(128)), false);  // nothing to track
  EXPECT_EQ(ds[12].reason, Reason::Lost);
  EXPECT_EQ(ds[12].promotedIndex, -1);
  EXPECT_EQ(sel.keyframes(), 1);
  // A new chain, blurred after its first frame, to the end of the stream.
  for (int i = 0; i < 12; ++i) feed(test::viewAt(strip, 700 + 8.0 * i), i > 0);
  EXPECT_EQ(ds[13].reason, Reason::First);
  ASSERT_GE(sel.candidateIndex(), 0);
  EXPECT_EQ(sel.finish(), -1);
  EXPECT_EQ(sel.keyframes(), 2);
}

TEST(Selector, MotionGateJudgesACruiseAfterAHoverByTheCruise) {
  // Cruise at 8 px a frame (1.7 % of the view: above the gate's floor), hover for 2 s,
  // cruise again; and a flight that starts in a hover. Standing still is no
  // reference for moving: no cruising frame is judged blurred by motion.
  for (const bool startHovering : {false, true}) {
    std::vector<double> xs = startHovering ? hover(60, 100) : linear(40, 100, 8.0);
    const auto cruise = [&xs](int n) {
      for (int i = 0; i < n; ++i) xs.push_back(xs.back() + 8.0);
    };
    if (startHovering) {
      cruise(60);
    } else {
      for (double x : hover(60, xs.back())) xs.push_back(x);
      cruise(60);
    }
    const PanRun r = pan(xs);
    int fast = 0;
    for (const Decision& d : r.decisions) fast += d.fastMotion ? 1 : 0;
    EXPECT_EQ(fast, 0) << (startHovering ? "starting in a hover" : "after a hover");
    // and the cruise after the hover is covered at the target, not by fallbacks
    int atTarget = 0;
    for (std::size_t i = xs.size() - 60; i < xs.size(); ++i)
      atTarget += r.decisions[i].reason == Reason::OverlapTarget ? 1 : 0;
    EXPECT_GE(atTarget, 2);
  }
}

TEST(Selector, MotionGateFlagsASuddenFastMove) {
  const cv::Mat strip = test::photoStrip();
  SelectorConfig cfg;
  cfg.analysisWidth = 0;
  KeyframeSelector sel(cfg);
  double x = 100;
  for (int i = 0; i < 60; ++i) {
    // 2 px a frame, then a jerk of three 25 px frames, then 2 px again.
    x += (i >= 40 && i < 43) ? 25.0 : 2.0;
    const Decision d = sel.process(Frame::ofGray(test::viewAt(strip, x), i, i));
    if (i >= 40 && i < 43) {
      EXPECT_TRUE(d.fastMotion) << i << " moved " << d.motionPx;
      EXPECT_FALSE(d.sharp);
      EXPECT_FALSE(d.kept);
    } else if (i > 10) {
      EXPECT_FALSE(d.fastMotion) << i << " moved " << d.motionPx;
      EXPECT_NEAR(d.motionPx, 2.0, 0.5) << i;
    }
  }
}

}  // namespace
}  // namespace keyframed
