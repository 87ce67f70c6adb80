#include "telemetry/link.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <ctime>
#include <vector>

#include "telemetry/tlog.h"

namespace keyframed {

std::int64_t monotonicNowNs() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

namespace {

struct Url {
  std::string scheme;  // udpin, udpout, serial, tlog
  std::string host;    // or device / path
  int port = 0;        // or baud
};

bool splitHostPort(const std::string& s, std::string& host, int& port) {
  const auto colon = s.rfind(':');
  if (colon == std::string::npos) return false;
  host = s.substr(0, colon);
  const std::string p = s.substr(colon + 1);
  if (host.empty() || p.empty() || p.size() > 5) return false;
  for (char c : p) {
    if (c < '0' || c > '9') return false;
  }
  port = std::stoi(p);
  return port > 0 && port < 65536;
}

}  // namespace

bool isTlogUrl(const std::string& url) {
  return url.starts_with("tlog:") || (url.ends_with(".tlog") && url.find(':') == std::string::npos);
}

namespace {

bool parseUrl(const std::string& url, Url& out, std::string& error) {
  auto bad = [&](const std::string& why) {
    error = "bad MAVLink link '" + url + "': " + why;
    return false;
  };
  if (url.ends_with(".tlog") && url.find(':') == std::string::npos) {
    out = {"tlog", url, 0};
    return true;
  }
  if (url.starts_with("/dev/")) return parseUrl("serial:" + url, out, error);
  const auto colon = url.find(':');
  if (colon == std::string::npos) {
    return bad("expected udpin:HOST:PORT, udpout:HOST:PORT, serial:DEVICE[:BAUD] or tlog:PATH");
  }
  out.scheme = url.substr(0, colon);
  const std::string rest = url.substr(colon + 1);
  if (out.scheme == "udpin" || out.scheme == "udpout" || out.scheme == "udp") {
    if (out.scheme == "udp") out.scheme = "udpin";
    if (!splitHostPort(rest, out.host, out.port)) return bad("expected HOST:PORT");
    return true;
  }
  if (out.scheme == "serial") {
    out.host = rest;
    out.port = 57600;
    // DEVICE:BAUD, where the baud rate is digits only: stable device names have
    // colons of their own (/dev/serial/by-path/...-usb-0:1.3:1.0-port0).
    const auto c2 = rest.rfind(':');
    if (c2 != std::string::npos && c2 + 1 < rest.size() &&
        rest.find_first_not_of("0123456789", c2 + 1) == std::string::npos) {
      const std::string baud = rest.substr(c2 + 1);
      if (baud.size() > 8) return bad("baud rate '" + baud + "' is out of range");
      out.host = rest.substr(0, c2);
      out.port = std::stoi(baud);
    }
    static const int kBauds[] = {9600,   19200,  38400,  57600,  115200,
                                 230400, 460800, 500000, 921600, 1500000};
    bool ok = false;
    for (int b : kBauds) ok = ok || b == out.port;
    if (!ok)
      return bad("unsupported baud rate " + std::to_string(out.port) +
                 " (a device whose name ends in :N is given with its baud rate: DEVICE:57600)");
    if (out.host.empty()) return bad("no device");
    return true;
  }
  if (out.scheme == "tlog") {
    out.host = rest;
    if (rest.empty()) return bad("no file");
    return true;
  }
  return bad("unknown scheme '" + out.scheme + "'");
}

std::string errnoText(const std::string& what) {
  return what + ": " + std::strerror(errno);
}

class UdpLink final : public MavlinkLink {
 public:
  explicit UdpLink(Url url) : url_(std::move(url)) {}
  ~UdpLink() override { closeFd(); }

  bool open(std::string& error) {
    addrinfo hints{};
    hints.ai_family = AF_INET;
    hints.ai_socktype = SOCK_DGRAM;
    addrinfo* res = nullptr;
    const std::string port = std::to_string(url_.port);
    if (getaddrinfo(url_.host.c_str(), port.c_str(), &hints, &res) != 0 || res == nullptr) {
      error = "cannot resolve " + url_.host;
      return false;
    }
    std::memcpy(&addr_, res->ai_addr, sizeof addr_);
    freeaddrinfo(res);
    fd_ = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    if (fd_ < 0) {
      error = errnoText("socket");
      return false;
    }
    if (url_.scheme == "udpin") {
      // No SO_REUSEADDR: on Linux a second socket bound to the same UDP port with it
      // takes every datagram from the first, so a `select --telemetry` on the vehicle
      // would silently starve the running service. UDP has no TIME_WAIT to wait out.
      if (::bind(fd_, reinterpret_cast<const sockaddr*>(&addr_), sizeof addr_) != 0) {
        error = errnoText("cannot listen on udp " + url_.host + ":" + port);
        closeFd();
        return false;
      }
      havePeer_ = false;
      pinned_ = false;
    } else {
      peer_ = addr_;
      havePeer_ = true;
    }
    return true;
  }

  Status read(std::uint8_t* buffer, std::size_t capacity, std::size_t& size, std::int64_t& timeNs,
              int timeoutMs, std::string& error) override {
    pollfd p{fd_, POLLIN, 0};
    const int r = ::poll(&p, 1, timeoutMs);
    if (r == 0) return Status::Timeout;
    if (r < 0) {
      if (errno == EINTR) return Status::Timeout;
      error = errnoText("poll");
      return Status::Error;
    }
    sockaddr_in from{};
    socklen_t fromLen = sizeof from;
    const ssize_t n =
        ::recvfrom(fd_, buffer, capacity, 0, reinterpret_cast<sockaddr*>(&from), &fromLen);
    timeNs = monotonicNowNs();
    if (n < 0) {
      // udpout to a closed port: ICMP unreachable surfaces as ECONNREFUSED. The
      // autopilot may come back, so this is not an error of the link.
      if (errno == EAGAIN || errno == EINTR || errno == ECONNREFUSED) return Status::Timeout;
      error = errnoText("recvfrom");
      return Status::Error;
    }
    if (url_.scheme == "udpin") {
      lastSender_ = from;
      if (!pinned_) {
        peer_ = from;
        havePeer_ = true;
      }
    }
    size = static_cast<std::size_t>(n);
    return Status::Data;
  }

  bool write(const std::uint8_t* data, std::size_t size, std::string& error) override {
    if (!havePeer_) return false;
    const ssize_t n = ::sendto(fd_, data, size, MSG_NOSIGNAL,
                               reinterpret_cast<const sockaddr*>(&peer_), sizeof peer_);
    if (n < 0) {
      if (errno == ECONNREFUSED || errno == EAGAIN) return false;  // peer not there (yet)
      error = errnoText("sendto");
      return false;
    }
    return true;
  }

  bool reopen(std::string& error) override {
    closeFd();
    return open(error);
  }

  [[nodiscard]] bool datagrams() const override { return true; }

  void pinPeerToLastSender() override {
    if (url_.scheme != "udpin") return;
    peer_ = lastSender_;  // follows the autopilot if it comes back from another port
    havePeer_ = true;
    pinned_ = true;
  }

  [[nodiscard]] std::string describe() const override {
    return url_.scheme + ":" + url_.host + ":" + std::to_string(url_.port);
  }

 private:
  void closeFd() {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
  }

  Url url_;
  int fd_ = -1;
  sockaddr_in addr_{};
  sockaddr_in peer_{};
  sockaddr_in lastSender_{};
  bool havePeer_ = false;
  bool pinned_ = false;  // udpin: peer_ is the autopilot's address
};

speed_t baudConstant(int baud) {
  switch (baud) {
    case 9600: return B9600;
    case 19200: return B19200;
    case 38400: return B38400;
    case 57600: return B57600;
    case 115200: return B115200;
    case 230400: return B230400;
    case 460800: return B460800;
    case 500000: return B500000;
    case 921600: return B921600;
    default: return B1500000;
  }
}

class SerialLink final : public MavlinkLink {
 public:
  explicit SerialLink(Url url) : url_(std::move(url)) {}
  ~SerialLink() override { closeFd(); }

  bool open(std::string& error) {
    fd_ = ::open(url_.host.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
    if (fd_ < 0) {
      absent_ = errno == ENOENT || errno == ENODEV || errno == ENXIO;
      error = errnoText("cannot open serial port " + url_.host);
      openError_ = error;
      return false;
    }
    openError_.clear();
    termios tio{};
    if (tcgetattr(fd_, &tio) == 0) {  // not a tty (a pipe in tests): use as is
      cfmakeraw(&tio);
      tio.c_cflag |= CLOCAL | CREAD;
      tio.c_cflag &= ~static_cast<tcflag_t>(CRTSCTS);
      cfsetispeed(&tio, baudConstant(url_.port));
      cfsetospeed(&tio, baudConstant(url_.port));
      if (tcsetattr(fd_, TCSANOW, &tio) != 0) {
        error = errnoText("cannot configure " + url_.host);
        closeFd();
        return false;
      }
    }
    return true;
  }

  Status read(std::uint8_t* buffer, std::size_t capacity, std::size_t& size, std::int64_t& timeNs,
              int timeoutMs, std::string& error) override {
    if (fd_ < 0) {
      error = openError_.empty() ? "serial port " + url_.host + " is closed" : openError_;
      return Status::Error;
    }
    // The rest of a frame cut short goes out as soon as there is room, not only
    // with the next write.
    if (!unsent_.empty() && !flush(error) && !error.empty()) return Status::Error;
    pollfd p{fd_, POLLIN, 0};
    const int r = ::poll(&p, 1, timeoutMs);
    if (r == 0) return Status::Timeout;
    if (r < 0) {
      if (errno == EINTR) return Status::Timeout;
      error = errnoText("poll " + url_.host);
      return Status::Error;
    }
    const ssize_t n = ::read(fd_, buffer, capacity);
    timeNs = monotonicNowNs();
    if (n < 0) {
      if (errno == EAGAIN || errno == EINTR) return Status::Timeout;
      error = errnoText("read " + url_.host);
      return Status::Error;
    }
    if (n == 0 || (p.revents & (POLLHUP | POLLERR)) != 0) {
      error = "serial port " + url_.host + " went away";
      return Status::Error;  // USB adapter unplugged: the caller reopens
    }
    size = static_cast<std::size_t>(n);
    return Status::Data;
  }

  bool write(const std::uint8_t* data, std::size_t size, std::string& error) override {
    if (fd_ < 0) return false;
    // A frame cut short is finished first: anything written before its rest would run
    // into it at the receiver, and both frames be lost.
    if (!flush(error)) return false;  // radio buffer still full: drop, MAVLink is lossy
    const ssize_t n = ::write(fd_, data, size);
    if (n < 0) {
      if (errno == EAGAIN) return false;  // radio buffer full: drop, MAVLink is lossy
      error = errnoText("write " + url_.host);
      return false;
    }
    // Room for only part of it: the rest is kept and goes before anything else, so
    // the frame is sent (read() and the next write() send what is left).
    unsent_.assign(data + n, data + size);
    return true;
  }

  bool reopen(std::string& error) override {
    closeFd();
    return open(error);
  }

  [[nodiscard]] std::string describe() const override {
    return "serial:" + url_.host + ":" + std::to_string(url_.port);
  }
  // The last open() failed because the device is not there.
  [[nodiscard]] bool absent() const { return absent_; }

 private:
  void closeFd() {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
    unsent_.clear();  // a reopened port starts on a frame boundary
  }

  // Writes what is left of a frame cut short; true once none is left. False with
  // error empty while the port has no room.
  bool flush(std::string& error) {
    if (unsent_.empty()) return true;
    const ssize_t n = ::write(fd_, unsent_.data(), unsent_.size());
    if (n < 0) {
      if (errno != EAGAIN) error = errnoText("write " + url_.host);
      return false;
    }
    unsent_.erase(unsent_.begin(), unsent_.begin() + n);
    return unsent_.empty();
  }

  Url url_;
  int fd_ = -1;
  bool absent_ = false;
  std::string openError_;             // why the last open() failed
  std::vector<std::uint8_t> unsent_;  // the rest of a frame that a write cut short
};

class TlogLink final : public MavlinkLink {
 public:
  explicit TlogLink(Url url) : url_(std::move(url)) {}

  bool open(std::string& error) { return reader_.open(url_.host, error); }

  Status read(std::uint8_t* buffer, std::size_t capacity, std::size_t& size, std::int64_t& timeNs,
              int /*timeoutMs*/, std::string& /*error*/) override {
    if (!reader_.next(timeNs, packet_)) return Status::End;
    size = std::min(capacity, packet_.size());
    std::memcpy(buffer, packet_.data(), size);
    return Status::Data;
  }

  bool write(const std::uint8_t* /*data*/, std::size_t /*size*/, std::string& /*error*/) override {
    return false;  // a recording has no one to answer
  }
  bool reopen(std::string& error) override {
    error = "a tlog cannot be reopened";
    return false;
  }
  [[nodiscard]] bool isReplay() const override { return true; }
  [[nodiscard]] std::string describe() const override { return "tlog:" + url_.host; }
  [[nodiscard]] bool truncated() const override { return reader_.truncated(); }
  [[nodiscard]] std::uint64_t skippedBytes() const override { return reader_.resyncedBytes(); }

 private:
  Url url_;
  TlogReader reader_;
  std::vector<std::uint8_t> packet_;
};

}  // namespace

bool parseMavlinkUrl(const std::string& url, std::string& error) {
  Url u;
  return parseUrl(url, u, error);
}

std::unique_ptr<MavlinkLink> openMavlinkLink(const std::string& url, std::string& error,
                                             bool serialMayBeAbsent) {
  Url u;
  if (!parseUrl(url, u, error)) return nullptr;
  if (u.scheme == "udpin" || u.scheme == "udpout") {
    auto link = std::make_unique<UdpLink>(u);
    if (!link->open(error)) return nullptr;
    return link;
  }
  if (u.scheme == "serial") {
    auto link = std::make_unique<SerialLink>(u);
    if (!link->open(error) && !(serialMayBeAbsent && link->absent())) return nullptr;
    return link;
  }
  auto link = std::make_unique<TlogLink>(u);
  if (!link->open(error)) return nullptr;
  return link;
}

}  // namespace keyframed
