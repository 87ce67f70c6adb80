// Python bindings of the selection core (nanobind). Images are numpy uint8
// arrays: (H, W) grey or (H, W, 3) BGR, as OpenCV's Python API uses.
#include <cmath>
#include <mutex>
#include <string>

#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/filesystem.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/unique_ptr.h>

#include "app/config.h"
#include "app/paced_source.h"
#include "app/select_command.h"
#include "app/settings.h"
#include "core/overlap.h"
#include "core/selector.h"
#include "core/sharpness.h"

namespace nb = nanobind;
using namespace nb::literals;

namespace keyframed {
namespace {

using Image = nb::ndarray<const std::uint8_t, nb::device::cpu>;

// An image's rows as the core reads them: some pixels, rows one after another in
// memory, never overlapping (a flipped or broadcast view, an empty array: refused,
// not read out of bounds).
void checkRows(const Image& a, std::size_t rowBytes) {
  constexpr std::size_t kMaxSide = 1u << 16;
  if (a.shape(0) == 0 || a.shape(1) == 0) throw nb::value_error("the image is empty");
  if (a.shape(0) > kMaxSide || a.shape(1) > kMaxSide)
    throw nb::value_error("the image is larger than 65536 pixels a side");
  if (a.stride(0) < 0 || static_cast<std::size_t>(a.stride(0)) < rowBytes)
    throw nb::value_error(
        "the image's rows must follow one another in memory (a C-contiguous array, or a "
        "slice of one)");
}

GrayView grayOf(const Image& a) {
  if (a.ndim() != 2) throw nb::value_error("expected a 2-D uint8 grey image");
  if (a.stride(1) != 1) throw nb::value_error("grey image rows must be contiguous");
  checkRows(a, a.shape(1));
  return GrayView{a.data(), static_cast<int>(a.shape(1)), static_cast<int>(a.shape(0)),
                  static_cast<int>(a.stride(0))};
}

Frame frameOf(const Image& a, std::int64_t index, std::int64_t ts) {
  if (index < 0) throw nb::value_error("index must be >= 0 (the frame's number in the stream)");
  if (a.ndim() == 2) {
    const GrayView g = grayOf(a);
    return Frame{PixelFormat::Gray8, g.data, g.width, g.height, g.stride, ts, index};
  }
  if (a.ndim() == 3 && a.shape(2) == 3 && a.stride(2) == 1 && a.stride(1) == 3) {
    checkRows(a, 3 * a.shape(1));
    return Frame{PixelFormat::BGR24,
                 a.data(),
                 static_cast<int>(a.shape(1)),
                 static_cast<int>(a.shape(0)),
                 static_cast<int>(a.stride(0)),
                 ts,
                 index};
  }
  throw nb::value_error("expected a uint8 image of shape (H, W) or (H, W, 3) with contiguous rows");
}

// What is wrong with `c`, or "": the core's rules, then the ranges and agreement that
// the daemon's [selection] and `keyframed select` hold the same settings to (a
// setting Python takes can be given to them again).
std::string selectionError(const SelectorConfig& c) {
  if (std::string e = c.validate(); !e.empty()) return e;
  const ConfigLoadResult r = loadSelectionOverrides(selectionOverrides(c));
  if (r.ok()) return {};
  // "--set selection.KEY=VALUE: selection.KEY: why": the attribute and why, not the
  // command line's assignment that was never typed.
  std::string e = r.errors.front();
  if (e.starts_with("--set ")) {
    if (const auto colon = e.find(": "); colon != std::string::npos) e.erase(0, colon + 2);
  }
  return e;
}

void checkValid(const SelectorConfig& c) {
  if (std::string e = selectionError(c); !e.empty()) throw nb::value_error(e.c_str());
}

// NaN (not measured) becomes None; infinity stays (a step that sent a point behind the
// camera: motion_px inf, fast_motion True).
nb::object optional(double v) {
  return std::isnan(v) ? nb::none() : nb::object(nb::float_(v));
}

nb::dict overlapDict(const OverlapResult& r) {
  nb::dict d;
  d["valid"] = r.valid;
  d["overlap"] = optional(r.overlap);
  d["paper_distance"] = optional(r.paperDistance);
  d["motion_px"] = optional(r.motionPx);
  d["features"] = r.features;
  d["matches"] = r.matches;
  d["inliers"] = r.inliers;
  return d;
}

// A read-write property of SelectorConfig for a field of one of its parts, e.g.
// blur.window exposed as "blur_window".
template <typename Part, typename T>
void partProperty(nb::class_<SelectorConfig>& cls, const char* name, Part SelectorConfig::*part,
                  T Part::*field) {
  cls.def_prop_rw(
      name, [part, field](const SelectorConfig& c) { return c.*part.*field; },
      [part, field](SelectorConfig& c, T v) { c.*part.*field = v; });
}

nb::dict decisionDict(const Decision& d) {
  nb::dict r;
  r["index"] = d.index;
  r["timestamp_ns"] = d.timestampNs;
  r["kept"] = d.kept;
  r["reason"] = toString(d.reason);
  r["candidate"] = d.candidate;
  r["promoted"] = d.promotedIndex >= 0 ? nb::object(nb::int_(d.promotedIndex)) : nb::none();
  r["sharpness"] = d.sharpness;
  r["threshold"] = d.threshold;
  r["sharp"] = d.sharp;
  r["overlap"] = optional(d.overlap);
  r["paper_distance"] = optional(d.paperDistance);
  r["tracking"] = d.tracking;
  r["motion_px"] = optional(d.motionPx);
  r["fast_motion"] = d.fastMotion;
  r["features"] = d.features;
  r["matches"] = d.matches;
  r["inliers"] = d.inliers;
  const auto ms = [](std::int64_t ns) { return static_cast<double>(ns) / 1e6; };
  r["total_ms"] = ms(d.times.totalNs);
  nb::dict t;
  t["luma"] = ms(d.times.lumaNs);
  t["blur"] = ms(d.times.blurNs);
  t["resize"] = ms(d.times.resizeNs);
  t["overlap"] = ms(d.times.overlapNs);
  t["total"] = ms(d.times.totalNs);
  r["times_ms"] = t;
  return r;
}

// The selector as Python holds it: KeyframeSelector is not thread-safe, and process()
// lets go of the GIL, so each call takes this lock.
struct LockedSelector {
  LockedSelector(const SelectorConfig& c, const Clock* clock) : selector(c, clock) {}
  KeyframeSelector selector;
  std::mutex mutex;
};

}  // namespace
}  // namespace keyframed

NB_MODULE(_core, m) {
  using namespace keyframed;
  m.doc() = "keyframed selection core";

  m.def(
      "sampled_laplacian_variance",
      [](const Image& img, int rowStep, int colStep) {
        if (rowStep < 1 || colStep < 1) throw nb::value_error("row_step and col_step must be >= 1");
        return sampledLaplacianVariance(grayOf(img), rowStep, colStep).variance;
      },
      "gray"_a.noconvert(), "row_step"_a = 2, "col_step"_a = 3,
      "The paper's one-pass variance of the Laplacian on a sampled grid (S9 by default).");
  m.def(
      "reference_laplacian_variance",
      [](const Image& img) { return referenceLaplacianVariance(grayOf(img)).variance; },
      "gray"_a.noconvert(), "Exact two-pass variance of the Laplacian over every interior pixel.");

  nb::class_<SelectorConfig> configClass(m, "SelectorConfig");
  configClass.def(nb::init<>())
      .def_prop_rw(
          "mode", [](const SelectorConfig& c) { return std::string(toString(c.overlap.mode)); },
          [](SelectorConfig& c, const std::string& v) {
            if (!parseOverlapMode(v, c.overlap.mode))
              throw nb::value_error("mode must be 'geometric' or 'paper'");
          })
      .def_rw("target", &SelectorConfig::target)
      .def_rw("band_low", &SelectorConfig::bandLow)
      .def_rw("band_high", &SelectorConfig::bandHigh)
      .def_rw("min_overlap", &SelectorConfig::minOverlap)
      .def_rw("motion_ratio", &SelectorConfig::motionRatio)
      .def_rw("motion_min_fraction", &SelectorConfig::motionMinFraction)
      .def_rw("motion_window", &SelectorConfig::motionWindow)
      .def_rw("capture_wait_ms", &SelectorConfig::captureWaitMs)
      .def_rw("analysis_width", &SelectorConfig::analysisWidth)
      .def_prop_rw(
          "blur_mode",
          [](const SelectorConfig& c) { return std::string(blurModeName(c.blur.mode)); },
          [](SelectorConfig& c, const std::string& v) {
            if (!parseBlurMode(v, c.blur.mode))
              throw nb::value_error("blur_mode must be 'adaptive' or 'absolute'");
          })
      .def(
          "validate", [](const SelectorConfig& c) { return selectionError(c); },
          "Empty string when valid, else what is wrong.");
  // The same names as the [selection] keys of the daemon's configuration.
  const auto blur = &SelectorConfig::blur;
  partProperty(configClass, "blur_threshold", blur, &SharpnessConfig::absoluteThreshold);
  partProperty(configClass, "blur_floor", blur, &SharpnessConfig::floor);
  partProperty(configClass, "blur_ratio", blur, &SharpnessConfig::ratio);
  partProperty(configClass, "blur_quantile", blur, &SharpnessConfig::quantile);
  partProperty(configClass, "blur_window", blur, &SharpnessConfig::window);
  partProperty(configClass, "blur_warmup", blur, &SharpnessConfig::warmup);
  partProperty(configClass, "blur_row_step", blur, &SharpnessConfig::rowStep);
  partProperty(configClass, "blur_col_step", blur, &SharpnessConfig::colStep);
  partProperty(configClass, "blur_width", blur, &SharpnessConfig::analysisWidth);
  const auto overlap = &SelectorConfig::overlap;
  partProperty(configClass, "orb_features", overlap, &OverlapConfig::orbFeatures);
  partProperty(configClass, "paper_threshold", overlap, &OverlapConfig::paperThreshold);
  partProperty(configClass, "paper_min_matches", overlap, &OverlapConfig::paperMinMatches);
  partProperty(configClass, "max_tracks", overlap, &OverlapConfig::maxTracks);
  partProperty(configClass, "min_tracks", overlap, &OverlapConfig::minTracks);
  partProperty(configClass, "min_inliers", overlap, &OverlapConfig::minInliers);
  partProperty(configClass, "ransac_px", overlap, &OverlapConfig::ransacPixels);
  partProperty(configClass, "fast_threshold", overlap, &OverlapConfig::fastThreshold);
  partProperty(configClass, "lk_window", overlap, &OverlapConfig::lkWindow);
  partProperty(configClass, "lk_levels", overlap, &OverlapConfig::lkLevels);

  nb::class_<SharpnessScorer>(m, "SharpnessScorer")
      .def(
          "__init__",
          [](SharpnessScorer* self, const SelectorConfig& c) {
            checkValid(c);
            new (self) SharpnessScorer(c.blur);
          },
          "config"_a = SelectorConfig{})
      .def(
          "evaluate",
          [](SharpnessScorer& s, const Image& img) {
            const auto r = s.evaluate(grayOf(img));
            return std::make_tuple(r.score, r.threshold, r.sharp);
          },
          "gray"_a.noconvert(),
          "Score a frame, judge it and add it to the running statistic: (score, threshold, sharp).")
      .def(
          "score", [](SharpnessScorer& s, const Image& img) { return s.score(grayOf(img)); },
          "gray"_a.noconvert())
      .def_prop_ro("threshold", &SharpnessScorer::threshold);

  nb::class_<OverlapEstimator>(m, "OverlapEstimator")
      .def_static(
          "create",
          [](const SelectorConfig& c) {
            checkValid(c);
            return OverlapEstimator::create(c.overlap);
          },
          "config"_a = SelectorConfig{})
      .def(
          "observe",
          [](OverlapEstimator& e, const Image& img) { return overlapDict(e.observe(grayOf(img))); },
          "gray"_a.noconvert(),
          "Analyse the next grey frame (at analysis size) against the reference.")
      .def("set_reference_to_current", &OverlapEstimator::setReferenceToCurrent)
      .def("mark_candidate", &OverlapEstimator::markCandidate)
      .def(
          "set_reference_to_candidate",
          [](OverlapEstimator& e) { return overlapDict(e.setReferenceToCandidate()); },
          "The marked candidate becomes the reference; returns the current frame's overlap "
          "with it.")
      .def("reset", &OverlapEstimator::reset);

  nb::class_<LockedSelector>(m, "KeyframeSelector")
      .def(
          "__init__",
          [](LockedSelector* self, const SelectorConfig& c) {
            checkValid(c);
            // Core reads no clock; like the daemon, the binding lends it one so
            // that decisions carry per-stage times.
            static const MonotonicClock clock;
            new (self) LockedSelector(c, &clock);
          },
          "config"_a = SelectorConfig{})
      .def(
          "process",
          [](LockedSelector& s, const Image& img, std::int64_t index, std::int64_t ts) {
            const Frame f = frameOf(img, index, ts);
            Decision d;
            {
              // Without the GIL (other Python threads run meanwhile), under the
              // selector's own lock: two threads on one selector take turns. The lock
              // is let go before the GIL is taken back.
              nb::gil_scoped_release release;
              std::lock_guard lock(s.mutex);
              d = s.selector.process(f);
            }
            return decisionDict(d);
          },
          "image"_a.noconvert(), "index"_a, "timestamp_ns"_a = 0,
          "Decide for the next frame; returns the decision as a dict. Thread-safe.")
      .def(
          "finish",
          [](LockedSelector& s) {
            std::int64_t i = -1;
            {
              nb::gil_scoped_release release;
              std::lock_guard lock(s.mutex);
              i = s.selector.finish();
            }
            return i >= 0 ? nb::object(nb::int_(i)) : nb::none();
          },
          "End of stream: the index of the pending candidate, now a keyframe, or None.")
      // Meant for another thread while frames are processed: atomic, no lock.
      .def(
          "request_capture", [](LockedSelector& s) { return s.selector.requestCapture(); },
          "Ask for a keyframe (as MAV_CMD_IMAGE_START_CAPTURE does): the next sharp frame is "
          "kept whatever its overlap. False when too many requests wait already.")
      .def_prop_ro("pending_captures",
                   [](LockedSelector& s) { return s.selector.pendingCaptures(); })
      .def_prop_ro("keyframes", [](LockedSelector& s) {
        nb::gil_scoped_release release;
        std::lock_guard lock(s.mutex);
        return s.selector.keyframes();
      });

  m.def(
      "select_video",
      [](const std::filesystem::path& video, const std::filesystem::path& outDir,
         std::optional<SelectorConfig> config, const std::string& decisions, int jpegQuality,
         std::int64_t maxFrames, const std::filesystem::path& calibration, bool overwrite) {
        // str or os.PathLike; a NUL would cut the name short at the C library.
        for (const auto* p : {&video, &outDir, &calibration}) {
          if (p->native().find('\0') != std::string::npos)
            throw nb::value_error("a path must not contain a NUL character");
        }
        SelectOptions o;
        o.video = video.string();
        o.outDir = outDir.string();
        o.overwrite = overwrite;
        o.calibration = calibration.string();
        if (config) {
          o.selector = *config;
          o.selectorGiven = true;
        }
        checkValid(o.selector);
        if (decisions == "csv")
          o.decisions = DecisionFormat::Csv;
        else if (decisions == "jsonl")
          o.decisions = DecisionFormat::JsonLines;
        else
          throw nb::value_error("decisions must be 'csv' or 'jsonl'");
        if (jpegQuality < 1 || jpegQuality > 100)
          throw nb::value_error("jpeg_quality must be 1..100");
        o.jpegQuality = jpegQuality;
        if (maxFrames != -1 && (maxFrames < 1 || maxFrames > (std::int64_t{1} << 40)))
          throw nb::value_error("max_frames must be -1 (all) or 1..2^40");
        o.maxFrames = maxFrames;
        SelectSummary s;
        {
          nb::gil_scoped_release release;
          s = runSelection(o);
        }
        // Failures raise; only a video that breaks off part-way returns (what came
        // before the break was selected and written).
        if (!s.error.empty() && (s.framesRead == 0 || !s.truncated))
          throw std::runtime_error(s.error);
        nb::dict r;
        r["frames_read"] = s.framesRead;
        r["kept"] = s.kept;
        r["rejected_blur"] = s.rejectedBlur;
        r["rejected_overlap"] = s.rejectedOverlap;
        r["gap_fills"] = s.promoted;
        r["seconds"] = s.seconds;
        r["frames_per_second"] = s.framesPerSecond;
        r["analysis_ms_mean"] = s.analysisMsMean;
        r["truncated"] = s.truncated;
        r["error"] = s.error;
        r["decisions_path"] = s.decisionsPath;
        r["summary_path"] = s.summaryPath;
        return r;
      },
      "video"_a, "out_dir"_a, "config"_a = nb::none(), "decisions"_a = "csv", "jpeg_quality"_a = 92,
      "max_frames"_a = -1, "calibration"_a = "", "overwrite"_a = false,
      "Run selection over a video file, writing keyframes, decisions and summary into out_dir.\n"
      "An earlier run's output in out_dir raises RuntimeError, or with overwrite=True is\n"
      "replaced (as `keyframed select --overwrite`).\n"
      "calibration: a camera calibration file (as `keyframed select --calibration`): its\n"
      "intrinsics go into the keyframes' tags, and a fisheye or distorting lens is the one\n"
      "the overlap is measured through.\n"
      "Raises RuntimeError when the video cannot be read at all or an output cannot be\n"
      "written (a full disk); a video that breaks off part-way returns the summary with\n"
      "'error' and 'truncated' set.");
}
