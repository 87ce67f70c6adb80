#include "app/sd_notify.h"

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <ctime>

#include <systemd/sd-daemon.h>

namespace keyframed {
namespace {

// STATUS= is one line of the newline-separated protocol.
std::string statusLine(std::string_view text) {
  std::string line(text);
  for (char& c : line) {
    if (c == '\n' || c == '\r') c = ' ';
  }
  return line;
}

}  // namespace

Notifier::Notifier() {
  const char* socket = std::getenv("NOTIFY_SOCKET");
  active_ = socket != nullptr && *socket != '\0';
  std::uint64_t usec = 0;
  if (sd_watchdog_enabled(0, &usec) > 0) watchdog_ = std::chrono::microseconds(usec);
}

bool Notifier::send(const std::string& state) const {
  if (!active_) return false;
  return sd_notify(0, state.c_str()) > 0;
}

bool Notifier::ready(std::string_view status) {
  return send(status.empty() ? "READY=1" : "READY=1\nSTATUS=" + statusLine(status));
}

bool Notifier::status(std::string_view text) {
  return send("STATUS=" + statusLine(text));
}

bool Notifier::watchdog() {
  return send("WATCHDOG=1");
}

bool Notifier::extendTimeout(std::chrono::microseconds more) {
  return send("EXTEND_TIMEOUT_USEC=" + std::to_string(more.count()));
}

bool Notifier::reloading() {
  // systemd >= 253 (Type=notify-reload) wants the time the reload began; older
  // managers ignore the field.
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  const long long usec = static_cast<long long>(ts.tv_sec) * 1'000'000 + ts.tv_nsec / 1000;
  return send("RELOADING=1\nMONOTONIC_USEC=" + std::to_string(usec));
}

bool Notifier::stopping(std::string_view status) {
  return send(status.empty() ? "STOPPING=1" : "STOPPING=1\nSTATUS=" + statusLine(status));
}

int notifySelftestMain() {
  Notifier n;
  std::printf("notify_socket=%s\nwatchdog_usec=%lld\nping_usec=%lld\n", n.active() ? "yes" : "no",
              static_cast<long long>(n.watchdogTimeout().count()),
              static_cast<long long>(n.watchdogPingInterval().count()));
  std::fflush(stdout);
  bool ok = n.status("starting");
  ok = n.ready("selecting\nkeyframes") && ok;  // the newline must not split the message
  ok = n.watchdog() && ok;
  ok = n.reloading() && ok;
  ok = n.ready() && ok;
  ok = n.stopping("bye") && ok;
  ok = n.extendTimeout(std::chrono::seconds(40)) && ok;
  return ok ? 0 : 1;
}

}  // namespace keyframed
