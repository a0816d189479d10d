#include "surfel/surface/mls.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <numeric>
#include <string>

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/surface/fit_kernels.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/poly_fit.h"
#include "surfel/spatial/uniform_grid.h"

namespace surfel {
namespace {

// Statistics of one polynomial fit for the noise rule (ChooseMlsScale): sum w r^2, and in the
// scaled terms t = (1, x/h, y/h, x^2/h^2, x y/h^2, y^2/h^2) of the fitted degree, with
// M = sum w t t^T and B = sum w^2 t t^T: sum w - tr(M^-1 B) (the residual's degrees of freedom)
// and [M^-1 B M^-1]_00 (the variance of c0 per unit noise variance).
struct FitStats {
    double residual2 = 0.0;
    double dof = 0.0;
    double variance = 0.0;
    bool valid = false;
};

FitStats ComputeFitStats(const NeighborBatch& nb, int degree, double h, const PolyCoeffs& g) {
    const int terms = degree == 0 ? 1 : degree == 1 ? 3 : 6;
    Eigen::Matrix<double, 6, 6> M = Eigen::Matrix<double, 6, 6>::Zero(), B = Eigen::Matrix<double, 6, 6>::Zero();
    FitStats st;
    double wsum = 0.0;
    for (std::size_t j = 0; j < nb.size(); ++j) {
        const double x = nb.lx[j], y = nb.ly[j], w = nb.w[j];
        const double r = nb.lz[j] - g(x, y);
        st.residual2 += w * r * r;
        wsum += w;
        const double xs = x / h, ys = y / h;
        Eigen::Matrix<double, 6, 1> t;
        t << 1.0, xs, ys, xs * xs, xs * ys, ys * ys;
        M.noalias() += w * t * t.transpose();
        B.noalias() += (w * w) * t * t.transpose();
    }
    const Eigen::MatrixXd Mt = M.topLeftCorner(terms, terms), Bt = B.topLeftCorner(terms, terms);
    const Eigen::LDLT<Eigen::MatrixXd> ldlt(Mt);
    if (ldlt.info() != Eigen::Success || !(ldlt.vectorD().minCoeff() > 1e-10 * ldlt.vectorD().cwiseAbs().maxCoeff()))
        return st;
    const Eigen::MatrixXd MiB = ldlt.solve(Bt);
    const Eigen::VectorXd e0 = ldlt.solve(Eigen::VectorXd::Unit(terms, 0));
    st.dof = wsum - MiB.trace();
    st.variance = e0.dot(Bt * e0);
    st.valid = std::isfinite(st.variance) && st.dof > 0;
    return st;
}

// The eigenvector of the smallest eigenvalue of the symmetric 3x3 matrix `mat` (lower triangle
// read), to the bit as Eigen::SelfAdjointEigenSolver<Matrix3d>::computeDirect(mat)
// .eigenvectors().col(0): Eigen 3.4's direct_selfadjoint_eigenvalues<., 3, false>::run step for
// step, with its own computeRoots and extract_kernel, less what col(0) does not need (the other
// eigenvectors where col(0) is found first, the eigenvalues' rescaling). The reference plane's
// normal (one per iteration per projection) spent a third of its solve there.
Vec3d SmallestEigenvector(const Eigen::Matrix3d& mat) {
    using Direct = Eigen::internal::direct_selfadjoint_eigenvalues<Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>, 3, false>;
    const double eps = Eigen::NumTraits<double>::epsilon();
    // Shifted to the mean eigenvalue and scaled into [-1, 1], as Eigen does.
    const double shift = mat.trace() / 3.0;
    Eigen::Matrix3d scaled = mat.selfadjointView<Eigen::Lower>();
    scaled.diagonal().array() -= shift;
    const double scale = scaled.cwiseAbs().maxCoeff();
    if (scale > 0) scaled /= scale;
    Vec3d eivals;
    Direct::computeRoots(scaled, eivals);
    if ((eivals(2) - eivals(0)) <= eps) return Vec3d::UnitX();  // Eigen: the identity
    Eigen::Matrix3d eivecs, tmp = scaled;
    double d0 = eivals(2) - eivals(1);
    const double d1 = eivals(1) - eivals(0);
    if (d0 > d1) {  // the largest eigenvalue is the most distinct: its vector first (k = 2, l = 0)
        d0 = d1;
        tmp.diagonal().array() -= eivals(2);
        Direct::extract_kernel(tmp, eivecs.col(2), eivecs.col(0));
        if (d0 <= 2 * eps * d1) {
            eivecs.col(0) -= eivecs.col(2).dot(eivecs.col(0)) * eivecs.col(0);
            eivecs.col(0).normalize();
        } else {
            tmp = scaled;
            tmp.diagonal().array() -= eivals(0);
            Vec3d dummy;
            Direct::extract_kernel(tmp, eivecs.col(0), dummy);
        }
    } else {  // the smallest is (k = 0): Eigen's next two vectors leave col(0) alone
        tmp.diagonal().array() -= eivals(0);
        Direct::extract_kernel(tmp, eivecs.col(0), eivecs.col(2));
    }
    return eivecs.col(0);
}

// The points within `reach` of a centre c, in the grid's cell order, as structure of arrays: a
// per-thread superset of the neighbourhoods of the next projections (the render's, aa_surface.cpp).
// ProjectAll visits its points in a spatial order, so a gather within `radius` of x whose ball
// lies inside this one (|x - c| + radius <= reach) filters these points instead of walking the
// grid's columns. The dense grid visits its points in ascending cell order, so the filtered list
// is the one the grid walk gives, in the same order, with the same float test: the fits are
// unchanged.
struct Superset {
    std::uint64_t owner = 0;  // MlsSurface::Impl id the points belong to; 0 = empty
    Vec3f c = Vec3f::Zero();
    float reach = 0.0f;
    std::vector<float> x, y, z;
    std::vector<std::uint32_t> index;
    std::vector<float> d2;            // scratch: squared distances to the current gather's origin
    std::vector<std::uint32_t> keep;  // scratch: positions of the accepted points
    std::size_t n = 0;
    int at[3] = {0, 0, 0};            // FillBlock's cell

    /// Room for `need` points (doubling, at least 1024), keeping the first n.
    void Reserve(std::size_t need) {
        if (need <= index.size()) return;
        const std::size_t cap = std::max<std::size_t>(1024, 2 * need);
        for (auto* v : {&x, &y, &z, &d2}) v->resize(cap);
        index.resize(cap);
        keep.resize(cap);
    }
};
thread_local Superset tls_superset;
// ProjectAll over the cloud's own points: the 3 x 3 x 3 block of grid cells around the current
// query's cell (FillBlock), per thread.
thread_local Superset tls_block;
std::atomic<std::uint64_t> next_surface_id{1};

// How far (in units of h) the superset reaches beyond the gather that filled it, and the cell
// (in units of h) of ProjectAll's visiting order.
// Measured on bunny_scan (surfel project, callgrind, whole process): margin 0.5 / 1 / 2 / 3 h
// with cells of 1 h: 2.01 / 1.85 / 1.80 / 1.81 G instructions (no superset: 1.90 G); cells of
// 0.5 / 2 h change it by under 0.5 % at margin 2. A margin of 0.5 / 0.67 / 1 x the radius
// instead was no better at cutoff 3, 2 (h / 2) or 1.5 (bench/README.md).
constexpr float kSupersetMargin = 2.0f;
constexpr float kOrderCell = 1.0f;

// Fills `s` with the points within `reach` of c, in ascending cell order (dense grid only).
void FillSuperset(const UniformGrid& grid, std::uint64_t owner, const Vec3f& c, float reach, Superset& s) {
    s.owner = 0;
    s.n = 0;
    const float r2 = reach * reach;
    const Vec3f* pts = grid.sorted_points();
    const std::uint32_t* idx = grid.sorted_indices();
    grid.ForEachCandidateRun(c, reach, [&](std::uint32_t first, std::uint32_t last) {
        s.Reserve(s.n + (last - first));
        std::size_t n = s.n;
        float *X = s.x.data(), *Y = s.y.data(), *Z = s.z.data();
        std::uint32_t* I = s.index.data();
        for (std::uint32_t j = first; j < last; ++j) {
            const Vec3f p = pts[j];
            const Vec3f e = p - c;
            X[n] = p.x();
            Y[n] = p.y();
            Z[n] = p.z();
            I[n] = idx[j];
            n += e.squaredNorm() <= r2 ? 1 : 0;
        }
        s.n = n;
    });
    s.c = c;
    s.reach = reach;
    s.owner = owner;
}

// Fills `s` with the points of the 3 x 3 x 3 block of cells around cell `at` (dense grid only),
// in ascending cell order: a superset of the ball within cell() of any point of cell `at` that
// lies at least a hair inside its cell (UniformGrid::BlockReach). ProjectAll over the cloud's own
// points visits them cell by cell (the grid's order), so each thread fills one block per cell.
void FillBlock(const UniformGrid& grid, std::uint64_t owner, const int at[3], Superset& s) {
    s.owner = 0;
    s.n = 0;
    const Vec3f* pts = grid.sorted_points();
    const std::uint32_t* idx = grid.sorted_indices();
    grid.ForEachBlockRun(at, [&](std::uint32_t first, std::uint32_t last) {
        s.Reserve(s.n + (last - first));
        std::size_t n = s.n;
        float *X = s.x.data(), *Y = s.y.data(), *Z = s.z.data();
        std::uint32_t* I = s.index.data();
        for (std::uint32_t j = first; j < last; ++j, ++n) {
            X[n] = pts[j].x();
            Y[n] = pts[j].y();
            Z[n] = pts[j].z();
            I[n] = idx[j];
        }
        s.n = n;
    });
    for (int a = 0; a < 3; ++a) s.at[a] = at[a];
    s.owner = owner;
}

// Spreads the low 21 bits of v to every third bit (a Morton code's axis).
std::uint64_t Spread3(std::uint32_t v) {
    std::uint64_t x = v & 0x1fffff;
    x = (x | x << 32) & 0x1f00000000ffffULL;
    x = (x | x << 16) & 0x1f0000ff0000ffULL;
    x = (x | x << 8) & 0x100f00f00f00f00fULL;
    x = (x | x << 4) & 0x10c30c30c30c30c3ULL;
    x = (x | x << 2) & 0x1249249249249249ULL;
    return x;
}

}  // namespace

struct MlsSurface::Impl {
    const PointCloud& cloud;
    const KdTree& tree;
    MlsOptions opt;
    SamplingDensity density;  // only for adaptive h
    std::unique_ptr<UniformGrid> grid;  // fixed h: neighbours within cutoff * h, cell = cutoff * h
    BoundingBox box;                    // of the cloud, when the grid was built
    std::optional<MlsScaleChoice> choice;  // the noise rule's, when it chose h
    // The fit's inner loops (weights, moments, local coordinates, normal equations): the
    // render's kernels, AVX2 where the CPU has it (fit_kernels.h).
    const fit_kernels::Kernels* kernels = &fit_kernels::Best();
    const std::uint64_t id = next_surface_id.fetch_add(1);  // owner tag of the per-thread superset

    Impl(const PointCloud& c, const KdTree& t, const MlsOptions& o) : cloud(c), tree(t), opt(o) {}

    // Local h at x for the adaptive variant: a Gaussian-weighted average of the spacing of the
    // 6 nearest samples (a smooth continuation of eta_i), scaled so that the median maps to h.
    float LocalH(const Vec3f& x, std::vector<Neighbor>& buf) const {
        if (!opt.adaptive) return opt.h;
        tree.Knn(x, 6, &buf);
        const float r2 = buf.back().dist2 > 0 ? buf.back().dist2 : 1.0f;
        double ws = 0, es = 0;
        for (const auto& nb : buf) {
            const double w = std::exp(-nb.dist2 / r2);
            ws += w;
            es += w * density.spacing[nb.index];
        }
        return static_cast<float>(opt.h * (es / ws) / density.median_spacing);
    }

    // nb.Weights(h) and nb.WeightsAround(c, h) (poly_fit.h), through the kernels: the same bits.
    void Weights(NeighborBatch& nb, double h) const {
        kernels->gauss_weights(nb.d2.data(), static_cast<float>(1.0 / (h * h)), nb.w.data(), nb.size());
    }
    void WeightsAround(NeighborBatch& nb, const Vec3d& c, double h) const {
        kernels->squared_distances_around(nb.x.data(), nb.y.data(), nb.z.data(), nb.size(), c.x(), c.y(), c.z(),
                                          nb.d2.data());
        Weights(nb, h);
    }

    // The neighbours within `radius` of o, relative to o, as the grid walk and PushWithin give
    // them (the same points in the same order, the same float offsets and d2), from the thread's
    // superset, refilled (margin kSupersetMargin x h) when it does not cover the ball. Three
    // passes: the squared distances (x^2 + (y^2 + z^2), PushWithin's squaredNorm, vectorised),
    // the accepted positions (a branch-free compaction), then the accepted offsets.
    void GatherFromSuperset(const Vec3f& o, float radius, float h, NeighborBatch& nb) const {
        nb.clear();
        Superset& s = tls_superset;
        // Covered when |o - c| + radius <= reach, less a hair for the rounding of these floats.
        if (!(s.owner == id && (o - s.c).norm() + radius <= s.reach * (1.0f - 1e-4f)))
            FillSuperset(*grid, id, o, radius + kSupersetMargin * h, s);
        FilterSuperset(s, o, radius, nb);
    }

    // The gather within `radius` of o, one of the cloud's points, in grid cell `at` (ProjectAll
    // over the cloud's own points), from the thread's block of the 3 x 3 x 3 cells around `at`:
    // the same points in the same order as the grid walk when the block holds the ball
    // (BlockReach); false (nothing gathered) for the few points within a hair of their cell's
    // faces, which walk the grid.
    bool GatherFromBlock(const Vec3f& o, float radius, const int at[3], NeighborBatch& nb) const {
        nb.clear();
        if (!(grid->BlockReach(o, at) >= radius)) return false;
        Superset& s = tls_block;
        if (!(s.owner == id && s.at[0] == at[0] && s.at[1] == at[1] && s.at[2] == at[2]))
            FillBlock(*grid, id, at, s);
        FilterSuperset(s, o, radius, nb);
        return true;
    }

    // The points of `s` within `radius` of o (PushWithin's float test), relative to o, in the
    // order of `s`: the squared distances (x^2 + (y^2 + z^2), PushWithin's squaredNorm,
    // vectorised), the accepted positions (a branch-free compaction), then the accepted offsets.
    void FilterSuperset(Superset& s, const Vec3f& o, float radius, NeighborBatch& nb) const {
        const std::size_t m = s.n;
        const float r2 = radius * radius;
        const float ox = o.x(), oy = o.y(), oz = o.z();
        const float *SX = s.x.data(), *SY = s.y.data(), *SZ = s.z.data();
        float* SD = s.d2.data();
        kernels->squared_distances(SX, SY, SZ, m, ox, oy, oz, SD);
        std::uint32_t* K = s.keep.data();
        std::size_t n = 0;
        for (std::size_t j = 0; j < m; ++j) {
            K[n] = static_cast<std::uint32_t>(j);
            n += SD[j] <= r2 ? 1 : 0;
        }
        nb.Reserve(n);
        const std::uint32_t* SI = s.index.data();
        float *X = nb.x.data(), *Y = nb.y.data(), *Z = nb.z.data(), *D = nb.d2.data();
        std::uint32_t* I = nb.index.data();
        for (std::size_t k = 0; k < n; ++k) {
            const std::uint32_t j = K[k];
            X[k] = SX[j] - ox;
            Y[k] = SY[j] - oy;
            Z[k] = SZ[j] - oz;
            D[k] = SD[j];
            I[k] = SI[j];
        }
        nb.Resize(n);
    }

    // The order in which ProjectAll visits `points`: along a Morton curve over cells of
    // kOrderCell x h (ties by index), so that consecutive projections share the thread's
    // superset. Each projection is independent of the order; only the time changes.
    std::vector<std::uint32_t> VisitOrder(std::span<const Vec3f> points) const {
        std::vector<std::uint32_t> order(points.size());
        std::iota(order.begin(), order.end(), 0u);
        if (!grid || !grid->dense() || points.empty()) return order;
        const Vec3f lo = box.min;  // the grid's points; queries outside clamp to its faces
        const float inv = 1.0f / (kOrderCell * opt.h);
        // A cell coordinate in 0..2^21 - 1 (non-finite and outside values clamp: order only).
        const auto cell = [&](float v) {
            const float c = v * inv;
            return c > 0.0f ? static_cast<std::uint32_t>(std::min(c, float(0x1fffff))) : 0u;
        };
        std::vector<std::uint64_t> key(points.size());
        for (std::size_t i = 0; i < points.size(); ++i) {
            const Vec3f d = points[i] - lo;
            key[i] = Spread3(cell(d.x())) << 2 | Spread3(cell(d.y())) << 1 | Spread3(cell(d.z()));
        }
        std::sort(order.begin(), order.end(),
                  [&](std::uint32_t a, std::uint32_t b) { return key[a] < key[b] || (key[a] == key[b] && a < b); });
        return order;
    }

    // `superset`: gather through the thread's superset (ProjectAll, whose visiting order keeps
    // consecutive points close); lone projections (booleans, patches) walk the grid, where a
    // refill at radius + 2h would cost more than it saves.
    // `block_at`: xf is one of the cloud's points and lies in that grid cell (ProjectAll over
    // the cloud's own points); gather through the thread's block of cells around it.
    std::optional<MlsPoint> Project(const Vec3f& xf, std::vector<Neighbor>& nbrs, FitStats* stats = nullptr,
                                    MlsPatch* patch = nullptr, bool superset = false,
                                    const int* block_at = nullptr) const {
        const float h = LocalH(xf, nbrs);
        const Vec3d x = xf.cast<double>();
        // Neighbours relative to x (small, well-conditioned numbers), as arrays for the
        // vectorised kernels.
        thread_local NeighborBatch nb;
        nb.clear();
        if (block_at && GatherFromBlock(xf, opt.cutoff * h, block_at, nb)) {
        } else if (superset && grid && grid->dense()) {
            GatherFromSuperset(xf, opt.cutoff * h, h, nb);
        } else if (grid) {
            const float radius = opt.cutoff * h;
            grid->ForEachCandidateRun(xf, radius, [&](std::uint32_t first, std::uint32_t last) {
                nb.PushWithin(grid->sorted_points() + first, grid->sorted_indices() + first, last - first, xf,
                              radius * radius);
            });
        } else {
            tree.Radius(xf, opt.cutoff * h, &nbrs);
            const auto pts = tree.points();
            for (const Neighbor& nbr : nbrs) nb.Push(nbr.index, pts[nbr.index] - xf);
        }
        const std::size_t m = nb.size();
        if (static_cast<int>(m) < opt.min_neighbors) return std::nullopt;
        Vec3d q = Vec3d::Zero(), n = Vec3d::Zero();  // q relative to x
        int it = 0;
        bool converged = false;
        for (; it < opt.max_iterations; ++it) {
            // Reference plane (notes 1.3): weighted centroid and covariance around q, in one pass
            // over the first and second moments about x.
            if (it == 0) Weights(nb, h);  // centred at x: the distances of the gather
            else WeightsAround(nb, q, h);
            double mom[10];
            kernels->moments(nb.x.data(), nb.y.data(), nb.z.data(), nb.w.data(), m, mom);
            const WeightedMoments wm{mom[0], mom[1], mom[2], mom[3], mom[4], mom[5], mom[6], mom[7], mom[8], mom[9]};
            if (!(wm.w > 1e-12)) return std::nullopt;
            const Vec3d c = Vec3d(wm.x, wm.y, wm.z) / wm.w;
            Eigen::Matrix3d C = wm.Second();
            C -= wm.w * c * c.transpose();
            Vec3d nn = SmallestEigenvector(C).normalized();  // computeDirect(C)'s col(0), to the bit
            if (it > 0 && nn.dot(n) < 0) nn = -nn;
            n = nn;
            // The foot of x on the plane through c with normal n: x - ((x - c) . n) n, relative to x.
            const Vec3d q_next = c.dot(n) * n;
            const double moved = (q_next - q).norm();
            q = q_next;
            if (moved < opt.tolerance * h) {
                ++it;
                converged = true;
                break;
            }
        }
        // Polynomial over the plane, weights centred at q. Once converged, the last iteration's
        // weights are those (centred within tolerance * h of q) and are reused.
        const LocalFrame frame = LocalFrame::FromNormal(q, n);
        if (!converged) WeightsAround(nb, q, h);
        const double f[12] = {q.x(),       q.y(),       q.z(),       frame.u.x(), frame.u.y(), frame.u.z(),
                              frame.v.x(), frame.v.y(), frame.v.z(), frame.n.x(), frame.n.y(), frame.n.z()};
        kernels->to_local(nb.x.data(), nb.y.data(), nb.z.data(), m, f, nb.lx.data(), nb.ly.data(), nb.lz.data());
        PolyFit fit(opt.degree, h);
        double sums[21];
        kernels->poly_sums(nb.lx.data(), nb.ly.data(), nb.lz.data(), nb.w.data(), m, fit.inv_h(), sums);
        fit.AddSums(sums);
        PolyCoeffs g;
        if (!fit.Solve(&g)) return std::nullopt;
        if (stats) *stats = ComputeFitStats(nb, opt.degree, h, g);
        MlsPoint out;
        out.position = (x + q + g.c[0] * n).cast<float>();
        Vec3d normal = frame.NormalAt(g, 0.0, 0.0);
        // Orientation: agree with the cloud's normals where it has them.
        const bool flip = normal.dot(WeightedNormal(cloud, nb)) < 0;
        if (flip) normal = -normal;
        if (patch) {
            patch->origin = x + q;
            patch->u = frame.u;
            patch->v = frame.v;
            patch->n = frame.n;
            for (int k = 0; k < 6; ++k) patch->c[k] = g.c[k];
            patch->sign = flip ? -1.0 : 1.0;
        }
        out.normal = normal.cast<float>();
        out.iterations = it;
        out.neighbors = static_cast<int>(m);
        return out;
    }
};

void MlsOptions::Validate() const {
    CheckAtLeast("h", h, 0.0);
    CheckRange("degree", degree, kMinMlsDegree, kMaxMlsDegree);
    CheckRange("cutoff", cutoff, kMinMlsCutoff, kMaxMlsCutoff);
    CheckRange("max_iterations", max_iterations, kMinMlsIterations, kMaxMlsIterations);
    CheckRange("tolerance", tolerance, 0.0, kMaxMlsTolerance);
    CheckRange("min_neighbors", min_neighbors, kMinMlsNeighbors, kMaxMlsNeighbors);
    if (scale_rule != MlsScaleRule::kSpacing && scale_rule != MlsScaleRule::kNoise)
        InvalidField("scale_rule", "unknown rule " + std::to_string(static_cast<int>(scale_rule)));
}

namespace {

// The spacing rule's scale: 2 x the median spacing (adaptive: of `density`, the multiplier of
// eta / median eta). Throws when the points give none.
float SpacingRuleScale(const MlsOptions& o, const SamplingDensity& density, const KdTree& tree) {
    const float h = o.adaptive ? DefaultScale(density) : 2.0f * MedianSpacing(tree);
    if (!(h > 0)) throw Error(ErrorCode::kInvalidArgument, "cannot derive an MLS scale from fewer than 2 distinct points");
    return h;
}

}  // namespace

// The noise rule (see the header): per sample point, ICI over the scales h0 sqrt(2)^k; h the
// median of the chosen scales.
MlsScaleChoice ChooseMlsScale(const PointCloud& cloud, const KdTree& tree, const MlsOptions& options) {
    MlsOptions o = options;
    o.h = 0.0f;
    o.scale_rule = MlsScaleRule::kSpacing;
    // h0 as the spacing rule derives it; no grid (the candidates change h: radius queries on the
    // kd-tree).
    SURFEL_CHECK(tree.size() == cloud.size(), "tree over " << tree.size() << " points, cloud " << cloud.size());
    o.Validate();
    MlsSurface::Impl impl(cloud, tree, o);
    if (o.adaptive) impl.density = ComputeSamplingDensity(tree);
    impl.opt.h = SpacingRuleScale(o, impl.density, tree);
    MlsScaleChoice choice;
    choice.h0 = impl.opt.h;
    const std::size_t n = cloud.size(), count = std::min(n, kMlsNoiseSamples);
    std::vector<double> chosen(count, -1.0), noise(count, -1.0);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, count, 8), [&](const tbb::blocked_range<std::size_t>& r) {
        std::vector<Neighbor> buf;
        MlsSurface::Impl local(impl.cloud, impl.tree, impl.opt);
        if (impl.opt.adaptive) local.density = impl.density;
        // The noise is measured with the quadratic, whatever the degree asked for: the
        // residuals of a plane or a constant on a curved surface are its bias, not noise.
        MlsSurface::Impl quadratic(impl.cloud, impl.tree, impl.opt);
        quadratic.opt.degree = 2;
        if (impl.opt.adaptive) quadratic.density = impl.density;
        for (std::size_t s = r.begin(); s != r.end(); ++s) {
            const Vec3f& p = cloud.positions[s * n / count];
            double lo = -INFINITY, hi = INFINITY, sigma = 0.0;
            Vec3d n0 = Vec3d::Zero();
            for (int k = 0; k < kMlsNoiseScales; ++k) {
                local.opt.h = static_cast<float>(choice.h0 * std::pow(std::sqrt(2.0), k));
                FitStats st;
                const std::optional<MlsPoint> q = local.Project(p, buf, &st);
                if (!q || !st.valid) break;
                if (k == 0) {
                    FitStats st2 = st;
                    if (impl.opt.degree != 2 && !(quadratic.Project(p, buf, &st2) && st2.valid)) break;
                    sigma = std::sqrt(st2.residual2 / st2.dof);
                    n0 = q->normal.cast<double>();
                    noise[s] = sigma;
                }
                const double y = (q->position - p).cast<double>().dot(n0);
                const double sd = sigma * std::sqrt(std::max(0.0, st.variance));
                lo = std::max(lo, y - kMlsNoiseGamma * sd);
                hi = std::min(hi, y + kMlsNoiseGamma * sd);
                if (lo > hi) break;
                chosen[s] = local.opt.h;
            }
        }
    });
    std::vector<double> hs, sigmas;
    for (std::size_t s = 0; s < count; ++s) {
        if (chosen[s] > 0) hs.push_back(chosen[s]);
        if (noise[s] >= 0) sigmas.push_back(noise[s]);
    }
    choice.samples = hs.size();
    choice.h = choice.h0;
    if (!hs.empty()) {
        std::nth_element(hs.begin(), hs.begin() + static_cast<std::ptrdiff_t>(hs.size() / 2), hs.end());
        choice.h = static_cast<float>(hs[hs.size() / 2]);
    }
    if (!sigmas.empty()) {
        std::nth_element(sigmas.begin(), sigmas.begin() + static_cast<std::ptrdiff_t>(sigmas.size() / 2), sigmas.end());
        choice.noise = sigmas[sigmas.size() / 2];
    }
    choice.scale_factor = choice.h / choice.h0;
    return choice;
}

MlsSurface::MlsSurface(const PointCloud& cloud, const KdTree& tree, const MlsOptions& options)
    : impl_(std::make_unique<Impl>(cloud, tree, options)) {
    SURFEL_CHECK(tree.size() == cloud.size(), "tree over " << tree.size() << " points, cloud " << cloud.size());
    options.Validate();
    if (options.adaptive) impl_->density = ComputeSamplingDensity(tree);
    if (impl_->opt.h == 0 && options.scale_rule == MlsScaleRule::kNoise) {
        impl_->choice = ChooseMlsScale(cloud, tree, options);
        impl_->opt.h = impl_->choice->h;
    }
    if (impl_->opt.h == 0) impl_->opt.h = SpacingRuleScale(options, impl_->density, tree);
    // A fixed scale: one uniform grid answers every neighbour query (faster than the kd-tree's
    // radius search for this fixed radius). Skipped when the grid would be absurdly fine.
    if (!options.adaptive) {
        const BoundingBox box = cloud.Bounds();
        const float cell = impl_->opt.cutoff * impl_->opt.h;
        if (!box.empty() && (box.Extent() / cell).maxCoeff() < float(1 << 20)) {
            impl_->grid = std::make_unique<UniformGrid>(cloud.positions, cell);
            impl_->box = box;
        }
    }
}

MlsSurface::~MlsSurface() = default;

float MlsSurface::h() const { return impl_->opt.h; }

const std::optional<MlsScaleChoice>& MlsSurface::scale_choice() const { return impl_->choice; }

std::optional<MlsPoint> MlsSurface::Project(const Vec3f& x) const {
    std::vector<Neighbor> buf;
    return impl_->Project(x, buf);
}

std::optional<MlsPatch> MlsSurface::Fit(const Vec3f& x) const {
    std::vector<Neighbor> buf;
    MlsPatch patch;
    if (!impl_->Project(x, buf, nullptr, &patch)) return std::nullopt;
    return patch;
}

MlsPoint MlsPatch::Project(const Vec3f& y) const {
    const Vec3d d = y.cast<double>() - origin;
    const double a = d.dot(u), b = d.dot(v);
    PolyCoeffs g;
    for (int k = 0; k < 6; ++k) g.c[k] = c[k];
    MlsPoint out;
    out.position = (origin + a * u + b * v + g(a, b) * n).cast<float>();
    out.normal = (sign * (n - g.Dx(a, b) * u - g.Dy(a, b) * v).normalized()).cast<float>();
    return out;
}

MlsSurface::Batch MlsSurface::ProjectAll(std::span<const Vec3f> points, const ProgressFn& progress) const {
    Batch b;
    const std::size_t n = points.size();
    b.positions.resize(n);
    b.normals.resize(n);
    std::vector<std::uint8_t> ok(n, 0);
    std::vector<std::uint16_t> iters(n, 0);
    ProgressTracker tracker(progress, static_cast<double>(n), "MLS projection");
    const auto store = [&](std::size_t i, const std::optional<MlsPoint>& p) {
        if (p) {
            b.positions[i] = p->position;
            b.normals[i] = p->normal;
            ok[i] = 1;
            iters[i] = static_cast<std::uint16_t>(p->iterations);
        } else {
            b.positions[i] = points[i];
            b.normals[i] = Vec3f::Zero();
        }
    };
    const UniformGrid* grid = impl_->grid.get();
    if (grid && grid->dense() && points.data() == impl_->cloud.positions.data() && n == impl_->cloud.size()) {
        // The cloud's own points (`surfel project`, resampling's final pass): visited in the
        // grid's cell order, each thread's gathers in a cell filtered from one block of the
        // 3 x 3 x 3 cells around it (no visiting order to sort, one fill per cell).
        const Vec3f* sorted = grid->sorted_points();
        const std::uint32_t* sorted_index = grid->sorted_indices();
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const tbb::blocked_range<std::size_t>& r) {
            std::vector<Neighbor> buf;
            for (std::size_t k = r.begin(); k != r.end(); ++k) {
                int at[3];
                grid->DenseCellOf(sorted[k], at);
                const std::size_t i = sorted_index[k];
                store(i, impl_->Project(points[i], buf, nullptr, nullptr, /*superset=*/true, at));
            }
            tracker.Advance(static_cast<double>(r.size()));
        });
    } else {
        const std::vector<std::uint32_t> order = impl_->VisitOrder(points);
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const tbb::blocked_range<std::size_t>& r) {
            std::vector<Neighbor> buf;
            for (std::size_t k = r.begin(); k != r.end(); ++k) {
                const std::size_t i = order[k];
                store(i, impl_->Project(points[i], buf, nullptr, nullptr, /*superset=*/true));
            }
            tracker.Advance(static_cast<double>(r.size()));
        });
    }
    double it_sum = 0;
    for (std::size_t i = 0; i < n; ++i) {
        if (!ok[i]) ++b.failed;
        it_sum += iters[i];
    }
    b.mean_iterations = n ? it_sum / static_cast<double>(n) : 0.0;
    return b;
}

}  // namespace surfel
