// keyframed-libcamera-probe: the probe-libcamera diagnostic as a small program that
// links only libcamera (no OpenCV, MCAP or Zenoh), so that it can be built against
// another libcamera release than the daemon's and run where the daemon cannot.
#include <string>
#include <vector>

#include "app/probe_libcamera.h"

int main(int argc, char** argv) {
  return keyframed::probeLibcameraMain(std::vector<std::string>(argv + 1, argv + argc));
}
