#include "app/log.h"

#include <sys/stat.h>
#include <unistd.h>

#include <array>
#include <cinttypes>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <mutex>

#include <systemd/sd-journal.h>

namespace keyframed {
namespace {

constexpr std::array<const char*, kLogCategories> kCategoryNames = {
    "capture", "select", "telemetry", "tagging", "output", "app"};

struct State {
  std::mutex mutex;
  LogTarget target = LogTarget::Auto;
  int journal = -1;  // -1: not decided yet (Auto), 0: stderr, 1: journald
  std::string journalSocket = "/run/systemd/journal/socket";
  logging::Sink sink;
};

State& state() {
  static State s;
  return s;
}

// The first record decides, so that the environment is read once. sd_journal_send
// drops records silently when journald is absent: then stderr it is.
bool useJournal(State& s) {
  if (s.journal < 0) {
    const bool wanted = s.target == LogTarget::Journal ||
                        (s.target == LogTarget::Auto &&
                         logging::isJournalStream(STDERR_FILENO, std::getenv("JOURNAL_STREAM")));
    s.journal = wanted && access(s.journalSocket.c_str(), F_OK) == 0 ? 1 : 0;
  }
  return s.journal == 1;
}

char levelLetter(LogLevel level) {
  switch (level) {
    case LogLevel::Error: return 'E';
    case LogLevel::Warning: return 'W';
    case LogLevel::Notice: return 'N';
    case LogLevel::Info: return 'I';
    case LogLevel::Debug: return 'D';
  }
  return '?';
}

}  // namespace

const char* toString(LogCategory category) {
  return kCategoryNames[static_cast<std::size_t>(category)];
}

const char* toString(LogLevel level) {
  switch (level) {
    case LogLevel::Error: return "error";
    case LogLevel::Warning: return "warning";
    case LogLevel::Notice: return "notice";
    case LogLevel::Info: return "info";
    case LogLevel::Debug: return "debug";
  }
  return "info";
}

const char* toString(LogTarget target) {
  switch (target) {
    case LogTarget::Auto: return "auto";
    case LogTarget::Journal: return "journal";
    case LogTarget::Stderr: return "stderr";
  }
  return "auto";
}

bool parseLogCategory(std::string_view text, LogCategory& category) {
  for (int i = 0; i < kLogCategories; ++i) {
    if (text == kCategoryNames[static_cast<std::size_t>(i)]) {
      category = static_cast<LogCategory>(i);
      return true;
    }
  }
  return false;
}

bool parseLogLevel(std::string_view text, LogLevel& level) {
  for (LogLevel l :
       {LogLevel::Error, LogLevel::Warning, LogLevel::Notice, LogLevel::Info, LogLevel::Debug}) {
    if (text == toString(l)) {
      level = l;
      return true;
    }
  }
  return false;
}

bool parseLogTarget(std::string_view text, LogTarget& target) {
  for (LogTarget t : {LogTarget::Auto, LogTarget::Journal, LogTarget::Stderr}) {
    if (text == toString(t)) {
      target = t;
      return true;
    }
  }
  return false;
}

namespace logging {

void setLevel(LogCategory category, LogLevel level) {
  gThresholds[static_cast<int>(category)].store(static_cast<int>(level), std::memory_order_relaxed);
}

void setAllLevels(LogLevel level) {
  for (int i = 0; i < kLogCategories; ++i) setLevel(static_cast<LogCategory>(i), level);
}

LogLevel level(LogCategory category) {
  return static_cast<LogLevel>(
      gThresholds[static_cast<int>(category)].load(std::memory_order_relaxed));
}

std::string applyLevelSpec(std::string_view spec) {
  while (!spec.empty()) {
    const auto comma = spec.find(',');
    const std::string_view item = spec.substr(0, comma);
    spec = comma == std::string_view::npos ? std::string_view{} : spec.substr(comma + 1);
    if (item.empty()) continue;
    const auto colon = item.find(':');
    LogLevel lvl{};
    if (colon == std::string_view::npos) {
      if (!parseLogLevel(item, lvl)) return "unknown log level '" + std::string(item) + "'";
      setAllLevels(lvl);
      continue;
    }
    const std::string_view name = item.substr(0, colon);
    if (!parseLogLevel(item.substr(colon + 1), lvl))
      return "unknown log level '" + std::string(item.substr(colon + 1)) + "'";
    if (name == "*") {
      setAllLevels(lvl);
      continue;
    }
    LogCategory cat{};
    if (!parseLogCategory(name, cat)) return "unknown log category '" + std::string(name) + "'";
    setLevel(cat, lvl);
  }
  return {};
}

void setTarget(LogTarget target) {
  State& s = state();
  std::lock_guard lock(s.mutex);
  s.target = target;
  s.journal = -1;
}

void setJournalSocketForTesting(std::string path) {
  State& s = state();
  std::lock_guard lock(s.mutex);
  s.journalSocket = std::move(path);
  s.journal = -1;
}

std::string configure(const LogConfig& config) {
  setAllLevels(config.level);
  for (int i = 0; i < kLogCategories; ++i) {
    if (const auto& l = config.categories[static_cast<std::size_t>(i)]) {
      setLevel(static_cast<LogCategory>(i), *l);
    }
  }
  setTarget(config.target);
  const char* env = std::getenv("KEYFRAMED_LOG_LEVELS");
  if (env == nullptr || *env == '\0') return {};
  if (std::string e = applyLevelSpec(env); !e.empty()) return "KEYFRAMED_LOG_LEVELS: " + e;
  return {};
}

bool isJournalStream(int fd, const char* journalStream) {
  if (journalStream == nullptr) return false;
  std::uintmax_t dev = 0;
  std::uintmax_t ino = 0;
  if (std::sscanf(journalStream, "%ju:%ju", &dev, &ino) != 2) return false;
  struct stat st {};
  if (fstat(fd, &st) != 0) return false;
  return static_cast<std::uintmax_t>(st.st_dev) == dev &&
         static_cast<std::uintmax_t>(st.st_ino) == ino;
}

void setSink(Sink sink) {
  State& s = state();
  std::lock_guard lock(s.mutex);
  s.sink = std::move(sink);
}

void write(LogCategory category, LogLevel level, std::string_view message, const char* file,
           int line) {
  State& s = state();
  std::lock_guard lock(s.mutex);
  if (s.sink) s.sink(category, level, message);
  const int length = static_cast<int>(message.size());
  // Should journald fail, the record still reaches stderr.
  if (useJournal(s) && sd_journal_send("MESSAGE=%.*s", length, message.data(), "PRIORITY=%d",
                                       static_cast<int>(level), "KEYFRAMED_CATEGORY=%s",
                                       toString(category), "SYSLOG_IDENTIFIER=keyframed",
                                       "CODE_FILE=%s", file, "CODE_LINE=%d", line, nullptr) >= 0) {
    return;
  }
  timespec ts{};
  clock_gettime(CLOCK_REALTIME, &ts);
  std::tm tm{};
  localtime_r(&ts.tv_sec, &tm);
  std::fprintf(stderr, "%02d:%02d:%02d.%03ld %c %s: %.*s\n", tm.tm_hour, tm.tm_min, tm.tm_sec,
               ts.tv_nsec / 1'000'000, levelLetter(level), toString(category), length,
               message.data());
}

}  // namespace logging
}  // namespace keyframed
