#pragma once
/// \file
/// The point-set surface of Adamson & Alexa, "Approximating and Intersecting Surfaces from
/// Points" (2003): the implicit function of section 3 and the ray-surface iteration of
/// sections 4-5, evaluated with Gaussian weights theta(d) = exp(-d^2/h^2).

#include <array>
#include <atomic>
#include <cstdint>
#include <limits>
#include <memory>
#include <optional>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/surface/poly_fit.h"

namespace surfel {

/// Most section-4 iterations per ball (AaOptions::max_iterations); the paper's figures need < 10.
inline constexpr int kMaxSurfaceIterations = 1000;
/// Most neighbours a ball radius may enclose (AaOptions::ball_k; the neighbour search's limit).
inline constexpr int kMaxBallNeighbors = 64;

/// How the Gaussian scale varies over the cloud (AaOptions::bandwidth).
enum class AaBandwidth {
    /// One h for every point (the paper's theta(d) = exp(-d^2/h^2)).
    kFixed,
    /// A scale h_j per point from the local sampling density (course notes 1.3, adaptive MLS):
    /// h_j = h * eta~_j / median(eta), eta the spacing of the ball_k-th neighbour, clamped to
    /// [1/kAdaptiveRange, kAdaptiveRange] x the median and smoothed twice over the neighbourhood
    /// (a Gaussian average at the point's own scale), so that the weights, and with them the
    /// surface, vary smoothly. Point j weighs theta_j(x) = exp(-|x - p_j|^2 / h_j^2) wherever x
    /// is, so f(x) stays one smooth function (no switch of scale between balls).
    kAdaptive,
};

/// AaBandwidth::kAdaptive: the per-point scale lies within [1/kAdaptiveRange, kAdaptiveRange] x h.
inline constexpr float kAdaptiveRange = 3.0f;
/// AaOptions::normal_sigma of the normal-aware weights, the default (the CLI's `--weights normal`,
/// the job's NORMAL_AWARE): the best of 0.25, 0.5 and 1 on the buddha, dragon and Lucy
/// (bench/results-render-mesh.md).
inline constexpr float kNormalAwareSigma = 0.5f;
/// AaOptions::boundary, the default: about 1/sqrt(pi) = 0.56, the tangential distance from x to
/// a(x) at the edge of a uniformly sampled half-plane (Gaussian weights exp(-d^2/h^2)); on samples
/// spaced h/2 it puts the edge about a quarter spacing beyond the last row (0.4 cuts into real
/// surface on the dragon: bench/results-render-mesh.md).
inline constexpr float kSurfaceBoundary = 0.5f;
/// AaOptions::h = 0: h = kSurfaceScaleSpacings x the median sample spacing (with the default
/// adaptive bandwidth, the scale of a point whose spacing is the median). The paper leaves h to
/// the user (its rabbit: h = 0.004 x the diameter for 67k points, about 1.1 spacings when the
/// diameter is the bounding box's diagonal). Measured against the meshes of every model in
/// ../shared/data (bench/results-render-mesh.md, session 12), adaptive at 1.4 spacings meets 99.5 %
/// hit agreement and a p95 depth error <= 2e-3 x diag on 28 of 32 views and is no worse than
/// Open3D's Poisson on 28 (fixed at 2 spacings, sessions 5-11: 23 and 6); on the raw range scans
/// it renders as the fixed 2 spacings did (within 0.3 points of agreement). Fixed 1.4 spacings
/// opens holes in a randomly sampled sphere and in the noisy merged bunny scans.
inline constexpr float kSurfaceScaleSpacings = 1.4f;
/// The boundary test never measures in units smaller than this many median spacings: with h
/// below it, the chance offsets of a randomly sampled interior's weighted average would be taken
/// for rims (holes in a random sphere at h = 1.4 spacings).
inline constexpr float kBoundarySpacings = 2.0f;

/// AaOptions::relative_precision, the default: the paper's |c| < 1e-3 h (section 6).
inline constexpr float kPaperRelativePrecision = 1e-3f;

struct AaOptions {
    float h = 0.0f;             ///< Gaussian scale; 0 = kSurfaceScaleSpacings (1.4) x median spacing. Adaptive: the median point's scale.
    int degree = 2;             ///< Local polynomial degree (0 = the paper's analysis, 1, 2).
    float cutoff = 3.0f;        ///< Points farther than cutoff * h are ignored (weight < exp(-9)).
    float precision = 0.0f;     ///< Accept when |c| < precision (absolute); 0 = relative_precision * h.
    /// precision = 0: accept when |c| < relative_precision x h (the paper's section 6: 1e-3, the
    /// default; RenderQuality::kPreview: kPreviewRelativePrecision).
    float relative_precision = kPaperRelativePrecision;
    int max_iterations = 20;    ///< Iterations per ball before giving up.
    float normal_ratio = 0.5f;  ///< Normal well-defined when lambda0 < normal_ratio * lambda1 (Definition 1).
    int ball_k = 6;             ///< Ball radius rho_i encloses the ball_k nearest neighbours (section 5).
    /// One h, or a smooth h_j per point (see AaBandwidth); adaptive by default since session 12
    /// (kSurfaceScaleSpacings: the figures behind the choice).
    AaBandwidth bandwidth = AaBandwidth::kAdaptive;
    /// Region of trust (section 5) at least this many h_j wide: rho_i = max(r_k(i), ball_h * h_i).
    /// 0 = the paper's ball alone. Where samples are sparse the k-th neighbour's ball can be too
    /// small for the iteration to settle in before it leaves the ball (a hole).
    float ball_h = 0.0f;
    /// Thin sheets: 0 = the paper's weights. > 0 (default kNormalAwareSigma): in the render's fits each neighbour's weight
    /// is also multiplied by exp(-((1 - n_j . n_i) / normal_sigma)^2), n_i the oriented normal of
    /// the ball the ray is in and n_j the neighbour's (the cloud's own normals, else estimated and
    /// oriented with EstimateNormals): where the two sheets of a thin part lie within the
    /// support, the fit keeps to the sheet of the ball (robust MLS: normal-aware weights).
    float normal_sigma = kNormalAwareSigma;
    /// Boundary of the surface (course notes 6.3, "Surfaces from normals and weighted averages":
    /// require ||x - a(x)|| below a threshold): a converged hit x is kept only where the weighted
    /// average a(x) of its fit lies within boundary x h_i of it along the support plane (the
    /// notes' distance for their degree-0 surface, where x - a(x) is tangential at f = 0; the
    /// height component here is the fit's curvature, not a sign of a boundary). h_i is the
    /// point's scale, raised where the samples around p_i lie farther apart than the median
    /// spacing (BoundaryScale), so that chance offsets of sparse interiors are not taken for
    /// edges. 0 = no boundary (the paper's surface, which
    /// extrapolates up to a ball radius past the rim of every part).
    float boundary = kSurfaceBoundary;

    /// Throws Error(kInvalidArgument, "<field>: <what>") for the first bad field, named as in the
    /// render job spec: "h" (finite, >= 0; 0 = auto), "precision" (finite, >= 0; 0 = auto),
    /// "degree" (0..2), "max_iterations" (1..kMaxSurfaceIterations), and, not in the job spec,
    /// "relative_precision" (0..1, > 0), "cutoff" (finite, >= 1), "normal_ratio" (0..1), "ball_k" (1..kMaxBallNeighbors), "bandwidth"
    /// (a known kind), "ball_h" (0..10), "normal_sigma" (0..10),
    /// "boundary" (0..10).
    /// Example: "degree: must lie in 0..2, got 3". The default-constructed options are valid.
    void Validate() const;
};

/// Section 3 at one location: a(x) (eq. 1), n(x) (Definition 1) and f(x) = n(x).(a(x) - x) (eq. 5).
/// When the cloud has normals, n(x) is turned to agree with their weighted average, so f > 0
/// inside and f < 0 outside of a closed, outward-oriented surface.
struct AaEvaluation {
    Vec3d a = Vec3d::Zero();
    Vec3d n = Vec3d::Zero();
    double f = 0.0;
    bool well_defined = false;  ///< False where too few points are near or lambda0 ~ lambda1.
};

/// A converged ray-surface intersection.
struct AaHit {
    double t = 0.0;                 ///< Ray parameter (distance when the direction is unit).
    Vec3d position = Vec3d::Zero();
    Vec3d normal = Vec3d::Zero();   ///< Unit; from the cloud's normals if any, else facing the ray.
    std::array<float, 4> color{0, 0, 0, 1};  ///< Weighted colour when the cloud has colours.
    int iterations = 0;
};

/// Work counters, summed by the caller over threads.
struct AaCounters {
    /// Support plane + polynomial fits computed: every iteration's, and each ball's centre fit
    /// once (two threads that computed it at the same time count one evaluation and one hit, so
    /// the counters do not depend on the threads' timing).
    std::uint64_t evaluations = 0;
    std::uint64_t cache_hits = 0;    ///< Ball-centre polynomial look-ups that found (or lost the race to store) it.
    std::uint64_t iterations = 0;    ///< Section-4 iterations run.
    std::uint64_t converged = 0;     ///< Iterations that ended in a hit.
    void Add(const AaCounters& o) {
        evaluations += o.evaluations;
        cache_hits += o.cache_hits;
        iterations += o.iterations;
        converged += o.converged;
    }
};

/// The surface over a cloud (kept by reference: it must outlive this object). Thread-safe:
/// every method is const; the per-ball centre polynomials are cached lazily without locks.
class AaSurface {
public:
    /// Throws Error(kInvalidArgument) when `options` fail AaOptions::Validate(), the cloud has
    /// fewer than 3 points, or h = 0 cannot be derived (all points coincide). The normal
    /// estimation that the normal-aware weights need for a cloud without normals (the longest
    /// part of the setup) runs on its own thread from here on, beside the rest of the setup and
    /// whatever the caller does next (the renderer builds its BVH); the first evaluation (or
    /// WeightNormals()) waits for it. `progress` (a copy of it is kept until then; it must be
    /// callable from any thread) is polled with fraction 0 during that estimation; returning
    /// false makes the first evaluation throw Error(kCancelled).
    explicit AaSurface(const PointCloud& cloud, const AaOptions& options = {}, const ProgressFn& progress = {});
    ~AaSurface();

    float h() const;
    float precision() const;
    const AaOptions& options() const;
    const PointCloud& cloud() const;

    /// Ball i of the bounding volume (section 5): centre p_i, radius rho_i.
    float BallRadius(std::uint32_t i) const;
    /// The Gaussian scale of point i: h() when the bandwidth is fixed, h_i when adaptive.
    float PointScale(std::uint32_t i) const;
    /// The local scale of ball i's boundary test (AaOptions::boundary): h x the Gaussian-weighted
    /// mean sample spacing within 2h of p_i over the median spacing; PointScale(i) when the
    /// boundary is off. Computed on first use and cached.
    float BoundaryScale(std::uint32_t i) const;
    /// The normals the normal-aware weights use (the cloud's or estimated; waits for the
    /// estimation); empty when options().normal_sigma = 0.
    const std::vector<Vec3f>& WeightNormals() const;

    /// Evaluates a(x), n(x), f(x) (section 3).
    AaEvaluation Evaluate(const Vec3d& x) const;

    /// Section 4 inside ball `ball` (its region of trust): starts from the ball centre's cached
    /// polynomial, then iterates support plane -> polynomial -> intersection until the constant
    /// term |c| < precision. Returns the hit with the smallest t in [tmin, tmax] found this way,
    /// or nullopt ("no surface here": no intersection in the ball, ill-defined normal, the
    /// iterate left the ball, or no convergence). `dir` must be unit length. Every call reads the
    /// centre polynomial rounded to the cache's single precision, the call that fills the cache
    /// included, so the result does not depend on the order (or thread) of the calls.
    ///
    /// `known_hit` is the t of a hit the ray already has (+inf when none). A ball whose
    /// centre-polynomial root lies less than kSameSheet * h in front of it is skipped: the
    /// iteration would converge to the same sheet again (sheets closer than that are not
    /// resolved by the fit at scale h anyway). On the bunny this drops about two thirds of the
    /// iteration runs of primary rays.
    std::optional<AaHit> IntersectInBall(std::uint32_t ball, const Vec3d& origin, const Vec3d& dir, double tmin,
                                         double tmax, AaCounters* counters,
                                         double known_hit = std::numeric_limits<double>::infinity()) const;

    /// See IntersectInBall: in units of h.
    static constexpr double kSameSheet = 0.3;

    /// Support (in units of h) of the ball-centre fits, which only seed the iteration.
    static constexpr float kCenterCutoff = 2.0f;

private:
    struct Fit;
    /// `attributes`: also the reference normal and colour (only converged fits need them).
    /// `ball`: the ball the fit serves (its gather reach and, with normal weights, its normal).
    bool FitAt(const Vec3d& r, Fit* fit, float cutoff, bool attributes, std::uint32_t ball) const;
    /// The ball centre's support plane and polynomial (no attributes), from the per-ball cache;
    /// false when that fit is not defined.
    bool CenterFit(std::uint32_t ball, Fit* out, AaCounters* counters) const;
    /// The constructor's setup besides the weight normals: ball radii, h, precision, grid, scales,
    /// caches (run beside the normal estimation).
    void SetUpScales();
    /// Waits for the weight normals (estimated on another thread from the constructor on) and
    /// puts them in grid order, once; rethrows what the estimation threw.
    void AwaitNormals() const;
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

}  // namespace surfel
