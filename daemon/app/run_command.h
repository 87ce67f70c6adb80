#pragma once

#include <string>
#include <vector>

namespace keyframed {

// `keyframed run [--config-dir DIR] [--set SECTION.KEY=VALUE]...`: the live daemon.
// Returns the process exit code (0 after a clean stop or the end of a video file).
int runMain(const std::vector<std::string>& args);

}  // namespace keyframed
