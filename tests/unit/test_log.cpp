#include <gtest/gtest.h>
#include <stdlib.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cstdio>
#include <string>
#include <vector>

#include "app/log.h"
#include "app/log_throttle.h"
#include "app/sd_notify.h"

namespace keyframed {
namespace {

struct Record {
  LogCategory category;
  LogLevel level;
  std::string message;
};

class LogTest : public ::testing::Test {
 protected:
  void SetUp() override {
    logging::setAllLevels(LogLevel::Info);
    logging::setTarget(LogTarget::Stderr);
    logging::setSink([this](LogCategory c, LogLevel l, std::string_view m) {
      records_.push_back({c, l, std::string(m)});
    });
  }
  void TearDown() override {
    logging::setSink({});
    logging::setAllLevels(LogLevel::Info);
    logging::setTarget(LogTarget::Auto);
  }
  std::vector<Record> records_;
};

TEST_F(LogTest, LevelsFilterPerCategory) {
  logging::setLevel(LogCategory::Capture, LogLevel::Debug);
  logging::setLevel(LogCategory::Telemetry, LogLevel::Error);
  KF_LOG(Capture, Debug) << "frame " << 1;
  KF_LOG(Telemetry, Warning) << "dropped";
  KF_LOG(Telemetry, Error) << "link lost";
  KF_LOG(App, Info) << "ready";
  KF_LOG(App, Debug) << "not shown";
  ASSERT_EQ(records_.size(), 3u);
  EXPECT_EQ(records_[0].message, "frame 1");
  EXPECT_EQ(records_[0].category, LogCategory::Capture);
  EXPECT_EQ(records_[1].message, "link lost");
  EXPECT_EQ(records_[1].level, LogLevel::Error);
  EXPECT_EQ(records_[2].category, LogCategory::App);
}

TEST_F(LogTest, DisabledMessagesDoNotEvaluateTheirArguments) {
  int calls = 0;
  auto expensive = [&calls] {
    ++calls;
    return 42;
  };
  KF_LOG(Select, Debug) << expensive();
  EXPECT_EQ(calls, 0);
  KF_LOG(Select, Info) << expensive();
  EXPECT_EQ(calls, 1);
  // A single expression: safe in an unbraced if/else.
  if (calls == 1)
    KF_LOG(Select, Info) << "one";
  else
    KF_LOG(Select, Info) << "other";
  ASSERT_EQ(records_.size(), 2u);
  EXPECT_EQ(records_[1].message, "one");
}

TEST_F(LogTest, LevelSpecs) {
  EXPECT_EQ(logging::applyLevelSpec("warning,capture:debug,telemetry:error"), "");
  EXPECT_EQ(logging::level(LogCategory::App), LogLevel::Warning);
  EXPECT_EQ(logging::level(LogCategory::Capture), LogLevel::Debug);
  EXPECT_EQ(logging::level(LogCategory::Telemetry), LogLevel::Error);
  EXPECT_EQ(logging::applyLevelSpec("*:notice"), "");
  EXPECT_EQ(logging::level(LogCategory::Capture), LogLevel::Notice);
  EXPECT_EQ(logging::applyLevelSpec("camera:debug"), "unknown log category 'camera'");
  EXPECT_EQ(logging::applyLevelSpec("capture:loud"), "unknown log level 'loud'");
}

TEST_F(LogTest, ConfigureAppliesConfigThenEnvironment) {
  LogConfig c;
  c.level = LogLevel::Warning;
  c.categories[static_cast<int>(LogCategory::Output)] = LogLevel::Debug;
  ::setenv("KEYFRAMED_LOG_LEVELS", "tagging:error", 1);
  EXPECT_EQ(logging::configure(c), "");
  ::unsetenv("KEYFRAMED_LOG_LEVELS");
  EXPECT_EQ(logging::level(LogCategory::App), LogLevel::Warning);
  EXPECT_EQ(logging::level(LogCategory::Output), LogLevel::Debug);
  EXPECT_EQ(logging::level(LogCategory::Tagging), LogLevel::Error);
}

TEST(LogJournal, FallsBackToStderrWithoutJournald) {
  // Where journald runs too: its socket looked for where there is none.
  logging::setJournalSocketForTesting("/nonexistent/keyframed-test/journal/socket");
  logging::setTarget(LogTarget::Journal);
  testing::internal::CaptureStderr();
  KF_LOG(Output, Warning) << "disk " << 97 << "% full";
  const std::string err = testing::internal::GetCapturedStderr();
  logging::setJournalSocketForTesting("/run/systemd/journal/socket");
  logging::setTarget(LogTarget::Auto);
  // "HH:MM:SS.mmm W output: disk 97% full"
  EXPECT_EQ(err.size(), 13 + std::string("W output: disk 97% full\n").size()) << err;
  EXPECT_NE(err.find(" W output: disk 97% full\n"), std::string::npos) << err;
}

TEST(LogJournal, DetectsTheJournalStreamByDeviceAndInode) {
  char path[] = "/tmp/keyframed-log-XXXXXX";
  const int fd = mkstemp(path);
  ASSERT_GE(fd, 0);
  struct stat st {};
  ASSERT_EQ(fstat(fd, &st), 0);
  const std::string match = std::to_string(st.st_dev) + ":" + std::to_string(st.st_ino);
  const std::string other = std::to_string(st.st_dev) + ":" + std::to_string(st.st_ino + 1);
  EXPECT_TRUE(logging::isJournalStream(fd, match.c_str()));
  EXPECT_FALSE(logging::isJournalStream(fd, other.c_str()));
  EXPECT_FALSE(logging::isJournalStream(fd, nullptr));
  EXPECT_FALSE(logging::isJournalStream(fd, "garbage"));
  close(fd);
  unlink(path);
}

TEST(Notifier, WithoutAServiceManagerEverythingIsANoOp) {
  ::unsetenv("NOTIFY_SOCKET");
  ::unsetenv("WATCHDOG_USEC");
  Notifier n;
  EXPECT_FALSE(n.active());
  EXPECT_EQ(n.watchdogTimeout().count(), 0);
  EXPECT_FALSE(n.ready());
  EXPECT_FALSE(n.watchdog());
  EXPECT_FALSE(n.stopping());
}

TEST(Notifier, ReadsTheWatchdogInterval) {
  ::setenv("WATCHDOG_USEC", "10000000", 1);
  ::setenv("WATCHDOG_PID", std::to_string(getpid()).c_str(), 1);
  Notifier n;
  ::unsetenv("WATCHDOG_USEC");
  ::unsetenv("WATCHDOG_PID");
  EXPECT_EQ(n.watchdogTimeout().count(), 10'000'000);
  EXPECT_EQ(n.watchdogPingInterval().count(), 5'000'000);
}

}  // namespace
}  // namespace keyframed

namespace keyframed {
namespace {

TEST(LogThrottle, FirstAtOnceNewKindAfterItsGapSameKindAfterTheRepeatGap) {
  constexpr std::int64_t kS = 1'000'000'000;
  LogThrottle t(10 * kS, 1 * kS);
  EXPECT_EQ(t.pass("disk full", 0), 0U);        // the first line at once
  EXPECT_FALSE(t.pass("disk full", 2 * kS));    // same kind: held back
  EXPECT_FALSE(t.pass("device lost", kS / 2));  // new kind, too soon after the last line
  EXPECT_EQ(t.heldBack(), 2U);
  EXPECT_EQ(t.pass("device lost", 3 * kS), 2U);   // new kind after 1 s: written, 2 held back
  EXPECT_FALSE(t.pass("device lost", 12 * kS));   // same kind within 10 s of the last line
  EXPECT_EQ(t.pass("device lost", 13 * kS), 1U);  // ... and after them
  t.reset();                                      // the problem is over
  EXPECT_EQ(t.heldBack(), 0U);
  EXPECT_EQ(t.pass("device lost", 13 * kS + 1), 0U);  // a new outage is said at once
}

}  // namespace
}  // namespace keyframed
