#pragma once
/// \file
/// Moving least squares projection (course notes: Alexa 6.2, Pauly 1.3).

#include <memory>
#include <optional>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/spatial/kd_tree.h"

namespace surfel {

/// Limits of MlsOptions, written once here; the CLI and the docs read them.
/// Range of `degree`, the bivariate polynomial over the reference plane (notes eq. 1.3).
inline constexpr int kMinMlsDegree = 0;
inline constexpr int kMaxMlsDegree = 2;
/// Range of `cutoff`, in units of h: below 1 the Gaussian is cut where it still weighs exp(-1).
inline constexpr double kMinMlsCutoff = 1.0;
inline constexpr double kMaxMlsCutoff = 10.0;
/// Range of `max_iterations`: the reference plane needs at least one.
inline constexpr int kMinMlsIterations = 1;
inline constexpr int kMaxMlsIterations = 1000;
/// Largest `tolerance`, in units of h.
inline constexpr double kMaxMlsTolerance = 1.0;
/// Range of `min_neighbors`.
inline constexpr int kMinMlsNeighbors = 1;
inline constexpr int kMaxMlsNeighbors = 100000;
/// The noise rule's candidate scales h0 * sqrt(2)^k, k = 0..kMlsNoiseScales - 1 (up to 16 h0).
inline constexpr int kMlsNoiseScales = 9;
/// The noise rule's confidence factor Gamma of the intervals y_k +- Gamma s_k.
inline constexpr double kMlsNoiseGamma = 1.0;
/// The noise rule's sample: this many input points (strided; all of them when fewer).
inline constexpr std::size_t kMlsNoiseSamples = 256;

/// How MlsSurface chooses h when options.h = 0.
enum class MlsScaleRule {
    /// h0 = 2 x the median spacing (adaptive: DefaultScale of the density). Fine for clean
    /// scans; with noise it averages too few samples (a unit sphere of 20k samples with 1 %
    /// Gaussian noise keeps 0.30 % RMS radial error).
    kSpacing,
    /// The largest scale whose bias stays within the noise: ChooseMlsScale (intersection of
    /// confidence intervals over h0 * sqrt(2)^k). h0 on clean data; on the 1 % noisy sphere
    /// 4 h0 and 0.088 % RMS radial error.
    kNoise,
};

struct MlsOptions {
    /// Gaussian scale of theta(d) = exp(-d^2/h^2), model units, >= 0; 0 = DefaultScale (2 x median spacing).
    float h = 0.0f;
    /// Degree of the bivariate polynomial over the reference plane, kMinMlsDegree..kMaxMlsDegree.
    int degree = 2;
    /// Neighbours within cutoff * h (weights beyond 3h are below exp(-9) = 1.2e-4),
    /// kMinMlsCutoff..kMaxMlsCutoff.
    float cutoff = 3.0f;
    bool adaptive = false;    ///< Adaptive MLS (notes 1.3): h(x) = h * eta(x) / median(eta).
    /// Reference-plane iterations at most, kMinMlsIterations..kMaxMlsIterations.
    int max_iterations = 8;
    /// Stop when the plane's foot point moves less than tolerance * h, 0..kMaxMlsTolerance.
    float tolerance = 1e-3f;
    /// Fewer neighbours within the cutoff: no projection (nullopt), kMinMlsNeighbors..kMaxMlsNeighbors.
    int min_neighbors = 4;
    /// The rule for h = 0 (ignored when h > 0). Default kSpacing, as before the rule existed.
    MlsScaleRule scale_rule = MlsScaleRule::kSpacing;

    /// Throws Error(kInvalidArgument, "<field>: <what>") for the first bad field: "h", "degree",
    /// "cutoff", "max_iterations", "tolerance", "min_neighbors", "scale_rule" (e.g. "degree: must
    /// lie in 0..2, got 3", "scale_rule: unknown rule 5").
    void Validate() const;
};

/// What ChooseMlsScale found.
struct MlsScaleChoice {
    float h = 0.0f;       ///< The chosen scale (model units; adaptive: the multiplier of eta / median eta).
    float h0 = 0.0f;      ///< The spacing rule's scale, the first candidate.
    double noise = 0.0;   ///< Median over the sample of the noise estimate sigma_i, model units.
    double scale_factor = 1.0;  ///< h / h0.
    std::size_t samples = 0;    ///< Sample points that took part.
};

/// Chooses the MLS scale h from the data (MlsScaleRule::kNoise): the largest scale whose
/// projection is still consistent with all smaller ones, within their noise.
///
/// The MLS estimate at a point is a weighted least-squares fit (notes eq. 1.3); with noise of
/// standard deviation sigma in the heights, its value c0 has standard deviation
/// s(h) = sigma sqrt([M^-1 B M^-1]_00), M = sum w t t^T, B = sum w^2 t t^T (t the polynomial's
/// terms), and falls as h grows, while the bias (curvature, features the polynomial cannot
/// follow) grows with h. For each of kMlsNoiseSamples strided input points p_i:
///  1. sigma_i from the residuals r_j of the quadratic fit (whatever `degree`: a plane's
///     residuals on a curved surface are its bias) at the smallest scale h0 (the spacing rule):
///     sigma_i^2 = sum w r^2 / (sum w - tr(M^-1 B)) (the weighted least-squares residual's
///     expectation, so the few samples within h0 are not taken as no noise);
///  2. the projection at h_k = h0 sqrt(2)^k, k = 0..kMlsNoiseScales - 1, as the height
///     y_k = (Psi_k(p_i) - p_i) . n_0 and its standard deviation s_k = sigma_i sqrt(v_k);
///  3. the intersection of confidence intervals (Goldenshluger & Nemirovski 1997, Katkovnik's
///     ICI rule): the largest k for which the intervals [y_j - Gamma s_j, y_j + Gamma s_j],
///     j <= k, Gamma = kMlsNoiseGamma, still share a point. A scale whose estimate leaves every
///     earlier interval has met a bias larger than the noise it removes.
/// h is the median of the chosen h_k over the sample points (one global scale). On clean data
/// s_k is ~0 and the rule keeps h0; on a unit sphere of 20k samples with 1 % Gaussian noise it
/// gives h = 4 h0 = 0.21 and 0.088 % RMS radial error (h0: 0.30 %; best fixed h, 0.2: 0.09 %),
/// with sigma estimated as 0.0095. Gamma = 1: with 1.5 and 2 the rule took one step more there
/// (0.3, where the sphere's shrinkage shows: 0.20 % RMS). Options as for MlsSurface (degree,
/// cutoff, adaptive, ...; h and scale_rule are ignored). Deterministic (the sample is strided, the projections independent). Throws
/// kInvalidArgument like MlsSurface when h0 cannot be derived.
MlsScaleChoice ChooseMlsScale(const PointCloud& cloud, const KdTree& tree, const MlsOptions& options = {});

/// One projection: the point on the MLS surface and the surface normal there.
struct MlsPoint {
    Vec3f position;
    Vec3f normal;          ///< Unit; oriented like the cloud's normals when it has them.
    int iterations = 0;
    int neighbors = 0;
};

/// The MLS fit at one point kept for re-use (a cached local fit): the converged reference plane
/// (foot q, frame u, v, n) and the polynomial g over it (notes eq. 1.3), in world units.
struct MlsPatch {
    Vec3d origin, u, v, n;      ///< The plane's foot q and its frame; g is over (u, v) about q.
    double c[6] = {0, 0, 0, 0, 0, 0};  ///< g(a, b) = c0 + c1 a + c2 b + c3 a^2 + c4 a b + c5 b^2.
    double sign = 1.0;          ///< The normal's orientation: +1 along n, -1 against it.

    /// y moved along n onto the graph of g: q + a u + b v + g(a, b) n, with (a, b) the plane
    /// coordinates of y, and the graph's unit normal there (oriented like the fit's). Exact MLS
    /// at the fit's own point; elsewhere the polynomial's extrapolation, good to O(|(a, b)|^3)
    /// for a distance well within h.
    MlsPoint Project(const Vec3f& y) const;
};

/// The MLS projection operator Psi_P of a point set.
///
/// Reference plane (notes eq. 1.2): minimise sum_i (n.p_i - D)^2 theta(|p_i - q|) where q is the
/// foot of x on the plane. Solved as a fixed point: weights centred at q, the weighted
/// covariance plane through the weighted centroid, then q re-projected from x, until q is
/// stationary. Polynomial (eq. 1.3): weighted least squares fit g(u, v) of degree 0..2 to the
/// heights over the plane with weights theta(|p_i - q|); Psi(x) = q + g(0, 0) n, and the normal
/// is that of the graph of g at (0, 0).
class MlsSurface {
public:
    /// Keeps references to `cloud` and `tree` (built over cloud.positions): both must outlive it.
    /// Calls options.Validate() first; throws kInvalidArgument when h = 0 and the cloud has fewer
    /// than 2 distinct points to derive it from.
    MlsSurface(const PointCloud& cloud, const KdTree& tree, const MlsOptions& options = {});
    ~MlsSurface();

    /// The scale in use (options.h or the default).
    float h() const;
    /// What ChooseMlsScale found when options.h = 0 and the rule is kNoise; nullopt otherwise.
    const std::optional<MlsScaleChoice>& scale_choice() const;

    /// Projects x onto the surface; nullopt where too few points lie within reach.
    std::optional<MlsPoint> Project(const Vec3f& x) const;

    /// The fit that Project(x) uses, kept (MlsPatch); nullopt where Project(x) is.
    /// patch.Project(x) equals Project(x) up to rounding.
    std::optional<MlsPatch> Fit(const Vec3f& x) const;

    /// Projects every point of `points` in parallel; a point that cannot be projected keeps its
    /// position and reports `failed`. Output order equals input order; thread-count independent.
    struct Batch {
        std::vector<Vec3f> positions, normals;
        std::size_t failed = 0;
        double mean_iterations = 0;
    };
    Batch ProjectAll(std::span<const Vec3f> points, const ProgressFn& progress = {}) const;

private:
    friend MlsScaleChoice ChooseMlsScale(const PointCloud&, const KdTree&, const MlsOptions&);
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

}  // namespace surfel
