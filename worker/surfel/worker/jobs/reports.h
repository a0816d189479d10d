#pragma once
/// \file
/// JSON pieces that several job kinds' reports share.

#include <nlohmann/json.hpp>

#include "surfel/surface/surface_error.h"

namespace surfel::worker {

/// The surface error of a result against its input (course notes 2.4.1): {max, avg,
/// max_relative, avg_relative, avg_per_sample_relative, samples, failed, time_ms}.
nlohmann::json SurfaceErrorJson(const SurfaceError& error, double time_ms);

}  // namespace surfel::worker
