#pragma once
/// \file
/// Resampling of a point-sampled surface to a new count or spacing, up or down (course notes,
/// Pauly 2.3: "particle simulation ... can also be used for up-sampling"): particles spread by
/// density, repelled until even, kept on the surface and MLS-projected at the end. The output
/// carries MLS normals oriented like the input's, colours and extra attributes interpolated
/// from the original samples (which stay fixed, like the zombies of notes 3.2.3), and a splat
/// radius per point. Three methods (ResampleMethod): particle (to a count or spacing, up or
/// down), mls (smoothing: every point projected, h from the noise), split (densification by
/// splitting to a spacing, notes 3.2.2-3.2.3).

#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/surface/mls.h"
#include "surfel/surface/surface_error.h"

namespace surfel {

enum class ResampleMethod {
    kParticle,  ///< 2.3: particle simulation on the sampled surface, final MLS projection.
    /// Smoothing (notes 1.3): every input point replaced by its MLS projection Psi_P(p_i), with
    /// the MLS normal; the count, colours and extra attributes stay those of the input. h from
    /// the data by default (ChooseMlsScale: the noise rule), or `mls_h`; `adaptive` makes it
    /// adaptive MLS, h(x) = h eta(x) / median(eta).
    kMls,
    /// Densification by splitting (notes 3.2.2-3.2.3, dynamic sampling): rounds of measuring each
    /// sample's tangent ellipse (the second moments of its 6 nearest neighbours in the tangent
    /// plane, s^2 / 2 I on a hexagonal lattice of spacing s), splitting every sample whose spacing
    /// along the main axis, sqrt(2 lambda_max), exceeds kSplitSlack x the target spacing into two
    /// samples a quarter of that spacing either side on the axis, and relaxing (linear repulsion
    /// within the target spacing, on the tangent planes), until no sample exceeds it (every
    /// region meets the target), or splitting stalls (the samples above it are at most 0.1 % of
    /// all and 4 rounds did not halve them: creases where it does not converge), or
    /// kMaxSplitRounds; a final MLS projection; colours and attributes interpolated from the
    /// input samples, which never move (the zombies). Samples at a rim of the surface (the
    /// input's rim, where the 32 nearest input samples leave an angle gap above 150 degrees,
    /// and the sample's own 16 nearest leave one on that side) are judged by their interior side
    /// only, and the relaxation keeps samples within a quarter of a rim sample's reach past it.
    /// Only adds: regions already denser than the target keep their samples. Target: `spacing`,
    /// or `target` read as the spacing of a hexagonal lattice of that many points on the
    /// input's area (the count is not exact).
    kSplit,
};

/// "particle", "mls", "split".
const char* ResampleMethodName(ResampleMethod method);
/// Parses a method name; nullopt when unknown.
std::optional<ResampleMethod> ParseResampleMethod(std::string_view name);
/// Every method, in declaration order.
inline constexpr std::array<ResampleMethod, 3> kResampleMethods = {ResampleMethod::kParticle, ResampleMethod::kMls,
                                                                   ResampleMethod::kSplit};

/// Limits of ResampleOptions, written once here; the CLI, the worker and the docs read them.
inline constexpr std::size_t kMaxResampleTarget = 1000000000;  ///< Largest output count.
inline constexpr int kMaxResampleIterations = 1000;            ///< Largest `iterations`.
/// The particle method's step per unit force (ParticleParams::gain; eq. 2.2's constant k).
inline constexpr double kResampleGain = 0.5;
/// Smallest input that defines a surface: a sample and its 6 nearest neighbours, and one more.
inline constexpr std::size_t kMinResampleInput = 8;
/// split method: a sample is split while its spacing along the main axis exceeds this many
/// target spacings.
inline constexpr double kSplitSlack = 1.5;
/// split method: split-and-relax rounds at most (each can double a region's density).
inline constexpr int kMaxSplitRounds = 32;

struct ResampleOptions {
    ResampleMethod method = ResampleMethod::kParticle;
    /// Exact number of output points, 1..kMaxResampleTarget, above or below the input's size
    /// (with keep_input: above it, the input's points included). 0 = use `spacing`. The mls
    /// method keeps the input's count: target and spacing must both be 0 there.
    std::size_t target = 0;
    /// Target spacing in model units, > 0: the output gets the count whose hexagonal lattice on
    /// the input's area (sum of 1 / rho, notes 1.1.1) has this nearest-neighbour distance
    /// (area / (sqrt(3)/2 spacing^2) points); with `adaptive` it is the spacing where the
    /// surface variation equals its median. 0 = use `target`. Exactly one of the two is given
    /// (neither for mls). The split method splits until every sample's spacing along its
    /// tangent ellipse's main axis (at a rim: of its interior side) is at most kSplitSlack x
    /// this, or splitting stalls (ResampleMethod::kSplit).
    double spacing = 0.0;
    /// Curvature-adaptive (2.3.4): repulsion radius scaled by 1 / sigma_n relative to the
    /// median, clamped to [1/2, 2], so up to 16x the density where the surface bends most;
    /// sigma_n of the 16 nearest neighbours, put at one scale and averaged over them
    /// (CommonScaleVariation in particle_engine.h).
    /// With the mls method: adaptive MLS (notes 1.3), h(x) = h eta(x) / median(eta).
    bool adaptive = false;
    /// Keep every input point unchanged (with its attributes) and only add points: the input
    /// points repel the new ones but never move. Needs a count above the input's size.
    bool keep_input = false;
    std::uint64_t seed = 1;   ///< Seeds the initial spreading (2.3.1); every value is valid.
    /// Relaxation steps of the particle simulation at most, 0..kMaxResampleIterations. Each
    /// step moves a particle by kResampleGain (r - d) per neighbour at d < r; at that gain 20
    /// steps leave the bunny x4 as even as 40 steps of the engine's default gain 0.3 did (NN CV
    /// 0.089 against 0.091, mean distance to the mesh 1.78e-4 against 1.80e-4, bench/results-resample.md).
    int iterations = 20;
    /// Particle method: stop relaxing once the mean step of a relaxation step falls below this
    /// fraction of the repulsion radius, 0..1 (0 = run every one of `iterations`).
    double relax_tolerance = 0.0;
    /// Particle method: the initial placement (2.3.1) splits each sample's tangent disk among
    /// the particles it receives (true) or jitters them around the sample (false, the notes'
    /// random spreading; the default: at 40 steps the disk start ends slightly less even on the
    /// bunny, NN CV 0.093 against 0.091, bench/README.md).
    bool spread_disk = false;
    /// Particle method: the final MLS projection by cached local fits (the MLS polynomial of
    /// each particle's closest input point, fitted once per input point) instead of one MLS
    /// projection per particle (ParticleParams::cached_fits). Off by default: 20 % less CPU on
    /// the bunny x4 but 11 % more mean distance to the mesh (bench/README.md).
    bool cached_fits = false;
    /// mls method: degree of the MLS polynomial (notes eq. 1.3), kMinMlsDegree..kMaxMlsDegree.
    int mls_degree = 2;
    /// mls method: Gaussian scale h of theta(d) = exp(-d^2 / h^2), model units, >= 0 and finite;
    /// 0 = chosen from the data by ChooseMlsScale (surface/mls.h: the largest scale whose
    /// projection stays within the noise of all smaller ones, found from the residuals of the
    /// local fits; 2 x median spacing on clean data, ~4x that on a 1 %-noise sphere).
    double mls_h = 0.0;
    bool measure_error = true;          ///< Compute the surface error of the result (Delta_max, Delta_avg).
    std::size_t error_samples = 20000;  ///< |Q| for the surface error (0 = every input point).

    /// Throws Error(kInvalidArgument, "<field>: <what>") for the first bad field, named as in
    /// the job spec: "method: unknown method 7", "target: give target or spacing, not both",
    /// "target: give target or spacing", "target: must lie in 1..1e+09, got V",
    /// "spacing: must be positive, got V", "iterations: must lie in 0..1000, got V",
    /// "relax_tolerance: must lie in 0..1, got V",
    /// "mls_degree: must lie in 0..2, got V", "mls_h: must be finite and at least 0, got V",
    /// "target: the mls method keeps the input's points; give neither target nor spacing",
    /// "keep_input: the mls method moves every input point; it cannot keep them", "keep_input:
    /// the split method splits and relaxes the input's points; it cannot keep them". Options only:
    /// counts that the input makes impossible are checked by Resample().
    void Validate() const;
};

/// What a resampling achieved.
struct ResampleReport {
    std::string method;
    bool adaptive = false;
    bool keep_input = false;
    std::size_t input_points = 0;
    std::size_t output_points = 0;
    int iterations = 0;            ///< Relaxation steps run (mls: 0; split: split-and-relax rounds).
    double spacing_mean = 0.0;     ///< Mean nearest-neighbour distance of the output, model units.
    /// Coefficient of variation (std. deviation / mean) of the output's nearest-neighbour
    /// distances: 0 for a hexagonal lattice, about 0.52 for uniform random sampling.
    double spacing_cv = 0.0;
    double time_ms = 0.0;          ///< The algorithm alone (without the error measurement).
    double error_time_ms = 0.0;    ///< Time spent measuring the surface error.
    /// Delta_max / Delta_avg of the input's surface against the output's (notes 2.4, eq. 2.4-2.5).
    std::optional<SurfaceError> error;
    bool normals_estimated = false;  ///< The input had no normals; they were estimated.
    /// mls method: the scale h used (model units; adaptive: the multiplier of eta / median eta).
    double mls_h = 0.0;
    /// mls method with mls_h = 0: the noise sigma that ChooseMlsScale estimated (model units).
    double noise = 0.0;
    /// mls method: points with too few neighbours to project, output where they were.
    std::size_t mls_failed = 0;
    /// split method: samples split in all.
    std::size_t splits = 0;
    /// split method: the largest spacing along a tangent ellipse's main axis after the last
    /// round (model units); <= kSplitSlack x the target spacing when every region met it.
    double max_spacing = 0.0;
    /// split method: samples whose spacing still exceeds kSplitSlack x the target after the last
    /// round (0: every region meets the target), and the regions they form.
    std::size_t above_target = 0;
    std::size_t above_target_regions = 0;
    /// split method: samples at a rim of the surface after the last round, judged by their
    /// interior side.
    std::size_t rim_samples = 0;
};

struct ResampleResult {
    /// Positions; unit normals oriented like the input's; a splat radius per point (the spacing
    /// eta = r_6 sqrt(pi / 6) of the output's own sampling density, notes 1.1.1); colours and
    /// every extra attribute when the input has them (types kept).
    PointCloud cloud;
    ResampleReport report;
};

/// Resamples `input` as `options` say. Throws Error(kInvalidArgument) for bad options
/// (options.Validate()), for an input of fewer than kMinResampleInput points, a spacing whose
/// count is 0 or above kMaxResampleTarget, and a keep_input count not above the input's size;
/// Error(kCancelled) when `progress` asks to stop. The same input, options and seed give the
/// same output whatever the thread count.
ResampleResult Resample(const PointCloud& input, const ResampleOptions& options, const ProgressFn& progress = {});

/// Nearest-neighbour distances of `points` (size >= 2): {mean, coefficient of variation}.
std::array<double, 2> NearestNeighborSpacing(std::span<const Vec3f> points);
/// The same over the points of an existing tree (no second tree built).
std::array<double, 2> NearestNeighborSpacing(const KdTree& tree);

}  // namespace surfel
