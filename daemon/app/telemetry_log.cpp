#include "app/telemetry_log.h"

#include "app/log.h"

namespace keyframed {

void logTelemetryEvents(TelemetryService& telemetry) {
  telemetry.setLogSink([](TelemetryLogLevel level, const std::string& message) {
    switch (level) {
      case TelemetryLogLevel::Warning: KF_LOG(Telemetry, Warning) << message; break;
      case TelemetryLogLevel::Notice: KF_LOG(Telemetry, Notice) << message; break;
      case TelemetryLogLevel::Info: KF_LOG(Telemetry, Info) << message; break;
    }
  });
}

}  // namespace keyframed
