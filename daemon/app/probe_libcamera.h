#pragma once

#include <string>
#include <vector>

namespace keyframed {

// `keyframed probe-libcamera`: lists the cameras libcamera sees, opens one through
// the daemon's LibcameraSource, captures frames and prints what it saw as JSON lines
// on stdout (one object a line, "event" names its kind). Exit status: 0 ok, 1 camera
// error, 2 usage.
int probeLibcameraMain(const std::vector<std::string>& args);

}  // namespace keyframed
