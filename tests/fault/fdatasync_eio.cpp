// A disk that reports an I/O error when a file is synced, for the harness (LD_PRELOAD):
// fdatasync(2) on a file whose name is $KEYFRAMED_FAULT_FDATASYNC fails with EIO, as
// on a failing SD card; every other call goes to the kernel.
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>
#include <climits>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string_view>

extern "C" int fdatasync(int fd) {
  const char* name = std::getenv("KEYFRAMED_FAULT_FDATASYNC");
  if (name != nullptr && *name != '\0') {
    char proc[48];
    std::snprintf(proc, sizeof proc, "/proc/self/fd/%d", fd);
    char link[PATH_MAX];
    const ssize_t n = ::readlink(proc, link, sizeof link - 1);
    const std::string_view path(link, n > 0 ? static_cast<std::size_t>(n) : 0);
    const std::size_t len = std::strlen(name);
    if (path.size() > len && path.ends_with(name) && path[path.size() - len - 1] == '/') {
      errno = EIO;
      return -1;
    }
  }
  return static_cast<int>(::syscall(SYS_fdatasync, fd));
}
