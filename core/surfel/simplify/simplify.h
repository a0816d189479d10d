#pragma once
/// \file
/// Point-cloud simplification (course notes, Pauly, chapter 2): incremental and hierarchical
/// clustering, iterative point-pair contraction with quadric errors, particle simulation, and a
/// voxel-grid baseline. Every method can hit an exact output count; the result carries
/// consistently oriented normals, averaged colours and splat radii that cover the input.

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/surface/surface_error.h"

namespace surfel {

class KdTree;

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
/// Every method, in declaration order (for loops, help texts and validation).
inline constexpr std::array<SimplifyMethod, 5> kSimplifyMethods = {
    SimplifyMethod::kHierarchical, SimplifyMethod::kIncremental, SimplifyMethod::kIterative,
    SimplifyMethod::kParticle, SimplifyMethod::kVoxel};

/// What stands for a cluster (or a contracted set) in the output.
enum class SimplifyRepresentative {
    /// The notes' rule (eq. 2.1): the cluster's centroid, lifted onto the cluster's fitted
    /// surface (BuildFromClusters); iterative: the contracted point; normals and colours averaged
    /// over the members. A resampling: no output point need be an input point.
    kCentroid,
    /// A subset of the input: the member nearest the point kCentroid would output (for the
    /// clustering methods the plain centroid, CGAL's `hierarchy_simplify_point_set` rule; for
    /// iterative the contracted point). Its position, colour and given normal are kept
    /// unchanged; only the splat radius is added. Not for particle simulation, whose points are
    /// not tied to members.
    kMember,
};
/// "centroid", "member".
const char* SimplifyRepresentativeName(SimplifyRepresentative representative);
/// Parses a representative name; nullopt when unknown.
std::optional<SimplifyRepresentative> ParseSimplifyRepresentative(std::string_view name);

/// Limits of SimplifyOptions, written once here; the CLI, the worker and the docs read them.
/// Smallest sigma_max (notes 2.1: surface variation sigma_n = lambda_0 / (lambda_0 + lambda_1 + lambda_2)).
inline constexpr double kMinMaxVariation = 1e-12;
/// Largest sigma_max: the surface variation of an isotropic point set, its upper bound.
inline constexpr double kMaxMaxVariation = 1.0 / 3.0;
/// Largest n_max of clustering without a target: above any cloud the service takes, so that
/// n_max = kMaxMaxClusterSize leaves the splitting to the error bound alone.
inline constexpr std::size_t kMaxMaxClusterSize = 1000000000;
/// Largest error bound, model units (a bound that large keeps one cluster or point).
inline constexpr double kMaxErrorBound = 1e30;
/// Range of `neighbors`, the k of the neighbour graph.
inline constexpr int kMinNeighbors = 1;
inline constexpr int kMaxNeighbors = 64;
/// Largest `particle_iterations`.
inline constexpr int kMaxParticleIterations = 1000;

struct SimplifyOptions {
    SimplifyMethod method = SimplifyMethod::kHierarchical;
    /// Exact number of output points (every method). 0 = use the method's own bound instead:
    /// `error` (iterative, hierarchical) or `max_cluster_size` / `max_variation` (clustering).
    /// Required for particle and voxel, and for iterative without `error`. At most the input's
    /// size (checked by Simplify, not by Validate).
    std::size_t target = 0;
    /// Error bound in model units, 0..kMaxErrorBound: iterative stops before the RMS distance of
    /// a contracted point to its tangent planes would exceed it; hierarchical splits every
    /// cluster whose points lie farther than this from the cluster's plane. 0 = none. Only
    /// hierarchical and iterative take one, and never together with `target`.
    double error = 0.0;
    /// Curvature-adaptive variant: clusters bounded by surface variation, particle radii scaled
    /// by 1 / sigma_n, so more points go where the surface bends.
    bool adaptive = false;
    /// sigma_max, the largest surface variation of a cluster in adaptive clustering (notes 2.1),
    /// kMinMaxVariation..kMaxMaxVariation.
    double max_variation = 0.01;
    /// n_max, the largest cluster of clustering without a target (hierarchical, incremental),
    /// 1..kMaxMaxClusterSize.
    std::size_t max_cluster_size = 10;
    /// What stands for a cluster: its (lifted) centroid, as the notes prescribe, or its member
    /// nearest that point, so that the output is a subset of the input (not for particle).
    SimplifyRepresentative representative = SimplifyRepresentative::kCentroid;
    /// Seeds (incremental) and the initial spreading (particle); every value is valid.
    std::uint64_t seed = 1;
    /// k of the neighbour graph (incremental growth, iterative pairs), kMinNeighbors..kMaxNeighbors.
    int neighbors = 6;
    /// Relaxation steps of the particle simulation, 0..kMaxParticleIterations.
    int particle_iterations = 40;
    /// Positions alone: no normals, splat radii or colours in the result (what CGAL's
    /// simplification functions return; for a caller that estimates them afterwards). Iterative
    /// and particle simulation still estimate the input normals they run on.
    bool positions_only = false;
    bool measure_error = true;          ///< Compute the quality report (Delta_max, Delta_avg).
    std::size_t error_samples = 20000;  ///< |Q| for the quality report (0 = every input point).

    /// Throws Error(kInvalidArgument, "<field>: <what>") for the first bad field, named as in
    /// the job spec (proto SimplifyJob): "method", "target", "error", "max_variation",
    /// "max_cluster_size", "neighbors", "particle_iterations", "representative"; ranges read
    /// "must lie in LO..HI, got V". Combinations: "target: give target or error, not both", "error:
    /// this method takes a target, not an error bound", "target: is required for this method",
    /// "representative: particle simulation places its own points; ...". Options
    /// only: a target above the input's size is checked by Simplify().
    void Validate() const;
};

/// The quality report of one simplification.
struct SimplifyReport {
    std::string method;
    std::string representative;  ///< SimplifyRepresentativeName of the options' representative.
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

/// Simplifies `input` as `options` say. Throws Error(kInvalidArgument) for bad options
/// (options.Validate()) and for an impossible request on this input (an empty cloud, a target
/// above the input size, particle simulation on fewer than 8 points) and Error(kCancelled) when `progress` asks to stop. The result is the same for
/// the same input, options and seed, whatever the thread count.
SimplifyResult Simplify(const PointCloud& input, const SimplifyOptions& options, const ProgressFn& progress = {});

/// The clusters of a simplification: label[i] is the output point input point i went to.
/// Exposed for tests.
struct Clustering {
    std::vector<std::uint32_t> label;
    std::size_t count = 0;
    /// Optional unoriented normal per cluster (hierarchical: the cluster covariance's v0); a zero
    /// vector where the cluster gives none. Empty: none at all.
    std::vector<Vec3f> normals;
};

/// Builds the output cloud from a clustering: `positions` (one per cluster) or, when empty, the
/// cluster centroids (eq. 2.1), those of clusters with 20+ members lifted onto the cluster's
/// least-squares quadratic height field (a centroid lies inside a bent surface); normals as the normalised sum of the members' oriented
/// normals (`normals` may be empty: then estimated on the output and oriented); colours averaged;
/// radius = the largest distance of a member from the representative, at least the distance to the nearest other representative, so splats leave no holes.
/// `positions_only`: the representatives alone (no normals, radii or colours). `input_tree`: a
/// kd-tree over input.positions when the caller has one (else one is built if needed).
PointCloud BuildFromClusters(const PointCloud& input, std::span<const Vec3f> normals, const Clustering& clusters,
                             std::span<const Vec3f> positions = {}, bool positions_only = false,
                             const KdTree* input_tree = nullptr);

/// For each cluster c, the index of its member nearest `near[c]` (or, when `near` is empty, the
/// cluster's centroid), the first in input order on a tie: the kMember representatives. Throws
/// Error(kInternal) for a cluster without members.
std::vector<std::uint32_t> NearestMembers(std::span<const Vec3f> points, const Clustering& clusters,
                                          std::span<const Vec3f> near = {});

/// Current peak resident set size of this process in MiB (Linux VmHWM), 0 when unknown.
double PeakResidentMiB();

}  // namespace surfel
