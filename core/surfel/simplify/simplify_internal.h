#pragma once
// Internal pieces shared by the simplification methods (not installed, not public API).

#include <Eigen/Core>
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <span>
#include <vector>

#include "surfel/base/progress.h"
#include "surfel/resample/particle_engine.h"
#include "surfel/simplify/simplify.h"
#include "surfel/spatial/kd_tree.h"

namespace surfel::detail {

/// Running first and second moments of a point set, in double precision.
struct Moments {
    double n = 0.0;
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    Eigen::Matrix3d outer = Eigen::Matrix3d::Zero();

    void Add(const Vec3f& p) {
        const Eigen::Vector3d d = p.cast<double>();
        n += 1.0;
        sum += d;
        outer.noalias() += d * d.transpose();
    }
    void Add(const Moments& o) {
        n += o.n;
        sum += o.sum;
        outer += o.outer;
    }
    Eigen::Vector3d Centroid() const { return n > 0 ? Eigen::Vector3d(sum / n) : Eigen::Vector3d::Zero(); }
    Eigen::Matrix3d Covariance() const {
        if (n <= 0) return Eigen::Matrix3d::Zero();
        const Eigen::Vector3d c = Centroid();
        Eigen::Matrix3d cov = outer / n - c * c.transpose();
        return 0.5 * (cov + cov.transpose());
    }
};

/// Eigen analysis of a covariance: eigenvalues ascending, v0 (normal) and v2 (largest variance).
struct Spread {
    Eigen::Vector3d eigenvalues = Eigen::Vector3d::Zero();
    Eigen::Vector3d v0 = Eigen::Vector3d::UnitZ();
    Eigen::Vector3d v2 = Eigen::Vector3d::UnitX();
    double Variation() const {
        const double s = eigenvalues.sum();
        return s > 0 ? std::max(0.0, eigenvalues[0]) / s : 0.0;
    }
};
Spread Analyze(const Moments& m);

/// x . y and a y for a symmetric 3x3 a given as a00 a01 a02 a11 a12 a22, written out with the
/// sums in the order of Eigen's `x.dot(y)` and `a * y` on this build (SSE2: a dot as the packet of
/// its first two products, then the third; a product's rows 0 and 1 as a packet, column by column,
/// row 2 by its reduction tree; the same bits, checked against Eigen on 2 M random cases).
/// Session 18: in the pair fit Eigen's product read the matrix's columns back from the stack
/// across two of its stores, and the loads stalled on store forwarding (a third of the fit's
/// samples). The iterative reference (tests) uses them too, so both keep the same numerics
/// whatever the target's vector width.
inline double Dot3(const Eigen::Vector3d& x, const Eigen::Vector3d& y) {
    return (x.x() * y.x() + x.y() * y.y()) + x.z() * y.z();
}
inline Eigen::Vector3d SymmetricTimes(const double* a, const Eigen::Vector3d& y) {
    return {(a[0] * y.x() + a[1] * y.y()) + a[2] * y.z(), (a[1] * y.x() + a[3] * y.y()) + a[4] * y.z(),
            a[2] * y.x() + (a[4] * y.y() + a[5] * y.z())};
}

/// The minimiser of the quadric x^T a x - 2 b^T x (a symmetric, positive semi-definite) by a
/// truncated pseudo-inverse around `mid`: the eigen-directions whose eigenvalue is at most 1e-3 of
/// the largest stay at `mid` (iterative simplification, notes 2.2: the tangent directions of a
/// flat region). When the invariants of `a` prove that every eigenvalue passes (the smallest is at
/// least det / e2, the largest at most the trace, e2 the sum of the principal 2x2 minors, with a
/// 1 % margin) the full inverse (adjugate / det) gives the same point without the eigen solve;
/// when they prove that only the largest passes, its eigenpair alone (found without the solve).
/// Otherwise (creases: two eigenvalues pass, or too close to the 1e-3 line to tell) Eigen's
/// direct 3x3 solve. The shortcuts agree with the solve to rounding, not to the bit.
/// Always inlined (session 18): called, the pair fit's matrix went through the stack, and its
/// 16-byte loads of 8-byte stores stalled on store forwarding (the loop ~3 % faster inlined; the
/// same arithmetic, the same bits).
[[gnu::always_inline]] inline Eigen::Vector3d MinimizeQuadric(const Eigen::Matrix3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& mid) {
    const double a00 = a(0, 0), a01 = a(0, 1), a02 = a(0, 2), a11 = a(1, 1), a12 = a(1, 2), a22 = a(2, 2);
    const double c00 = a11 * a22 - a12 * a12, c01 = a02 * a12 - a01 * a22, c02 = a01 * a12 - a02 * a11;
    const double c11 = a00 * a22 - a02 * a02, c12 = a01 * a02 - a00 * a12, c22 = a00 * a11 - a01 * a01;
    const double det = a00 * c00 + a01 * c01 + a02 * c02;
    const double trace = a00 + a11 + a22, e2 = c00 + c11 + c22;
    // g = b - a mid, written out with Eigen's sums (SSE2: rows 0 and 1 as a packet, column by
    // column, row 2 by its reduction tree; the same bits, checked against `b - a * mid`): Eigen's
    // product read the matrix's columns back from the stack across two of its stores (session 18:
    // a store-forwarding stall on a third of the pair fit's samples).
    const Eigen::Vector3d g(b.x() - ((a00 * mid.x() + a01 * mid.y()) + a02 * mid.z()),
                            b.y() - ((a01 * mid.x() + a11 * mid.y()) + a12 * mid.z()),
                            b.z() - (a02 * mid.x() + (a12 * mid.y() + a22 * mid.z())));
    if (det > 0 && det > 1.01e-3 * trace * e2) {
        const double inv = 1.0 / det;
        return mid + inv * Eigen::Vector3d(c00 * g.x() + c01 * g.y() + c02 * g.z(),
                                           c01 * g.x() + c11 * g.y() + c12 * g.z(),
                                           c02 * g.x() + c12 * g.y() + c22 * g.z());
    }
    // Only the largest eigenvalue passes when the two others, whose sum s = trace - l3 obeys
    // l3 s <= e2, are proven at most 1e-3 l3: l3 >= r+ and s <= r- = e2 / r+ for the roots r+-
    // of l (trace - l) = e2 (l3 >= trace / 3 > r- when e2 < 2 trace^2 / 9), 1 % margin. Then
    // x = mid + v3 (v3 . g) / l3, l3 by Newton's method on the characteristic polynomial from
    // the trace down (monotone: the polynomial is increasing and convex beyond its largest root),
    // v3 the largest cross product of two rows of a - l3 I.
    if (trace > 0 && e2 < (2.0 / 9.0) * trace * trace) {
        const double r_plus = 0.5 * (trace + std::sqrt(trace * trace - 4.0 * e2));
        if (e2 < 0.99e-3 * r_plus * r_plus) {
            double l3 = trace;
            for (int it = 0; it < 32; ++it) {
                const double p = ((l3 - trace) * l3 + e2) * l3 - det;
                const double dp = (3.0 * l3 - 2.0 * trace) * l3 + e2;
                if (!(dp > 0)) break;
                const double next = l3 - p / dp;
                if (!(next < l3)) break;
                l3 = next;
            }
            const Eigen::Vector3d r0(a00 - l3, a01, a02), r1(a01, a11 - l3, a12), r2(a02, a12, a22 - l3);
            const Eigen::Vector3d x01 = r0.cross(r1), x02 = r0.cross(r2), x12 = r1.cross(r2);
            const double n01 = x01.squaredNorm(), n02 = x02.squaredNorm(), n12 = x12.squaredNorm();
            const Eigen::Vector3d& w = n01 >= n02 && n01 >= n12 ? x01 : (n02 >= n12 ? x02 : x12);
            const double wn = std::max({n01, n02, n12});
            if (wn > 0 && l3 > 0) return mid + w * (w.dot(g) / (wn * l3));
        }
    }
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver;
    solver.computeDirect(a);
    const Eigen::Vector3d lambda = solver.eigenvalues();
    const Eigen::Matrix3d& v = solver.eigenvectors();
    const double limit = std::max(lambda.maxCoeff(), 0.0) * 1e-3;
    const Eigen::Vector3d r = v.transpose() * g;
    Eigen::Vector3d x = mid;
    for (int i = 0; i < 3; ++i)
        if (lambda[i] > limit && lambda[i] > 0) x += v.col(i) * (r[i] / lambda[i]);
    return x;
}

// Random, the portable generator, comes with the particle engine (surfel/resample/particle_engine.h).

/// Relabels `label` to 0..count-1 in order of first appearance of each cluster's smallest member
/// index (deterministic), returns count. `bound`, when not 0, is more than every label (the remap
/// table is sized once instead of grown as labels come).
std::size_t Compact(std::vector<std::uint32_t>& label, std::size_t bound = 0);

/// Brings a clustering to exactly `target` clusters: with too many, the clusters with the
/// smallest `weight` (size, or size x variation) are dissolved and their points go to the nearest
/// surviving centroid (the stray redistribution of notes 2.1.1); with too few, the largest are
/// split at their centroid across the axis of largest variance (2.1.2).
void AdjustCount(std::span<const Vec3f> points, Clustering& clusters, std::size_t target, bool adaptive);

Clustering HierarchicalClustering(std::span<const Vec3f> points, const SimplifyOptions& options,
                                  ProgressTracker& progress);
Clustering IncrementalClustering(std::span<const Vec3f> points, const SimplifyOptions& options,
                                 ProgressTracker& progress);
Clustering VoxelClustering(std::span<const Vec3f> points, const SimplifyOptions& options, ProgressTracker& progress);

/// Iterative point-pair contraction (notes 2.2): fills `positions` (one per cluster) and returns
/// the clusters. `knn`: the points' nearest neighbours when the caller has them (rows nearest
/// first, at least options.neighbors columns; the first options.neighbors make the graph), else
/// an empty table (k = 0). Taken by value: it is released as soon as the graph is built, before
/// the larger arrays of the contraction are first touched. `cluster_normals`: the normals are
/// unoriented; give each cluster the sum of its members' normals turned to agree with its
/// surviving point's (Clustering::normals) for BuildFromClusters to orient.
Clustering IterativeSimplification(std::span<const Vec3f> points, std::span<const Vec3f> normals,
                                   KnnTable knn, bool cluster_normals, const SimplifyOptions& options,
                                   std::vector<Vec3f>& positions, ProgressTracker& progress);

}  // namespace surfel::detail
