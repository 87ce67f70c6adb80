#include "capture/interrupter.h"

#include <poll.h>
#include <unistd.h>

#include <chrono>
#include <thread>

#include <gtest/gtest.h>

namespace keyframed {
namespace {

using namespace std::chrono_literals;
using SteadyClock = std::chrono::steady_clock;

// A pipe whose read end stands for a device that delivers nothing.
struct Pipe {
  Pipe() { EXPECT_EQ(::pipe(fd), 0); }
  ~Pipe() {
    ::close(fd[0]);
    ::close(fd[1]);
  }
  int fd[2] = {-1, -1};
};

TEST(Interrupter, TimesOutWhenNothingHappens) {
  Interrupter in;
  Pipe p;
  const auto t0 = SteadyClock::now();
  EXPECT_EQ(in.wait(p.fd[0], POLLIN, 80ms).wake, Interrupter::Wake::Timeout);
  EXPECT_GE(SteadyClock::now() - t0, 80ms);
}

TEST(Interrupter, ReportsAReadyDevice) {
  Interrupter in;
  Pipe p;
  ASSERT_EQ(::write(p.fd[1], "x", 1), 1);
  const Interrupter::Result r = in.wait(p.fd[0], POLLIN, 2000ms);
  EXPECT_EQ(r.wake, Interrupter::Wake::Ready);
  EXPECT_NE(r.revents & POLLIN, 0);
}

TEST(Interrupter, RaiseFromAnotherThreadEndsAStalledWaitAndEveryLaterOne) {
  Interrupter in;
  Pipe p;
  std::thread stopper([&] {
    std::this_thread::sleep_for(50ms);
    in.raise();
  });
  const auto t0 = SteadyClock::now();
  const Interrupter::Result r = in.wait(p.fd[0], POLLIN, 2000ms);  // a camera's frame timeout
  const auto took = SteadyClock::now() - t0;
  stopper.join();
  EXPECT_EQ(r.wake, Interrupter::Wake::Interrupted);
  EXPECT_LT(took, 500ms);
  EXPECT_TRUE(in.raised());
  const auto t1 = SteadyClock::now();
  EXPECT_EQ(in.wait(p.fd[0], POLLIN, 2000ms).wake, Interrupter::Wake::Interrupted);
  EXPECT_EQ(in.wait(-1, 0, 2000ms).wake, Interrupter::Wake::Interrupted);
  EXPECT_LT(SteadyClock::now() - t1, 100ms);
}

TEST(Interrupter, InterruptibleSleepWithoutADevice) {
  Interrupter in;
  const auto t0 = SteadyClock::now();
  EXPECT_EQ(in.wait(-1, 0, 60ms).wake, Interrupter::Wake::Timeout);
  EXPECT_GE(SteadyClock::now() - t0, 60ms);
  std::thread stopper([&] {
    std::this_thread::sleep_for(30ms);
    in.raise();
  });
  const auto t1 = SteadyClock::now();
  EXPECT_EQ(in.wait(-1, 0, 5000ms).wake, Interrupter::Wake::Interrupted);  // a reopen interval
  EXPECT_LT(SteadyClock::now() - t1, 500ms);
  stopper.join();
}

// A timeout is a deadline, never a little early: the paced file source hands a frame
// over when its wait ends and stamps it with the time it was due. Waits from a few
// microseconds to a few milliseconds, at every phase of the millisecond.
TEST(Interrupter, ATimeoutNeverEndsBeforeItsDeadline) {
  Interrupter in;
  for (int i = 0; i < 300; ++i) {
    const auto timeout = std::chrono::milliseconds(i % 3);
    const auto t0 = SteadyClock::now();
    ASSERT_EQ(in.wait(-1, 0, timeout).wake, Interrupter::Wake::Timeout);
    ASSERT_GE(SteadyClock::now() - t0, timeout) << "wait " << i;
    std::this_thread::sleep_for(std::chrono::microseconds(37 * (i % 29)));
  }
}

}  // namespace
}  // namespace keyframed
