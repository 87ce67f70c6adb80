// keyframed-v4l2-probe: the probe-v4l2 diagnostic as a small standalone (static
// where possible) program, for machines and test VMs without the full daemon.
#include <string>
#include <vector>

#include "app/probe_v4l2.h"

int main(int argc, char** argv) {
  return keyframed::probeV4l2Main(std::vector<std::string>(argv + 1, argv + argc));
}
