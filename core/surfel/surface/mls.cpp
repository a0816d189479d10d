#include "surfel/surface/mls.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <cmath>

#include "surfel/base/error.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/poly_fit.h"

namespace surfel {

struct MlsSurface::Impl {
    const PointCloud& cloud;
    const KdTree& tree;
    MlsOptions opt;
    SamplingDensity density;  // only for adaptive h

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

    std::optional<MlsPoint> Project(const Vec3f& xf, std::vector<Neighbor>& nbrs) const {
        const float h = LocalH(xf, nbrs);
        const double inv_h2 = 1.0 / (double(h) * h);
        tree.Radius(xf, opt.cutoff * h, &nbrs);
        if (static_cast<int>(nbrs.size()) < opt.min_neighbors) return std::nullopt;
        const auto pts = tree.points();
        const Vec3d x = xf.cast<double>();
        Vec3d q = x, n = Vec3d::Zero();
        int it = 0;
        for (; it < opt.max_iterations; ++it) {
            double ws = 0;
            Vec3d c = Vec3d::Zero();
            for (const auto& nb : nbrs) {
                const Vec3d p = pts[nb.index].cast<double>();
                const double w = std::exp(-(p - q).squaredNorm() * inv_h2);
                ws += w;
                c += w * p;
            }
            if (!(ws > 1e-12)) return std::nullopt;
            c /= ws;
            Eigen::Matrix3d C = Eigen::Matrix3d::Zero();
            for (const auto& nb : nbrs) {
                const Vec3d p = pts[nb.index].cast<double>();
                const double w = std::exp(-(p - q).squaredNorm() * inv_h2);
                const Vec3d d = p - c;
                C.noalias() += w * d * d.transpose();
            }
            Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
            es.computeDirect(C);
            Vec3d nn = es.eigenvectors().col(0).normalized();
            if (it > 0 && nn.dot(n) < 0) nn = -nn;
            n = nn;
            const Vec3d q_new = x - (x - c).dot(n) * n;
            const double moved = (q_new - q).norm();
            q = q_new;
            if (moved < opt.tolerance * h) {
                ++it;
                break;
            }
        }
        // Polynomial over the plane, weights centred at q.
        const LocalFrame frame = LocalFrame::FromNormal(q, n);
        PolyFit fit(opt.degree, h);
        for (const auto& nb : nbrs) {
            const Vec3d p = pts[nb.index].cast<double>();
            const double w = std::exp(-(p - q).squaredNorm() * inv_h2);
            const Vec3d l = frame.ToLocal(p);
            fit.Add(l.x(), l.y(), l.z(), w);
        }
        PolyCoeffs g;
        if (!fit.Solve(&g)) return std::nullopt;
        MlsPoint out;
        out.position = (q + g.c[0] * n).cast<float>();
        Vec3d normal = frame.NormalAt(g, 0.0, 0.0);
        // Orientation: agree with the cloud's normals where it has them.
        if (cloud.has_normals()) {
            Vec3d avg = Vec3d::Zero();
            for (const auto& nb : nbrs) {
                const double w = std::exp(-(pts[nb.index].cast<double>() - q).squaredNorm() * inv_h2);
                avg += w * cloud.normals[nb.index].cast<double>();
            }
            if (normal.dot(avg) < 0) normal = -normal;
        }
        out.normal = normal.cast<float>();
        out.iterations = it;
        out.neighbors = static_cast<int>(nbrs.size());
        return out;
    }
};

MlsSurface::MlsSurface(const PointCloud& cloud, const KdTree& tree, const MlsOptions& options)
    : impl_(std::make_unique<Impl>(cloud, tree, options)) {
    SURFEL_CHECK(tree.size() == cloud.size(), "tree over " << tree.size() << " points, cloud " << cloud.size());
    if (options.degree < 0 || options.degree > 2)
        throw Error(ErrorCode::kInvalidArgument, "MLS polynomial degree must be 0, 1 or 2, got " + std::to_string(options.degree));
    if (options.h < 0 || !std::isfinite(options.h))
        throw Error(ErrorCode::kInvalidArgument, "MLS scale h must be > 0 (or 0 for the default), got " + std::to_string(options.h));
    if (!(options.cutoff >= 1.0f)) throw Error(ErrorCode::kInvalidArgument, "MLS cutoff must be >= 1 (in units of h)");
    if (options.adaptive || options.h == 0) impl_->density = ComputeSamplingDensity(tree);
    if (impl_->opt.h == 0) impl_->opt.h = DefaultScale(impl_->density);
    if (!(impl_->opt.h > 0)) throw Error(ErrorCode::kInvalidArgument, "cannot derive an MLS scale from fewer than 2 distinct points");
}

MlsSurface::~MlsSurface() = default;

float MlsSurface::h() const { return impl_->opt.h; }

std::optional<MlsPoint> MlsSurface::Project(const Vec3f& x) const {
    std::vector<Neighbor> buf;
    return impl_->Project(x, buf);
}

MlsSurface::Batch MlsSurface::ProjectAll(std::span<const Vec3f> points, const ProgressFn& progress) const {
    Batch b;
    const std::size_t n = points.size();
    b.positions.resize(n);
    b.normals.resize(n);
    std::vector<std::uint8_t> ok(n, 0);
    std::vector<std::uint16_t> iters(n, 0);
    ProgressTracker tracker(progress, static_cast<double>(n), "MLS projection");
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const tbb::blocked_range<std::size_t>& r) {
        std::vector<Neighbor> buf;
        for (std::size_t i = r.begin(); i != r.end(); ++i) {
            auto p = impl_->Project(points[i], buf);
            if (p) {
                b.positions[i] = p->position;
                b.normals[i] = p->normal;
                ok[i] = 1;
                iters[i] = static_cast<std::uint16_t>(p->iterations);
            } else {
                b.positions[i] = points[i];
                b.normals[i] = Vec3f::Zero();
            }
        }
        tracker.Advance(static_cast<double>(r.size()));
    });
    double it_sum = 0;
    for (std::size_t i = 0; i < n; ++i) {
        if (!ok[i]) ++b.failed;
        it_sum += iters[i];
    }
    b.mean_iterations = n ? it_sum / static_cast<double>(n) : 0.0;
    return b;
}

}  // namespace surfel
