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

    /// Throws Error(kInvalidArgument, "<field>: <what>") for the first bad field: "h", "degree",
    /// "cutoff", "max_iterations", "tolerance", "min_neighbors" (e.g. "degree: must lie in 0..2, got 3").
    void Validate() const;
};

/// One projection: the point on the MLS surface and the surface normal there.
struct MlsPoint {
    Vec3f position;
    Vec3f normal;          ///< Unit; oriented like the cloud's normals when it has them.
    int iterations = 0;
    int neighbors = 0;
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

    /// Projects x onto the surface; nullopt where too few points lie within reach.
    std::optional<MlsPoint> Project(const Vec3f& x) const;

    /// Projects every point of `points` in parallel; a point that cannot be projected keeps its
    /// position and reports `failed`. Output order equals input order; thread-count independent.
    struct Batch {
        std::vector<Vec3f> positions, normals;
        std::size_t failed = 0;
        double mean_iterations = 0;
    };
    Batch ProjectAll(std::span<const Vec3f> points, const ProgressFn& progress = {}) const;

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

}  // namespace surfel
