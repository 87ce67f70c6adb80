#pragma once

#include <pthread.h>

namespace keyframed {

// Names the calling thread (at most 15 characters), so that `top -H`, `ps -L`, gdb
// and the allocation counter of tools/bench tell the daemon's threads apart. No I/O:
// the name lives in the kernel's task struct.
inline void nameThisThread(const char* name) {
  pthread_setname_np(pthread_self(), name);
}

}  // namespace keyframed
