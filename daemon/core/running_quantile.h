#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <vector>

namespace keyframed {

// A quantile of the last N values: a ring buffer, and nth_element on a scratch
// copy when asked. Both buffers are allocated once.
class RunningQuantile {
 public:
  explicit RunningQuantile(std::size_t window)
      : values_(std::max<std::size_t>(1, window), 0.0), scratch_(values_.size(), 0.0) {}

  void push(double v) {
    values_[next_] = v;
    next_ = (next_ + 1) % values_.size();
    size_ = std::min(size_ + 1, values_.size());
  }

  // q in [0, 1]; call only when size() > 0.
  [[nodiscard]] double quantile(double q) const {
    std::copy_n(values_.begin(), size_, scratch_.begin());
    const auto k = static_cast<std::size_t>(std::lround(q * static_cast<double>(size_ - 1)));
    const auto kth = scratch_.begin() + static_cast<std::ptrdiff_t>(k);
    std::nth_element(scratch_.begin(), kth, scratch_.begin() + static_cast<std::ptrdiff_t>(size_));
    return *kth;
  }

  [[nodiscard]] std::size_t size() const { return size_; }
  void clear() {
    next_ = 0;
    size_ = 0;
  }

 private:
  std::vector<double> values_;
  mutable std::vector<double> scratch_;
  std::size_t next_ = 0;
  std::size_t size_ = 0;
};

}  // namespace keyframed
