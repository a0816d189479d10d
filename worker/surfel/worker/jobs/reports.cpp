#include "surfel/worker/jobs/reports.h"

namespace surfel::worker {

nlohmann::json SurfaceErrorJson(const SurfaceError& e, double time_ms) {
    return {{"max", e.max},
            {"avg", e.avg},
            {"max_relative", e.max_relative()},
            {"avg_relative", e.avg_relative()},
            {"avg_per_sample_relative", e.avg_per_sample_relative()},
            {"samples", e.samples},
            {"failed", e.failed},
            {"time_ms", time_ms}};
}

}  // namespace surfel::worker
