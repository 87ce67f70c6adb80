#pragma once

#include <array>
#include <atomic>
#include <functional>
#include <optional>
#include <sstream>
#include <string>
#include <string_view>

// Logging by category, each with its own level:
//
//   KF_LOG(Capture, Warning) << "no frame for " << ms << " ms";
//
// A disabled message costs one relaxed atomic load; its arguments are not
// evaluated. Under systemd with stderr connected to the journal, records go to
// journald with PRIORITY and KEYFRAMED_CATEGORY fields; otherwise to stderr with a
// compact prefix. Thread-safe.
namespace keyframed {

enum class LogCategory : int { Capture, Select, Telemetry, Tagging, Output, App };
inline constexpr int kLogCategories = 6;

// Values are syslog priorities (journald's PRIORITY field).
enum class LogLevel : int { Error = 3, Warning = 4, Notice = 5, Info = 6, Debug = 7 };

enum class LogTarget {
  Auto,     // journald when stderr is the journal stream (JOURNAL_STREAM), else stderr
  Journal,  // always journald
  Stderr,   // always stderr
};

const char* toString(LogCategory category);  // "capture", ...
const char* toString(LogLevel level);        // "debug", "info", "notice", "warning", "error"
const char* toString(LogTarget target);      // "auto", "journal", "stderr"
bool parseLogCategory(std::string_view text, LogCategory& category);
bool parseLogLevel(std::string_view text, LogLevel& level);
bool parseLogTarget(std::string_view text, LogTarget& target);

// The [log] section of the daemon's configuration.
struct LogConfig {
  LogLevel level = LogLevel::Info;                                   // log.level
  std::array<std::optional<LogLevel>, kLogCategories> categories{};  // log.<category>; unset: level
  LogTarget target = LogTarget::Auto;                                // log.target
};

namespace logging {

// Per-category thresholds, read inline by KF_LOG.
inline std::atomic<int> gThresholds[kLogCategories] = {6, 6, 6, 6, 6, 6};

[[nodiscard]] inline bool enabled(LogCategory category, LogLevel level) {
  return static_cast<int>(level) <=
         gThresholds[static_cast<int>(category)].load(std::memory_order_relaxed);
}

void setLevel(LogCategory category, LogLevel level);
void setAllLevels(LogLevel level);
[[nodiscard]] LogLevel level(LogCategory category);

// Applies a spec such as "debug" or "capture:debug,telemetry:warning" (the
// KEYFRAMED_LOG_LEVELS environment variable uses it). Empty on success, else why not.
std::string applyLevelSpec(std::string_view spec);

void setTarget(LogTarget target);
// Where journald's socket is looked for (default /run/systemd/journal/socket), so a
// test sees the fallback to stderr on a machine where journald runs.
void setJournalSocketForTesting(std::string path);

// Applies a configuration, then KEYFRAMED_LOG_LEVELS from the environment on top
// (for debugging a deployed unit without editing its files). Empty, or why the
// environment variable was ignored.
std::string configure(const LogConfig& config);

// True when fd's device and inode match JOURNAL_STREAM's "DEV:INODE" (systemd sets
// it for services whose stdout/stderr go to the journal).
[[nodiscard]] bool isJournalStream(int fd, const char* journalStream);

// An extra receiver of every enabled record (e.g. the flight recorder, tests).
// Called under the logger's lock: it must not log.
using Sink = std::function<void(LogCategory, LogLevel, std::string_view message)>;
void setSink(Sink sink);

void write(LogCategory category, LogLevel level, std::string_view message, const char* file,
           int line);

}  // namespace logging

// One record, written when it goes out of scope.
class LogMessage {
 public:
  LogMessage(LogCategory category, LogLevel level, const char* file, int line)
      : category_(category), level_(level), file_(file), line_(line) {}
  LogMessage(const LogMessage&) = delete;
  LogMessage& operator=(const LogMessage&) = delete;
  ~LogMessage() { logging::write(category_, level_, stream_.view(), file_, line_); }

  std::ostream& stream() { return stream_; }

 private:
  LogCategory category_;
  LogLevel level_;
  const char* file_;
  int line_;
  std::ostringstream stream_;
};

// Lets KF_LOG be a single expression (safe in an unbraced if/else).
struct LogVoidify {
  void operator&(std::ostream&) {}
};

}  // namespace keyframed

#define KF_LOG(category, level)                                                                    \
  !::keyframed::logging::enabled(::keyframed::LogCategory::category, ::keyframed::LogLevel::level) \
      ? (void)0                                                                                    \
      : ::keyframed::LogVoidify() & ::keyframed::LogMessage(::keyframed::LogCategory::category,    \
                                                            ::keyframed::LogLevel::level,          \
                                                            __FILE__, __LINE__)                    \
                                        .stream()
