#pragma once
/// \file
/// Point-cloud simplification (course notes, Pauly, chapter 2): incremental and hierarchical
/// clustering, iterative point-pair contraction with quadric errors, particle simulation, and a
/// voxel-grid baseline. Every method can hit an exact output count; the result carries
/// consistently oriented normals, averaged colours and splat radii that cover the input.

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/surface/surface_error.h"

namespace surfel {

enum class SimplifyMethod {
    kHierarchical,  ///< 2.1.2: binary splits at the centroid across the axis of largest variance.
    kIncremental,   ///< 2.1.1: region growing by nearest neighbours from seeds.
    kIterative,     ///< 2.2: point-pair contraction ordered by a quadric error metric.
    kParticle,      ///< 2.3: repulsion of particles kept on the surface, final MLS projection.
    kVoxel,         ///< Baseline: one representative per occupied grid cell.
};

/// "hierarchical", "incremental", "iterative", "particle", "voxel".
const char* SimplifyMethodName(SimplifyMethod method);
/// Parses a method name; nullopt when unknown.
std::optional<SimplifyMethod> ParseSimplifyMethod(std::string_view name);

struct SimplifyOptions {
    SimplifyMethod method = SimplifyMethod::kHierarchical;
    /// Exact number of output points (every method). 0 = use the method's own bound instead:
    /// `error` (iterative, hierarchical) or `max_cluster_size` / `max_variation` (clustering).
    std::size_t target = 0;
    /// Error bound in model units: iterative stops before the RMS distance of a contracted
    /// point to its tangent planes would exceed it; hierarchical splits every cluster whose
    /// points lie farther than this from the cluster's plane. 0 = none.
    double error = 0.0;
    /// Curvature-adaptive variant: clusters bounded by surface variation, particle radii scaled
    /// by 1 / sigma_n, so more points go where the surface bends.
    bool adaptive = false;
    /// sigma_max, the largest surface variation of a cluster in adaptive clustering (notes 2.1).
    double max_variation = 0.01;
    /// n_max for clustering without a target (hierarchical, incremental). 0 = 10.
    std::size_t max_cluster_size = 0;
    std::uint64_t seed = 1;          ///< Seeds (incremental) and initial spreading (particle).
    int neighbors = 6;               ///< k of the neighbour graph (incremental growth, iterative pairs).
    int particle_iterations = 40;    ///< Relaxation steps of the particle simulation.
    bool measure_error = true;       ///< Compute the quality report (Delta_max, Delta_avg).
    std::size_t error_samples = 20000; ///< |Q| for the quality report (0 = every input point).
};

/// The quality report of one simplification.
struct SimplifyReport {
    std::string method;
    bool adaptive = false;
    std::size_t input_points = 0;
    std::size_t output_points = 0;
    double time_ms = 0.0;          ///< The algorithm alone (without reading, writing, error measurement).
    double error_time_ms = 0.0;    ///< Time spent measuring the surface error.
    std::optional<SurfaceError> error;  ///< Delta_max / Delta_avg of the input surface against the output's.
    double peak_rss_mb = 0.0;      ///< Peak resident memory of the process while simplifying.
    bool normals_estimated = false;///< The input had no normals; they were estimated.
};

struct SimplifyResult {
    PointCloud cloud;  ///< positions, normals, radii, and colours when the input has them.
    SimplifyReport report;
};

/// Simplifies `input` as `options` say. Throws Error(kInvalidArgument) for an impossible request
/// (empty cloud, target above the input size, an error bound on a method without one, no
/// bound at all) and Error(kCancelled) when `progress` asks to stop. The result is the same for
/// the same input, options and seed, whatever the thread count.
SimplifyResult Simplify(const PointCloud& input, const SimplifyOptions& options, const ProgressFn& progress = {});

/// The clusters of a simplification: label[i] is the output point input point i went to.
/// Exposed for tests and for the resample job.
struct Clustering {
    std::vector<std::uint32_t> label;
    std::size_t count = 0;
};

/// Builds the output cloud from a clustering: `positions` (one per cluster) or, when empty, the
/// cluster centroids (eq. 2.1), those of clusters with 20+ members lifted onto the cluster's
/// least-squares quadratic height field (a centroid lies inside a bent surface); normals as the normalised sum of the members' oriented
/// normals (`normals` may be empty: then estimated on the output and oriented); colours averaged;
/// radius = the largest distance of a member from the representative, at least the distance to the nearest other representative, so splats leave no holes.
PointCloud BuildFromClusters(const PointCloud& input, std::span<const Vec3f> normals, const Clustering& clusters,
                             std::span<const Vec3f> positions = {});

/// Current peak resident set size of this process in MiB (Linux VmHWM), 0 when unknown.
double PeakResidentMiB();

}  // namespace surfel
