#pragma once
/// \file
/// Moving least squares projection (course notes: Alexa 6.2, Pauly 1.3).

#include <memory>
#include <optional>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/spatial/kd_tree.h"

namespace surfel {

struct MlsOptions {
    float h = 0.0f;           ///< Gaussian scale of theta(d) = exp(-d^2/h^2); 0 = DefaultScale (2 x median spacing).
    int degree = 2;           ///< Degree of the bivariate polynomial over the reference plane: 0, 1 or 2.
    float cutoff = 3.0f;      ///< Neighbours within cutoff * h (notes 1.3: weights below 1e-3 beyond 3h... exp(-9)).
    bool adaptive = false;    ///< Adaptive MLS (notes 1.3): h(x) = h * eta(x) / median(eta).
    int max_iterations = 8;   ///< Reference-plane iterations.
    float tolerance = 1e-3f;  ///< Stop when the plane's foot point moves less than tolerance * h.
    int min_neighbors = 4;    ///< Fewer neighbours within the cutoff: no projection (nullopt).
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
