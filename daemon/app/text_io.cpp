#include "app/text_io.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdarg>
#include <cstring>
#include <ctime>

namespace keyframed {

namespace {

// `format` (strftime) of unixNs in UTC, then ".mmm" when millis, then "Z".
std::string formatUtc(std::int64_t unixNs, const char* format, bool millis) {
  // Milliseconds, rounded down (floor, also before 1970).
  const std::int64_t ms = unixNs >= 0 ? unixNs / 1'000'000 : -((-unixNs + 999'999) / 1'000'000);
  const std::int64_t sec = ms >= 0 ? ms / 1000 : -((-ms + 999) / 1000);
  const auto t = static_cast<std::time_t>(sec);
  std::tm tm{};
  if (gmtime_r(&t, &tm) == nullptr) return "?";
  char buf[64];
  std::size_t n = std::strftime(buf, sizeof buf, format, &tm);
  if (millis)
    n += static_cast<std::size_t>(
        std::snprintf(buf + n, sizeof buf - n, ".%03d", static_cast<int>(ms - sec * 1000)));
  std::snprintf(buf + n, sizeof buf - n, "Z");
  return buf;
}

}  // namespace

std::string formatUtcIso(std::int64_t unixNs) {
  return formatUtc(unixNs, "%Y-%m-%dT%H:%M:%S", true);
}

std::string formatUtcCompact(std::int64_t unixNs, bool millis) {
  return formatUtc(unixNs, "%Y%m%dT%H%M%S", millis);
}

std::string formatText(const char* format, ...) {
  va_list args;
  va_start(args, format);
  va_list again;
  va_copy(again, args);
  const int n = std::vsnprintf(nullptr, 0, format, args);
  va_end(args);
  std::string out;
  if (n > 0) {
    out.resize(static_cast<std::size_t>(n));
    std::vsnprintf(out.data(), out.size() + 1, format, again);
  }
  va_end(again);
  return out;
}

std::int64_t unixNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

bool writeFileAtomically(const std::string& path, std::span<const std::uint8_t> bytes,
                         std::string& error) {
  const std::string tmp = path + ".tmp";
  std::FILE* f = std::fopen(tmp.c_str(), "wb");
  if (f == nullptr) {
    error = "cannot create " + tmp + ": " + std::strerror(errno);
    return false;
  }
  // On the disk before the rename: after a power cut the file is whole or absent,
  // never a name with no data (ext4 does not order a rename to a new name after the
  // data it names).
  const bool ok = std::fwrite(bytes.data(), 1, bytes.size(), f) == bytes.size() &&
                  std::fflush(f) == 0 && (::fsync(fileno(f)) == 0 || errno == EINVAL);
  const int err = errno;
  if (std::fclose(f) != 0 || !ok) {
    error = "cannot write " + tmp + ": " + std::strerror(ok ? errno : err);
    std::remove(tmp.c_str());
    return false;
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) {
    error = "cannot rename " + tmp + ": " + std::strerror(errno);
    std::remove(tmp.c_str());
    return false;
  }
  syncDirectoryOf(path);
  return true;
}

void syncDirectoryOf(const std::string& path) {
  const std::size_t slash = path.rfind('/');
  const std::string dir = slash == std::string::npos ? std::string(".")
                          : slash == 0               ? std::string("/")
                                                     : path.substr(0, slash);
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) return;
  ::fsync(fd);  // best effort: some file systems cannot sync a directory
  ::close(fd);
}

bool writeAll(int fd, std::string_view bytes) {
  while (!bytes.empty()) {
    const ssize_t n = ::write(fd, bytes.data(), bytes.size());
    if (n < 0) {
      if (errno == EINTR) continue;
      return false;
    }
    if (n == 0) {
      errno = ENOSPC;
      return false;
    }
    bytes.remove_prefix(static_cast<std::size_t>(n));
  }
  return true;
}

bool writeFileAtomically(const std::string& path, std::string_view text, std::string& error) {
  return writeFileAtomically(
      path, std::span(reinterpret_cast<const std::uint8_t*>(text.data()), text.size()), error);
}

RowFile::~RowFile() {
  std::string ignored;
  close(ignored);
}

bool RowFile::open(const std::string& path, std::string_view header, std::string& error) {
  std::string ignored;
  close(ignored);
  path_ = path;
  fd_ = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd_ < 0 || !writeAll(fd_, header)) {
    error = "cannot create " + path + ": " + std::strerror(errno);
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
    return false;
  }
  good_ = static_cast<off_t>(header.size());
  return true;
}

bool RowFile::append(std::string_view rows, std::string& error) {
  if (fd_ < 0) {
    error = "cannot write " + path_ + ": not open";
    return false;
  }
  if (!writeAll(fd_, rows)) {
    error = "cannot write " + path_ + ": " + std::strerror(errno);
    if (::ftruncate(fd_, good_) != 0 || ::lseek(fd_, good_, SEEK_SET) < 0) {
      error += "; cannot cut back a part-written row";
    }
    return false;
  }
  good_ += static_cast<off_t>(rows.size());
  return true;
}

bool RowFile::sync(std::string& error) const {
  if (fd_ < 0 || ::fdatasync(fd_) == 0 || errno == EINVAL) return true;
  error = "cannot sync " + path_ + " to the disk: " + std::strerror(errno);
  return false;
}

bool RowFile::close(std::string& error) {
  if (fd_ < 0) return true;
  const bool ok = ::close(fd_) == 0;
  if (!ok) error = "cannot close " + path_ + ": " + std::strerror(errno);
  fd_ = -1;
  return ok;
}

}  // namespace keyframed
