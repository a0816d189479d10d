#pragma once
/// \file
/// XYZ text point clouds: one point per line, positions and optionally normals.

#include <cstdint>
#include <string>
#include <string_view>

#include "surfel/base/point_cloud.h"

namespace surfel {

/// Parses XYZ text: one point per line as `x y z` or `x y z nx ny nz` (the same count on every
/// line), `#` starts a comment, blank lines are ignored. `name` is used in error messages
/// (usually the path). Malformed input throws Error(kInvalidArgument) naming the line and the
/// field; so does an empty or whitespace-only file, which is not a point cloud (a file of
/// comments only is one, with 0 points: FormatXyz writes an empty cloud so). More than
/// `max_points` points throw Error(kResourceExhausted).
PointCloud ParseXyz(std::string_view data, std::string_view name, std::uint64_t max_points = 200'000'000);

/// Serialises positions (and normals when present) as XYZ text, shortest round-trip decimals,
/// one point per line. Other attributes are dropped. An empty cloud is the line "# 0 points".
std::string FormatXyz(const PointCloud& cloud);

}  // namespace surfel
