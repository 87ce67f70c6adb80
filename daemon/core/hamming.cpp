#include "core/hamming.h"

#include <cstring>
#include <limits>

namespace keyframed {
namespace {

constexpr int kDescriptorBytes = 32;

struct Desc {
  std::uint64_t w[4];
};

inline Desc load(const std::uint8_t* p) {
  Desc d;
  std::memcpy(d.w, p, sizeof d.w);
  return d;
}

// One row of queries against all train descriptors. Cloned for popcnt on x86
// so the same binary runs on CPUs without it; other targets use the default.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
__attribute__((target_clones("popcnt", "default")))
#endif
void matchBlock(const std::uint8_t* query, int nq, std::size_t qStep, const std::uint8_t* train,
                int nt, std::size_t tStep, std::uint16_t* bestTrainDist, std::int32_t* bestTrainIdx,
                std::uint16_t* bestQueryDist, std::int32_t* bestQueryIdx) {
  for (int i = 0; i < nq; ++i) {
    const Desc q = load(query + static_cast<std::size_t>(i) * qStep);
    int best = std::numeric_limits<int>::max();
    int bestJ = -1;
    for (int j = 0; j < nt; ++j) {
      const Desc t = load(train + static_cast<std::size_t>(j) * tStep);
      const int d = __builtin_popcountll(q.w[0] ^ t.w[0]) + __builtin_popcountll(q.w[1] ^ t.w[1]) +
                    __builtin_popcountll(q.w[2] ^ t.w[2]) + __builtin_popcountll(q.w[3] ^ t.w[3]);
      if (d < best) {
        best = d;
        bestJ = j;
      }
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
