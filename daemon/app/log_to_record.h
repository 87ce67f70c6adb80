#pragma once

#include <string_view>

#include "app/log.h"
#include "output/flight_outputs.h"

namespace keyframed {

// While alive, every enabled log record also goes into the flight record's
// /keyframed/log channel. FlightOutputs::log neither logs nor waits, as a sink must
// (it runs under the logger's lock). Destroy it before the FlightOutputs.
class LogToRecord {
 public:
  explicit LogToRecord(FlightOutputs& outputs) : active_(outputs.recording()) {
    if (!active_) return;
    logging::setSink([&outputs](LogCategory category, LogLevel level, std::string_view message) {
      outputs.log(static_cast<int>(level), toString(category), message);
    });
  }
  ~LogToRecord() {
    if (active_) logging::setSink(nullptr);
  }
  LogToRecord(const LogToRecord&) = delete;
  LogToRecord& operator=(const LogToRecord&) = delete;

 private:
  bool active_;
};

}  // namespace keyframed
