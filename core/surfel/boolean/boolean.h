#pragma once
/// \file
/// Boolean operations on point-sampled solids (course notes, Pauly 3.1): inside/outside
/// classification (3.1.1, Table 3.1), intersection curves sampled by a Newton-type iteration with
/// adaptive refinement (3.1.2), and sharp creases stored as surfel pairs (3.1.3).

#include <Eigen/Core>
#include <array>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/boolean/blend.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/mls.h"

namespace surfel {

/// The four operations of Table 3.1 on the solids V_A and V_B bounded by the inputs.
enum class BooleanOp {
    kUnion,              ///< A ∪ B.
    kIntersection,       ///< A ∩ B.
    kDifference,         ///< A − B.
    kReverseDifference,  ///< B − A.
};

/// "union", "intersection", "difference", "reverse-difference".
const char* BooleanOpName(BooleanOp op);
/// Parses an operation name; nullopt when unknown.
std::optional<BooleanOp> ParseBooleanOp(std::string_view name);
/// Every operation, in declaration order.
inline constexpr std::array<BooleanOp, 4> kBooleanOps = {
    BooleanOp::kUnion, BooleanOp::kIntersection, BooleanOp::kDifference,
    BooleanOp::kReverseDifference};

/// Limits of BooleanOptions, written once here; the CLI, the worker and the docs read them.
/// Largest deviation of rotation^T rotation from the identity (any entry), and of det from +1.
inline constexpr double kRotationTolerance = 1e-5;
/// Range of `transform.scale`.
inline constexpr double kMinBooleanScale = 1e-6;
inline constexpr double kMaxBooleanScale = 1e6;
/// Range of `curve_band`, in local spacings.
inline constexpr double kMinCurveBand = 0.5;
inline constexpr double kMaxCurveBand = 10.0;
/// Range of `max_newton_iterations`.
inline constexpr int kMinNewtonIterations = 1;
inline constexpr int kMaxNewtonIterations = 100;
/// Range of `newton_tolerance`, in local spacings.
inline constexpr double kMinNewtonTolerance = 1e-7;
inline constexpr double kMaxNewtonTolerance = 0.1;
/// Range of `max_refinement_rounds`.
inline constexpr int kMaxRefinementRounds = 10000;
/// Largest `max_open_area` (a share of the input's area).
inline constexpr double kMaxOpenArea = 1.0;
/// Largest `coincident_tolerance`, in local spacings.
inline constexpr double kMaxCoincidentTolerance = 1.0;
/// Range of a non-zero `upsample_ratio`, and the largest split factor per axis.
inline constexpr double kMinUpsampleRatio = 1.0;
inline constexpr double kMaxUpsampleRatio = 100.0;
inline constexpr int kMaxUpsampleFactor = 8;
/// Smallest input that bounds a volume: a sample, its 6 nearest neighbours, and one more.
inline constexpr std::size_t kMinBooleanInput = 8;

/// Where B is placed: x_world = scale * rotation * x_B + translation. Applied inside the
/// queries (a query x is taken to B's frame as rotation^T (x − translation) / scale), never by
/// transforming a copy of B.
struct Similarity {
    Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();  ///< Orthonormal, det = +1.
    Vec3d translation = Vec3d::Zero();                       ///< Model units.
    double scale = 1.0;  ///< Uniform, kMinBooleanScale..kMaxBooleanScale.

    /// Throws Error(kInvalidArgument) naming "<prefix>.rotation", "<prefix>.translation" or
    /// "<prefix>.scale" (e.g. "transform.scale: must lie in 1e-06..1e+06, got 0").
    void Validate(const std::string& prefix = "transform") const;
};

struct BooleanOptions {
    /// Placement of B in A's frame (identity: as given).
    Similarity transform;
    /// MLS projection of both inputs (classification near the surface, Newton re-projection);
    /// h = 0 derives each input's own scale (2 x its median spacing; B's in B's frame); h > 0 is
    /// in A's (world) units, so B uses h / transform.scale in its own frame.
    MlsOptions mls;
    /// Normal estimation and outward orientation for an input without normals.
    NormalOptions normals;
    /// The coherence-sphere shortcut of 3.1.1: Omega is constant within ||x − p|| − eta_p of a
    /// classified query x, so queries inside a recent sphere are not searched again.
    bool coherence = true;
    /// A kept sample whose MLS distance to the other surface is below curve_band local spacings
    /// seeds the curve (3.1.2), kMinCurveBand..kMaxCurveBand.
    double curve_band = 1.5;
    /// Newton iterations per curve sample at most, kMinNewtonIterations..kMaxNewtonIterations.
    int max_newton_iterations = 20;
    /// The iteration has converged when r lies on both surfaces: its re-projections onto both
    /// move it less than newton_tolerance local spacings (the finer side's),
    /// kMinNewtonTolerance..kMaxNewtonTolerance. The MLS projection itself stops at 1e-3 h (2e-3
    /// spacings); on the bunny ∪ a rotated copy 1e-3 takes 2.9 iterations on average, 1e-4 3.7.
    double newton_tolerance = 1e-3;
    /// Subdivision rounds of the curve at most (3.1.2, Figure 3.5), 0..kMaxRefinementRounds;
    /// 0 = keep the curve samples the closest pairs gave.
    int max_refinement_rounds = 200;
    /// An input whose open area share |sum_i a_i n_i| / sum_i a_i (a_i = eta_i^2; 0 on a closed
    /// surface, whose vector area vanishes; the holes' vector area otherwise) exceeds this does
    /// not bound a volume: kInvalidArgument naming the input. 0..kMaxOpenArea; 0 = no check.
    /// Measured with estimated normals: closed reconstructions of ../shared/data 0.003-0.014 (the
    /// bunny's small holes at its base included, Max Planck's open base 0.026), single range scans
    /// 0.65-0.79, a hemisphere 0.5. Holes whose vector areas cancel (a tube open at both ends)
    /// pass.
    double max_open_area = 0.05;
    /// A sample within coincident_tolerance local spacings of the other MLS surface lies on it (a
    /// coincident or touching face, which Table 3.1 leaves open): with the normals agreeing the
    /// face stays once (A's samples) in the union and the intersection and goes in both
    /// differences; with them opposed it goes in the union and the intersection and stays on the
    /// minuend's side of a difference (regularised CSG). 0..kMaxCoincidentTolerance; 0 = off.
    double coincident_tolerance = 0.01;
    /// Where one input's spacing near the curve exceeds upsample_ratio times the other's, its
    /// kept samples within 2 spacings of the curve are split to the finer density (3.1.2, by the
    /// splitting of 3.2.2): each into an n x n grid over its tangent square, n = round(ratio) up
    /// to kMaxUpsampleFactor, MLS-projected and classified. 0 = off, else
    /// kMinUpsampleRatio..kMaxUpsampleRatio.
    double upsample_ratio = 1.5;
    /// Particle-based blending of the creases (3.1.4, BlendCreases): the samples within
    /// blend_radius (model units, A's frame) of the intersection curve relax into a smooth blend.
    /// 0 = off: sharp creases as surfel pairs.
    double blend_radius = 0.0;
    /// Simulation steps of the blending, kMinBlendIterations..kMaxBlendIterations; more give a
    /// rounder blend (the notes: "the degree of smoothness can be controlled by the number of
    /// iterations").
    int blend_iterations = kDefaultBlendIterations;

    /// Throws Error(kInvalidArgument, "<field>: <what>") for the first bad field:
    /// "transform.rotation", "transform.translation", "transform.scale", the MLS fields as
    /// "mls.<field>", the normal fields as "normals.<field>", "curve_band",
    /// "max_newton_iterations", "newton_tolerance", "max_refinement_rounds", "max_open_area",
    /// "coincident_tolerance", "upsample_ratio", "blend_radius", "blend_iterations".
    void Validate() const;
};

/// Names of the extra vertex properties of a boolean result (PLY "property float crease_nx" ...).
/// Every output sample has them: a curve sample (a surfel pair, 3.1.3) has crease = 1, its A-side
/// normal in `normals` and its B-side normal in crease_n{x,y,z}, both oriented outward of the
/// result; every other sample has crease = 0 and crease_n = 0. `source` says where a sample
/// came from: 0 = A, 1 = B, 2 = the intersection curve.
inline constexpr const char* kCreaseAttribute = "crease";
inline constexpr const char* kCreaseNormalX = "crease_nx";
inline constexpr const char* kCreaseNormalY = "crease_ny";
inline constexpr const char* kCreaseNormalZ = "crease_nz";
inline constexpr const char* kSourceAttribute = "source";

struct BooleanReport {
    std::string op;  ///< BooleanOpName.
    std::size_t input_points_a = 0, input_points_b = 0;
    std::size_t kept_a = 0;       ///< |Q_1|: A's samples in the output as they were.
    std::size_t kept_b = 0;       ///< |Q_2|.
    std::size_t upsampled_a = 0;  ///< A's kept samples split near the curve (not in kept_a).
    std::size_t upsampled_b = 0;
    std::size_t added_a = 0;  ///< Samples the splits added on A's surface.
    std::size_t added_b = 0;
    std::size_t curve_samples = 0;           ///< Surfel pairs on the intersection curve.
    std::size_t curve_seeds = 0;             ///< Closest pairs the Newton iteration started from.
    std::size_t curve_refined = 0;           ///< Curve samples the refinement added.
    double mean_newton_iterations = 0.0;     ///< Over converged curve samples.
    std::size_t newton_failures = 0;         ///< Starts that did not converge (discarded).
    std::size_t classification_queries = 0;  ///< Omega evaluations asked for (|A| + |B|).
    std::size_t queries_saved = 0;           ///< Answered by a coherence sphere, no search.
    double queries_saved_share = 0.0;        ///< queries_saved / classification_queries.
    std::size_t mls_classifications = 0;     ///< Searched queries that needed the MLS projection.
    bool normals_estimated_a = false, normals_estimated_b = false;
    bool overlap = true;             ///< false: the bounding boxes are disjoint.
    std::vector<std::string> notes;  ///< E.g. the trivial answer for disjoint inputs.
    double blend_radius = 0.0;       ///< BooleanOptions::blend_radius.
    BlendReport blend;               ///< What the blending did (all 0 without blend_radius).
    double time_ms = 0.0;
};

struct BooleanResult {
    /// Q_1 (A's kept samples, input order; then the samples its up-sampling added), then Q_2
    /// (B's, placed by the transform; then its added ones), then the curve samples. Unit normals
    /// outward of the result (a subtracted solid's flipped), a splat radius per point (the input's
    /// radius if it has them, else its spacing eta, notes 1.1.1; times scale for B; the finer
    /// side's spacing on the curve) and the extras named above. Colours and the inputs' own extra
    /// attributes are not carried.
    PointCloud cloud;
    BooleanReport report;
};

/// The boolean `op` of the solids bounded by A and B (B placed by options.transform).
///
/// Classification (3.1.1, eq. 3.1): Omega_P(x) by the closest sample p and its outward normal,
/// outside iff (x − p) . n_p > 0; where ||x − p|| is below the spacing eta_p, by the MLS
/// projection y of x and its normal instead. Table 3.1 picks Q_1 and Q_2. Curve (3.1.2): kept
/// samples near the other surface, closest pairs, r = the point of the line of the two tangent
/// planes closest to both, re-projected onto both MLS surfaces until converged; then midpoints of
/// neighbouring curve samples farther apart than the local spacing are iterated too (and a start
/// one spacing ahead where a sample has no neighbour within 3 spacings on one side). Where one
/// input is coarser near the curve its samples there are split (options.upsample_ratio).
///
/// Throws Error(kInvalidArgument) for bad options, an input of fewer than kMinBooleanInput points
/// or with a non-finite position ("a: ..." / "b: ..."), and an input that does not bound a volume
/// ("b: does not bound a volume: its outward normals do not close (... = 0.65, ...)", see
/// max_open_area); Error(kCancelled) when `progress` asks to stop. Disjoint bounding boxes give
/// the trivial answer with a note; an empty result is an empty cloud (with the extras), not an
/// error. Deterministic: the same inputs and options give the same output whatever the thread
/// count.
BooleanResult Boolean(const PointCloud& a, const PointCloud& b, BooleanOp op,
                      const BooleanOptions& options = {}, const ProgressFn& progress = {});

}  // namespace surfel
