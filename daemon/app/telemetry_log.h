#pragma once

#include "telemetry/telemetry_service.h"

namespace keyframed {

// Routes what the telemetry thread reports (clock estimate, autopilot, link drops and
// reconnects) to the daemon's log under the Telemetry category.
void logTelemetryEvents(TelemetryService& telemetry);

}  // namespace keyframed
