#pragma once

#include <unistd.h>

#include <filesystem>
#include <string>
#include <system_error>

#include <gtest/gtest.h>

namespace keyframed::test {

// A directory of this test process's own under the system temp dir,
// <TempDir>/<prefix>-<pid>, created on the first call and removed (with what the
// tests left in it) when the process exits.
inline std::filesystem::path processTempDir(const std::string& prefix) {
  struct Dir {
    std::filesystem::path path;
    ~Dir() {
      std::error_code ec;
      std::filesystem::remove_all(path, ec);
    }
  };
  static const Dir d{std::filesystem::path(testing::TempDir()) /
                     (prefix + "-" + std::to_string(getpid()))};
  std::filesystem::create_directories(d.path);
  return d.path;
}

}  // namespace keyframed::test
