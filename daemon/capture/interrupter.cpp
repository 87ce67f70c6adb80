#include "capture/interrupter.h"

#include <poll.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>

namespace keyframed {

namespace {
// Without an eventfd a raise() is noticed within this long.
constexpr std::chrono::milliseconds kFallbackSlice{50};
}  // namespace

Interrupter::Interrupter() : eventFd_(::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC)) {}

Interrupter::~Interrupter() {
  if (eventFd_ >= 0) ::close(eventFd_);
}

void Interrupter::raise() {
  raised_.store(true);
  if (eventFd_ >= 0) {
    const std::uint64_t one = 1;
    // Never read back: the counter stays non-zero and every later poll() wakes.
    [[maybe_unused]] const ssize_t n = ::write(eventFd_, &one, sizeof one);
  }
}

Interrupter::Result Interrupter::wait(int fd, short events,
                                      std::chrono::milliseconds timeout) const {
  using SteadyClock = std::chrono::steady_clock;
  const auto deadline = SteadyClock::now() + timeout;
  for (;;) {
    if (raised_.load()) return {Wake::Interrupted, 0, 0};
    // Rounded up: a wait that ends, as poll() counts, in whole milliseconds never
    // times out before its deadline (truncating would return up to 1 ms early, and a
    // paced frame would be handed over before the time it is stamped with).
    const auto rest = deadline - SteadyClock::now();
    if (rest.count() <= 0) return {Wake::Timeout, 0, 0};
    const auto left = std::chrono::ceil<std::chrono::milliseconds>(rest);
    pollfd fds[2] = {{fd, events, 0}, {eventFd_, POLLIN, 0}};
    const auto slice = eventFd_ >= 0 ? left : std::min(left, kFallbackSlice);
    // A negative fd is ignored by poll(); so is the eventfd when it is missing.
    const int r = ::poll(fds, 2, static_cast<int>(slice.count()));
    if (r < 0) {
      if (errno == EINTR) continue;
      return {Wake::Failed, 0, errno};
    }
    if (fds[1].revents != 0 || raised_.load()) return {Wake::Interrupted, 0, 0};
    if (r > 0 && fd >= 0 && fds[0].revents != 0) return {Wake::Ready, fds[0].revents, 0};
  }
}

}  // namespace keyframed
