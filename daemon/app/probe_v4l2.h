#pragma once

#include <string>
#include <vector>

namespace keyframed {

// `keyframed probe-v4l2`: a diagnostic that lists V4L2 devices, opens one,
// captures frames and prints what it saw as JSON lines on stdout (one object a
// line, "event" names its kind). Exit status: 0 ok, 1 device error, 2 usage.
int probeV4l2Main(const std::vector<std::string>& args);

}  // namespace keyframed
