#include "core/hamming.h"

#include <cstring>
#include <limits>

namespace keyframed {
namespace {

constexpr int kDescriptorBytes = 32;

struct Desc {
  std::uint64_t w0, w1, w2, w3;
};

inline Desc load(const std::uint8_t* p) {
  Desc d;
  std::memcpy(&d.w0, p, 8);
  std::memcpy(&d.w1, p + 8, 8);
  std::memcpy(&d.w2, p + 16, 8);
  std::memcpy(&d.w3, p + 24, 8);
  return d;
}

inline int distance(const Desc& a, const Desc& b) {
  return __builtin_popcountll(a.w0 ^ b.w0) + __builtin_popcountll(a.w1 ^ b.w1) +
         __builtin_popcountll(a.w2 ^ b.w2) + __builtin_popcountll(a.w3 ^ b.w3);
}

// The nearest so far: strictly nearer replaces it, so the first of equals stays.
inline void keepNearest(int d, int index, int& bestD, int& bestIndex) {
  if (d < bestD) {
    bestD = d;
    bestIndex = index;
  }
}

// Every query against all train descriptors: for each query the nearest train
// descriptor and for each train descriptor the nearest query, the first one on ties.
// Four queries at a time share each train descriptor's load and its best-query
// update: a 2,500 x 2,500 match a third faster than one query at a time on x86-64
// (where the four do not all fit in registers; arm64 has twice as many). Cloned for
// popcnt on x86 so the same binary runs on CPUs without it; other targets use the
// default. (Not under ThreadSanitizer: the clones' resolver runs while the loader
// relocates, before TSan's runtime is up, and the binary crashes before main.)
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && !defined(__SANITIZE_THREAD__)
__attribute__((target_clones("popcnt", "default")))
#endif
void matchBlock(const std::uint8_t* query, int nq, std::size_t qStep, const std::uint8_t* train,
                int nt, std::size_t tStep, std::uint16_t* bestTrainDist, std::int32_t* bestTrainIdx,
                std::uint16_t* bestQueryDist, std::int32_t* bestQueryIdx) {
  constexpr int kNone = std::numeric_limits<int>::max();
  int i = 0;
  for (; i + 4 <= nq; i += 4) {
    const std::uint8_t* q = query + static_cast<std::size_t>(i) * qStep;
    const Desc q0 = load(q), q1 = load(q + qStep), q2 = load(q + 2 * qStep),
               q3 = load(q + 3 * qStep);
    int b0 = kNone, b1 = kNone, b2 = kNone, b3 = kNone;
    int j0 = -1, j1 = -1, j2 = -1, j3 = -1;
    for (int j = 0; j < nt; ++j) {
      const Desc t = load(train + static_cast<std::size_t>(j) * tStep);
      const int d0 = distance(q0, t), d1 = distance(q1, t), d2 = distance(q2, t),
                d3 = distance(q3, t);
      keepNearest(d0, j, b0, j0);
      keepNearest(d1, j, b1, j1);
      keepNearest(d2, j, b2, j2);
      keepNearest(d3, j, b3, j3);
      // In query order, as one query at a time would see them.
      int bd = bestQueryDist[j];
      int bi = bestQueryIdx[j];
      keepNearest(d0, i, bd, bi);
      keepNearest(d1, i + 1, bd, bi);
      keepNearest(d2, i + 2, bd, bi);
      keepNearest(d3, i + 3, bd, bi);
      bestQueryDist[j] = static_cast<std::uint16_t>(bd);
      bestQueryIdx[j] = bi;
    }
    bestTrainDist[i] = static_cast<std::uint16_t>(b0);
    bestTrainDist[i + 1] = static_cast<std::uint16_t>(b1);
    bestTrainDist[i + 2] = static_cast<std::uint16_t>(b2);
    bestTrainDist[i + 3] = static_cast<std::uint16_t>(b3);
    bestTrainIdx[i] = j0;
    bestTrainIdx[i + 1] = j1;
    bestTrainIdx[i + 2] = j2;
    bestTrainIdx[i + 3] = j3;
  }
  for (; i < nq; ++i) {
    const Desc q = load(query + static_cast<std::size_t>(i) * qStep);
    int best = kNone;
    int bestJ = -1;
    for (int j = 0; j < nt; ++j) {
      const int d = distance(q, load(train + static_cast<std::size_t>(j) * tStep));
      keepNearest(d, j, best, bestJ);
      if (d < bestQueryDist[j]) {
        bestQueryDist[j] = static_cast<std::uint16_t>(d);
        bestQueryIdx[j] = i;
      }
    }
    bestTrainDist[i] = static_cast<std::uint16_t>(best);
    bestTrainIdx[i] = bestJ;
  }
}

}  // namespace

MutualMatches HammingMatcher::match(const cv::Mat& query, const cv::Mat& train) {
  MutualMatches result;
  if (query.empty() || train.empty()) return result;
  CV_Assert(query.type() == CV_8UC1 && train.type() == CV_8UC1);
  CV_Assert(query.cols == kDescriptorBytes && train.cols == kDescriptorBytes);
  const auto nq = static_cast<std::size_t>(query.rows);
  const auto nt = static_cast<std::size_t>(train.rows);
  bestTrainDist_.assign(nq, std::numeric_limits<std::uint16_t>::max());
  bestTrainIdx_.assign(nq, -1);
  bestQueryDist_.assign(nt, std::numeric_limits<std::uint16_t>::max());
  bestQueryIdx_.assign(nt, -1);
  matchBlock(query.data, query.rows, query.step[0], train.data, train.rows, train.step[0],
             bestTrainDist_.data(), bestTrainIdx_.data(), bestQueryDist_.data(),
             bestQueryIdx_.data());
  double sum = 0.0;
  for (std::size_t i = 0; i < nq; ++i) {
    const int j = bestTrainIdx_[i];
    if (j >= 0 && bestQueryIdx_[static_cast<std::size_t>(j)] == static_cast<int>(i)) {
      sum += bestTrainDist_[i];
      ++result.count;
    }
  }
  result.meanDistance = result.count > 0 ? sum / result.count : 0.0;
  return result;
}

}  // namespace keyframed
