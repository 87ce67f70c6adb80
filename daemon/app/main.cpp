#include <signal.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <string>
#include <vector>

#include "app/config.h"
#include "app/probe_v4l2.h"
#ifdef KEYFRAMED_WITH_LIBCAMERA
#include "app/probe_libcamera.h"
#endif
#include "app/run_command.h"
#include "app/sd_notify.h"
#include "app/select_command.h"

namespace {

constexpr const char* kUsage = R"(usage: keyframed <command> [options]

commands:
  run                      the live daemon (see: keyframed run --help)
  select VIDEO --out DIR   pick keyframes from a video file (see: keyframed select --help)
  check-config [FILE...]   validate the daemon's configuration and print it (see --help)
  probe-v4l2               V4L2 cameras, their formats and frame timing (see --help)
)";
// Only in builds with libcamera, which alone have the command.
#ifdef KEYFRAMED_WITH_LIBCAMERA
constexpr const char* kLibcameraUsage =
    "  probe-libcamera          libcamera cameras and what they deliver (see --help)\n";
#else
constexpr const char* kLibcameraUsage = "";
#endif
constexpr const char* kVersionUsage = "  version                  print the version\n";

int dispatch(const std::string& command, const std::vector<std::string>& args);

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> args(argv + 1, argv + argc);
  if (args.empty() || args[0] == "-h" || args[0] == "--help" || args[0] == "help") {
    std::FILE* out = args.empty() ? stderr : stdout;
    for (const char* part : {kUsage, kLibcameraUsage, kVersionUsage}) std::fputs(part, out);
    return args.empty() ? 2 : 0;
  }
  const std::string command = args[0];
  args.erase(args.begin());
  // A peer that hangs up (a Zenoh session refused mid-handshake, a ground station
  // gone, a reader of stdout that quit) costs an EPIPE on that write, not the process:
  // Rust ignores SIGPIPE in its own programs, not in a library inside ours, and a TLS
  // stack that writes with writev() raises it.
  struct sigaction ignore {};
  ignore.sa_handler = SIG_IGN;
  sigemptyset(&ignore.sa_mask);
  sigaction(SIGPIPE, &ignore, nullptr);
  // FFmpeg (under OpenCV's video reader) would add its own lines to a bad video's one
  // error line ("moov atom not found"); ours say what failed. Set it to see FFmpeg's.
  setenv("OPENCV_FFMPEG_LOGLEVEL", "-8", /*overwrite=*/0);
  const int status = dispatch(command, args);
  // What a command printed (check-config's configuration, select's summary) must have
  // reached its reader: `check-config > effective.toml` on a full disk is a failure.
  errno = 0;
  if (std::fflush(stdout) != 0 || std::ferror(stdout) != 0) {
    std::fprintf(stderr, "keyframed: %s: cannot write standard output%s%s\n", command.c_str(),
                 errno != 0 ? ": " : "", errno != 0 ? std::strerror(errno) : "");
    return status == 0 ? 1 : status;
  }
  return status;
}

namespace {

int dispatch(const std::string& command, const std::vector<std::string>& args) {
  try {
    if (command == "select") return keyframed::selectMain(args);
    if (command == "run") return keyframed::runMain(args);
    // Diagnostics: V4L2 devices, formats and frame timing; libcamera cameras.
    if (command == "probe-v4l2") return keyframed::probeV4l2Main(args);
#ifdef KEYFRAMED_WITH_LIBCAMERA
    if (command == "probe-libcamera") return keyframed::probeLibcameraMain(args);
#endif
    if (command == "check-config") return keyframed::checkConfigMain(args);
    if (command == "notify-selftest") return keyframed::notifySelftestMain();  // tests only
    if (command == "version" || command == "--version") {
      std::puts("keyframed " KEYFRAMED_VERSION);
      return 0;
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "keyframed: %s\n", e.what());
    return 1;
  }
  std::fprintf(stderr, "keyframed: unknown command '%s' (see keyframed --help)\n", command.c_str());
  return 2;
}

}  // namespace
