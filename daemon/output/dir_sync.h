#pragma once

#include <fcntl.h>
#include <unistd.h>

#include <filesystem>
#include <string>

namespace keyframed {

// fsyncs the directory holding `path`, so that a file created or renamed there keeps
// its name through a power cut (its data synced is not enough: the directory entry
// is the directory's). Best effort: some file systems cannot sync a directory.
inline void syncParentDirectory(const std::string& path) {
  std::filesystem::path dir = std::filesystem::path(path).parent_path();
  if (dir.empty()) dir = ".";
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) return;
  ::fsync(fd);
  ::close(fd);
}

}  // namespace keyframed
