#pragma once
/// \file
/// Memory before work (issue 18.2): every job kind estimates its peak memory from its input
/// clouds' facts (points, attributes, file bytes: known at submit time from the stored cloud
/// record) and its options, and the job is refused with RESOURCE_EXHAUSTED before it starts
/// when the estimate exceeds the limit. docs/memory.md says how each kind estimates and how the
/// estimates compare with measured peak RSS.

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/v1/surfel.pb.h"

namespace surfel::worker {

/// What a job's memory estimate needs to know of one input cloud.
struct CloudFacts {
    std::uint64_t points = 0;
    std::vector<std::string> attributes;  ///< As v1::Cloud.attributes ("normals", "colors(rgb)", ...)
    std::uint64_t file_bytes = 0;         ///< Size of the stored file (read whole before parsing).
    Vec3d extent = Vec3d::Zero();         ///< Bounding box size (model units).
};

/// Facts of a stored cloud record.
CloudFacts FactsOf(const v1::Cloud& cloud);
/// Facts of a loaded cloud whose file had `file_bytes` bytes.
CloudFacts FactsOf(const PointCloud& cloud, std::uint64_t file_bytes);

/// Bytes per point of a PointCloud with these attributes: 12 (positions) + 12 (normals) + 16
/// (colours, RGBA float) + 4 (radius) + 8 per extra attribute (held as double).
std::uint64_t PointBytes(const std::vector<std::string>& attributes);
/// Bytes of a loaded cloud: points x PointBytes.
std::uint64_t CloudBytes(const CloudFacts& facts);
/// Bytes of a loaded cloud plus its file's bytes, both held while it is parsed.
std::uint64_t LoadBytes(const CloudFacts& facts);

/// Points a surface sampled at `spacing` (nearest-neighbour distance, hexagonal packing:
/// sqrt(3)/2 spacing^2 each) has when its area is taken as the surface area of the bounding box
/// of extent `extent`: a coarse upper figure for closed scans. At least 1.
std::uint64_t PointsAtSpacing(const Vec3d& extent, double spacing);

/// The estimate of `spec` on `inputs` (one per JobKind::Inputs, in that order): the kind's
/// EstimateMemory. `spec` must be valid (ValidateSpec).
std::uint64_t EstimateJobMemory(const v1::JobSpec& spec, std::span<const CloudFacts> inputs);

/// Bytes the machine can still give: MemAvailable of /proc/meminfo, or what this process's
/// cgroup (v2 memory.max - memory.current) leaves when that is less. 0 when unknown.
std::uint64_t AvailableMemory();
/// The default --max-job-memory: 3/4 of AvailableMemory() at start (0 = no limit, when unknown).
std::uint64_t DefaultMaxJobMemory();

/// "8.6 GiB"-free form used in messages: bytes in MiB with one decimal ("8192.0 MiB").
std::string MiB(std::uint64_t bytes);

/// Throws Error(kResourceExhausted) "<kind>: job needs an estimated X MiB, above <limit_name> Y
/// MiB" when `estimate` > `limit` (limit 0 = none), and "... above the Z MiB that running jobs
/// leave of <limit_name> Y MiB" when `estimate` > `limit` - `in_use`.
void CheckJobMemory(const v1::JobSpec& spec, std::uint64_t estimate, std::uint64_t limit,
                    const std::string& limit_name, std::uint64_t in_use = 0);

/// Issue 15.6: throws Error(kResourceExhausted) naming the field when the job asks for more
/// output points than `max_points` (the server's --max-points): resample.target.
void CheckOutputPoints(const v1::JobSpec& spec, std::uint64_t max_points);

}  // namespace surfel::worker
