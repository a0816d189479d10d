#pragma once
/// \file
/// Where the second solid B of `surfel boolean` and `surfel render --csg` goes: --translate,
/// --rotate and --scale, the same flags for both (commands_boolean.cpp).

#include <string>

#include "cli_common.h"
#include "surfel/v1/surfel.pb.h"

namespace surfel::cli {

struct PlacementFlags {
    std::string translate, rotate;
    double scale = 1.0;  ///< Similarity's default.
};

/// Adds --translate x,y,z, --rotate ax,ay,az,DEG and --scale S (range kMinBooleanScale..kMaxBooleanScale).
void AddPlacementFlags(CLI::App* sub, PlacementFlags* flags);
/// The flags as the proto's Similarity (x = scale * R x_B + translation). Throws UsageError naming
/// the flag for a malformed value or a zero rotation axis.
v1::Similarity PlacementToProto(const PlacementFlags& flags);

}  // namespace surfel::cli
