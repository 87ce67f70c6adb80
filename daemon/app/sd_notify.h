#pragma once

#include <chrono>
#include <string>
#include <string_view>

namespace keyframed {

// Talks to the service manager (sd_notify(3)): start-up done, status line,
// watchdog keep-alive, reload and stop. Without NOTIFY_SOCKET (not started by
// systemd) every call is a cheap no-op. Thread-safe (each call is one datagram).
class Notifier {
 public:
  // Reads NOTIFY_SOCKET and the watchdog settings (WATCHDOG_USEC, WATCHDOG_PID) once.
  Notifier();

  // A service manager listens.
  [[nodiscard]] bool active() const { return active_; }
  // The watchdog timeout systemd enforces (WatchdogSec=), zero when off.
  [[nodiscard]] std::chrono::microseconds watchdogTimeout() const { return watchdog_; }
  // How often to call watchdog(): half the timeout, as sd_watchdog_enabled(3) advises.
  [[nodiscard]] std::chrono::microseconds watchdogPingInterval() const { return watchdog_ / 2; }

  // Each returns false when the message could not be sent (or nobody listens).
  bool ready(std::string_view status = {});     // READY=1 [+ STATUS=]
  bool status(std::string_view text);           // STATUS=...
  bool watchdog();                              // WATCHDOG=1: call only while frames really arrive
  bool reloading();                             // RELOADING=1 + MONOTONIC_USEC=; ready() when done
  bool stopping(std::string_view status = {});  // STOPPING=1 [+ STATUS=]
  // EXTEND_TIMEOUT_USEC=: a start-up that may outlast TimeoutStartSec (a long wait
  // for the autopilot) asks for this much more from now.
  bool extendTimeout(std::chrono::microseconds more);

 private:
  bool send(const std::string& state) const;

  bool active_ = false;
  std::chrono::microseconds watchdog_{0};
};

// `keyframed notify-selftest` (hidden): sends each kind of message once, in a fixed
// order, so a test acting as the service manager can check the datagrams.
int notifySelftestMain();

}  // namespace keyframed
