#include "surfel/surface/aa_surface.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <bit>
#include <future>
#include <mutex>
#include <cmath>
#include <vector>
#include <string>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/spatial/uniform_grid.h"
#include "surfel/surface/fit_kernels.h"
#include "surfel/surface/local_analysis.h"

namespace surfel {

// Support plane and polynomial at one location (steps 1 and 2 of section 4).
struct AaSurface::Fit {
    LocalFrame frame;                     // origin r, normal n of the support plane
    PolyCoeffs g;                         // a_i(x, y) over the plane
    Vec3d normal_ref = Vec3d::Zero();     // weighted average of the cloud's normals (if any)
    Vec3d mean = Vec3d::Zero();           // the weighted average a(r) of the fit's points, eq. 1
    std::array<float, 4> color{0, 0, 0, 1};
    bool valid = false;
};

// A cached ball-centre fit: the plane's normal and first tangent and the polynomial, in single
// precision (48 bytes a ball instead of a whole Fit's 192: the cache has an entry per point, and
// it only seeds the iteration). The frame's origin is the ball centre; the second tangent is
// n x u. (The tangent is stored, not re-derived from the rounded normal, which could pick the
// other helper axis in LocalFrame::FromNormal and turn the polynomial's axes.)
struct CenterEntry {
    float n[3];
    float u[3];
    float c[6];
};

class ScaleMaxima;

struct AaSurface::Impl {
    const PointCloud& cloud;
    AaOptions opt;
    std::vector<float> ball_radius;
    // AaBandwidth::kAdaptive (empty when fixed): h_j and 1 / h_j^2.
    std::vector<float> scale, inv_h2;
    // AaBandwidth::kAdaptive: the gather scale of ball i, the largest h_j of the points near it (a
    // fit in ball i gathers within cutoff x that; 0 = not computed yet), filled on first need
    // (only the balls a ray tries need it: about half of them at the paper's framing), from
    // scale_maxima.
    std::unique_ptr<std::atomic<float>[]> reach;
    std::unique_ptr<ScaleMaxima> scale_maxima;
    // AaOptions::boundary (empty when boundary = 0): each point's sample spacing eta_j (notes
    // 1.1.1, the ball_k-th neighbour) over the median spacing, for the local scale of a hit.
    std::vector<float> relative_spacing;
    // The local scale of ball i's boundary test (0 = not computed yet), filled on first need.
    std::unique_ptr<std::atomic<float>[]> boundary_scale;
    // The boundary test's scales in units of max(h, kBoundarySpacings x the median spacing) / h.
    float boundary_unit = 1.0f;
    float max_scale = 0.0f;
    std::vector<Vec3f> weight_normals;  // normal-aware weights (normal_sigma > 0)
    std::unique_ptr<UniformGrid> grid;
    // The grid's cell-sorted points as structure of arrays (dense grids: the superset's fill).
    std::vector<float> sorted_x, sorted_y, sorted_z;
    // The weight normals in the same order, x/y/z arrays (dense grid, normal-aware weights): they
    // travel with the points through the superset and the gathers.
    std::vector<float> sorted_nx, sorted_ny, sorted_nz;
    std::vector<CenterEntry> centers;
    // 0 empty, 1 being computed, 2 ready, 3 ready but undefined (no fit at that centre).
    std::unique_ptr<std::atomic<std::uint8_t>[]> center_state;
    std::uint64_t id = 0;  // this surface's key in the per-thread neighbour superset
    const fit_kernels::Kernels* kernels = &fit_kernels::Best();  // the fits' weighted sums
    // Normal-aware weights on a cloud without normals: the estimation runs on its own thread from
    // the constructor on (beside the rest of the setup and the caller's BVH build); the first
    // evaluation waits for it and sorts the normals into grid order (AwaitNormals).
    std::once_flag normals_once;
    std::atomic<bool> normals_ready{false};
    // Last, so that it is destroyed first: releasing it waits for the estimation, which writes
    // weight_normals.
    std::shared_future<void> normals_job;
    Impl(const PointCloud& c, const AaOptions& o) : cloud(c), opt(o) {}
};

namespace {
thread_local NeighborBatch tls_batch;

// A point rounded to float (the gathers' origin), and that float point widened back to double.
// The rounding goes through memory the compiler cannot see into: GCC 12 (Debian 12's, from -O2)
// may fold a vectorised (double)(float)x back to x (see CenterFit), and whether it does depended
// on how much of the gather was inlined into FitAt, which moved 40 % of an image's pixels by up
// to 2e-5 when the gather's loops moved into fit_kernels.
Vec3f RoundToFloat(const Vec3d& r) {
    volatile float v[3] = {static_cast<float>(r.x()), static_cast<float>(r.y()), static_cast<float>(r.z())};
    return Vec3f(float(v[0]), float(v[1]), float(v[2]));
}
Vec3d Widen(const Vec3f& f) {
    volatile float v[3] = {f.x(), f.y(), f.z()};
    return Vec3d(double(v[0]), double(v[1]), double(v[2]));
}

// Ids of AaSurface objects (an address can be reused by a later surface; an id is not).
std::atomic<std::uint64_t> next_surface_id{1};

// Real roots of A t^2 + B t + C = 0 (numerically stable); returns the count.
int SolveQuadratic(double A, double B, double C, double* r0, double* r1) {
    const double scale = std::max({std::abs(A), std::abs(B), std::abs(C)});
    if (scale == 0) return 0;
    if (std::abs(A) <= 1e-12 * scale) {
        if (std::abs(B) <= 1e-300) return 0;
        *r0 = -C / B;
        return 1;
    }
    const double disc = B * B - 4 * A * C;
    if (disc < 0) return 0;
    const double s = std::sqrt(disc);
    const double q = -0.5 * (B + (B >= 0 ? s : -s));
    *r0 = q / A;
    *r1 = q != 0 ? C / q : *r0;
    if (*r0 > *r1) std::swap(*r0, *r1);
    return 2;
}

// Ray o + t d against the graph z = g(x, y) of a frame: the quadratic in t.
int IntersectPoly(const LocalFrame& f, const PolyCoeffs& g, const Vec3d& o, const Vec3d& d, double* t0, double* t1) {
    const Vec3d ol = f.ToLocal(o), dl = f.DirToLocal(d);
    const double ox = ol.x(), oy = ol.y(), oz = ol.z(), dx = dl.x(), dy = dl.y(), dz = dl.z();
    const double* c = g.c;
    const double A = c[3] * dx * dx + c[4] * dx * dy + c[5] * dy * dy;
    const double B = c[1] * dx + c[2] * dy + 2 * c[3] * ox * dx + c[4] * (ox * dy + oy * dx) + 2 * c[5] * oy * dy - dz;
    const double C = c[0] + c[1] * ox + c[2] * oy + c[3] * ox * ox + c[4] * ox * oy + c[5] * oy * oy - oz;
    return SolveQuadratic(A, B, C, t0, t1);
}
}  // namespace

void AaOptions::Validate() const {
    CheckAtLeast("h", h, 0.0);
    CheckAtLeast("precision", precision, 0.0);
    CheckRange("degree", degree, 0, 2);
    CheckRange("relative_precision", relative_precision, 0, 1);
    if (!(relative_precision > 0)) InvalidField("relative_precision", "must be > 0, got 0");
    CheckRange("max_iterations", max_iterations, 1, kMaxSurfaceIterations);
    CheckAtLeast("cutoff", cutoff, 1.0);
    CheckRange("normal_ratio", normal_ratio, 0, 1);
    CheckRange("ball_k", ball_k, 1, kMaxBallNeighbors);
    if (bandwidth != AaBandwidth::kFixed && bandwidth != AaBandwidth::kAdaptive)
        InvalidField("bandwidth", "unknown kind " + std::to_string(static_cast<int>(bandwidth)));
    CheckRange("ball_h", ball_h, 0, 10);
    CheckRange("normal_sigma", normal_sigma, 0, 10);
    CheckRange("boundary", boundary, 0, 10);
}

namespace {
// The cell-sorted points as x/y/z arrays (dense grids: the gathers' and the scales' candidates).
struct SortedXyz {
    const float* x;
    const float* y;
    const float* z;
};

// AaBandwidth::kAdaptive: the per-point scales h_j = h * s_j, s_j the spacing over its median
// (clamped to [1/kAdaptiveRange, kAdaptiveRange]) smoothed twice by a Gaussian average at the
// point's own scale (within 2 h_j, weights exp(-d^2 / h_j^2)): the notes (1.3) warn that the
// adaptation must itself be smooth, or the surface is not a manifold where the density jumps.
// Per point, so the result does not depend on the thread count.
// On a dense grid the candidates of each column run are filtered by the kernels' GatherWithin
// (the float distance test of ForEachWithin, x^2 + (y^2 + z^2), the same points in the same
// order), so the sums are ForEachWithin's term for term; a sparse grid walks ForEachWithin.
void AdaptiveScales(const UniformGrid& grid, std::span<const Vec3f> pts, const SortedXyz& sorted,
                    const fit_kernels::Kernels& kernels, const SamplingDensity& density, float h,
                    std::vector<float>* scale) {
    const std::size_t n = pts.size();
    const float med = density.median_spacing > 0 ? density.median_spacing : 1.0f;
    std::vector<float> s(n), t(n);
    for (std::size_t i = 0; i < n; ++i)
        s[i] = std::clamp(density.spacing[i] / med, 1.0f / kAdaptiveRange, kAdaptiveRange);
    scale->resize(n);
    if (!grid.dense()) {
        for (int pass = 0; pass < 2; ++pass) {
            tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const tbb::blocked_range<std::size_t>& r) {
                for (std::size_t i = r.begin(); i != r.end(); ++i) {
                    const float hi = h * s[i], inv = 1.0f / (hi * hi);
                    double sw = 0, ss = 0;
                    grid.ForEachWithin(pts[i], std::min(2.0f * hi, grid.cell()), [&](std::uint32_t j, const Vec3f&, float d2) {
                        const double w = std::exp(-double(d2) * inv);
                        sw += w;
                        ss += w * s[j];
                    });
                    t[i] = sw > 0 ? static_cast<float>(ss / sw) : s[i];
                }
            });
            s.swap(t);
        }
        for (std::size_t i = 0; i < n; ++i) (*scale)[i] = h * s[i];
        return;
    }
    // Dense grid: the points and their s in cell order (s[k] is point order[k]'s), the neighbours
    // named by their place in that order (`place`), for locality; the same values, the same sums.
    const std::uint32_t* order = grid.sorted_indices();
    const Vec3f* sp = grid.sorted_points();
    std::vector<std::uint32_t> place(n);
    for (std::size_t k = 0; k < n; ++k) place[k] = static_cast<std::uint32_t>(k), t[k] = s[order[k]];
    s.swap(t);
    for (int pass = 0; pass < 2; ++pass) {
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const tbb::blocked_range<std::size_t>& r) {
            std::vector<float> ox, oy, oz, od2;
            std::vector<std::uint32_t> oi;
            std::vector<double> ow;
            for (std::size_t k = r.begin(); k != r.end(); ++k) {
                const float hi = h * s[k], inv = 1.0f / (hi * hi);
                const float radius = std::min(2.0f * hi, grid.cell()), r2 = radius * radius;
                const Vec3f& q = sp[k];
                // Every candidate run's neighbours first, then their weights w = exp(-d^2 inv) as
                // std::exp gives them, four at a time (fit_kernels.h), then the sums in the same order.
                std::size_t c = 0;
                grid.ForEachCandidateRun(q, radius, [&](std::uint32_t first, std::uint32_t last) {
                    const std::size_t m = last - first;
                    if (od2.size() < c + m + 8) {
                        for (auto* v : {&ox, &oy, &oz, &od2}) v->resize(std::max<std::size_t>(1024, 2 * (c + m + 8)));
                        oi.resize(od2.size());
                    }
                    c += kernels.gather_within(sorted.x + first, sorted.y + first, sorted.z + first, place.data() + first,
                                               nullptr, m, q.x(), q.y(), q.z(), r2, ox.data() + c, oy.data() + c,
                                               oz.data() + c, od2.data() + c, oi.data() + c, nullptr);
                });
                if (ow.size() < c) ow.resize(od2.size());
                kernels.gauss_weights_d(od2.data(), inv, ow.data(), c);
                double sw = 0, ss = 0;
                for (std::size_t j = 0; j < c; ++j) {
                    sw += ow[j];
                    ss += ow[j] * s[oi[j]];
                }
                t[k] = sw > 0 ? static_cast<float>(ss / sw) : s[k];
            }
        });
        s.swap(t);
    }
    for (std::size_t k = 0; k < n; ++k) (*scale)[order[k]] = h * s[k];
}

}  // namespace

// The gather scale of a ball (AaSurface::Impl::reach): the largest h_j within
// radius(i) = cutoff x h_i + max(rho_i, ball_h x h_i) of p_i (ForEachWithin's float distance
// test), at least h_i. A maximum does not depend on the order of its terms, so on a dense grid
// only the points with a scale above the floor h_i are read: a candidate run, or a block of 16
// cell-sorted points, whose largest scale is <= the maximum so far is skipped (the largest scale
// of each block, and a sparse table over the blocks for a run's). A sparse grid walks
// ForEachWithin (within its cell).
class ScaleMaxima {
public:
    ScaleMaxima(const UniformGrid& grid, const std::vector<float>& scale) : grid_(grid), scale_(scale) {
        if (!grid.dense()) return;
        const std::size_t n = scale.size();
        const std::uint32_t* order = grid.sorted_indices();
        const std::size_t blocks = (n + kBlock - 1) / kBlock;
        sorted_scale_.resize(n);
        table_.assign(1, std::vector<float>(blocks, 0.0f));
        for (std::size_t k = 0; k < n; ++k) {
            sorted_scale_[k] = scale[order[k]];
            table_[0][k / kBlock] = std::max(table_[0][k / kBlock], sorted_scale_[k]);
        }
        // Level l: the largest of 2^l blocks from b.
        for (std::size_t span = 2; span <= blocks; span *= 2) {
            const std::vector<float>& below = table_.back();
            std::vector<float> level(blocks - span + 1);
            for (std::size_t b = 0; b < level.size(); ++b) level[b] = std::max(below[b], below[b + span / 2]);
            table_.push_back(std::move(level));
        }
    }

    /// The largest scale above `floor` within `rad` of q, or `floor` when there is none.
    float MaxAbove(const Vec3f& q, float rad, float floor) const {
        float m = floor;
        if (!grid_.dense()) {
            grid_.ForEachWithin(q, std::min(rad, grid_.cell()),
                                [&](std::uint32_t j, const Vec3f&, float) { m = std::max(m, scale_[j]); });
            return m;
        }
        const float r2 = rad * rad;
        const Vec3f* sp = grid_.sorted_points();
        const std::vector<float>& block_max = table_[0];
        grid_.ForEachCandidateRun(q, rad, [&](std::uint32_t first, std::uint32_t last) {
            if (BlocksMax(first / kBlock, (last - 1) / kBlock) <= m) return;
            for (std::size_t k = first; k < last;) {
                const std::size_t end = std::min<std::size_t>(last, (k / kBlock + 1) * kBlock);
                if (block_max[k / kBlock] > m)
                    for (std::size_t j = k; j < end; ++j)
                        if (sorted_scale_[j] > m && (sp[j] - q).squaredNorm() <= r2) m = sorted_scale_[j];
                k = end;
            }
        });
        return m;
    }

private:
    static constexpr std::size_t kBlock = 16;
    // The largest scale in blocks b0..b1 (inclusive).
    float BlocksMax(std::size_t b0, std::size_t b1) const {
        const int l = std::bit_width(b1 - b0 + 1) - 1;
        return std::max(table_[l][b0], table_[l][b1 + 1 - (std::size_t(1) << l)]);
    }
    const UniformGrid& grid_;
    const std::vector<float>& scale_;
    std::vector<float> sorted_scale_;
    std::vector<std::vector<float>> table_;
};

namespace {
// The gather scale of ball i (see ScaleMaxima), computed on first need and cached (the same value
// whichever thread computes it). (A template so that it can take the surface's private Impl.)
template <typename Impl>
float BallReach(const Impl& im, std::size_t i) {
    std::atomic<float>& cached = im.reach[i];
    const float c = cached.load(std::memory_order_relaxed);
    if (c > 0) return c;
    const float hi = im.scale[i];
    const float rad = im.opt.cutoff * hi + std::max(im.ball_radius[i], im.opt.ball_h * hi);
    const float v = im.scale_maxima->MaxAbove(im.cloud.positions[i], rad, hi);
    cached.store(v, std::memory_order_relaxed);
    return v;
}
}  // namespace

AaSurface::AaSurface(const PointCloud& cloud, const AaOptions& options, const ProgressFn& progress)
    : impl_(std::make_unique<Impl>(cloud, options)) {
    AaOptions& o = impl_->opt;
    if (cloud.size() < 3) throw Error(ErrorCode::kInvalidArgument, "the surface needs at least 3 points, got " + std::to_string(cloud.size()));
    o.Validate();
    // The normals of the normal-aware weights: the cloud's, else estimated (the longest part of
    // the setup, with serial stretches: the kd-tree build, the orientation's spanning tree) on
    // another thread while this one sets up the rest (sampling density, grid, scales) and the
    // caller builds its BVH; the first evaluation waits for them (AwaitNormals). Each part writes
    // its own members and neither depends on the thread count.
    if (o.normal_sigma > 0) {
        if (cloud.has_normals()) {
            impl_->weight_normals = cloud.normals;
        } else {
            Impl* im = impl_.get();
            impl_->normals_job = std::async(std::launch::async, [im, progress] {
                const KdTree tree(im->cloud.positions);
                // Only the caller's cancellation: its fractions are the caller's whole job's.
                const ProgressFn poll = [&progress](double) { return !progress || progress(0.0); };
                im->weight_normals = EstimateNormals(tree, {}, poll).normals;
            }).share();
        }
    }
    SetUpScales();
    if (!impl_->normals_job.valid()) AwaitNormals();
}

void AaSurface::AwaitNormals() const {
    if (impl_->normals_ready.load(std::memory_order_acquire)) return;
    // (An exception of the estimation, e.g. Error(kCancelled), leaves the flag unset: every later
    // call rethrows it from the shared future.)
    std::call_once(impl_->normals_once, [this] {
        Impl& im = *impl_;
        if (im.normals_job.valid()) im.normals_job.get();
        if (im.grid->dense() && !im.weight_normals.empty()) {
            const std::size_t n = im.cloud.size();
            const std::uint32_t* order = im.grid->sorted_indices();
            for (auto* v : {&im.sorted_nx, &im.sorted_ny, &im.sorted_nz}) v->resize(n);
            for (std::size_t i = 0; i < n; ++i) {
                const Vec3f& nrm = im.weight_normals[order[i]];
                im.sorted_nx[i] = nrm.x(), im.sorted_ny[i] = nrm.y(), im.sorted_nz[i] = nrm.z();
            }
        }
        im.normals_ready.store(true, std::memory_order_release);
    });
}

void AaSurface::SetUpScales() {
    const PointCloud& cloud = impl_->cloud;
    AaOptions& o = impl_->opt;
    const SamplingDensity density = ComputeSamplingDensity(cloud.positions, o.ball_k);
    impl_->ball_radius = density.radius;
    // DefaultScale is 2 median spacings; half of kSurfaceScaleSpacings of it (0.7f exactly).
    if (o.h == 0) o.h = (0.5f * kSurfaceScaleSpacings) * DefaultScale(density);
    if (!(o.h > 0)) throw Error(ErrorCode::kInvalidArgument, "cannot derive h from the cloud (all points coincide); pass h");
    if (o.precision == 0) o.precision = o.relative_precision * o.h;
    // The grid's cell-sorted points as x/y/z arrays (dense grids: the gathers and the adaptive
    // scales read them), once.
    const auto fill_sorted_xyz = [this] {
        if (!impl_->grid->dense() || !impl_->sorted_x.empty()) return;
        const std::size_t n = impl_->cloud.size();
        const Vec3f* p = impl_->grid->sorted_points();
        for (auto* v : {&impl_->sorted_x, &impl_->sorted_y, &impl_->sorted_z}) v->resize(n);
        for (std::size_t i = 0; i < n; ++i)
            impl_->sorted_x[i] = p[i].x(), impl_->sorted_y[i] = p[i].y(), impl_->sorted_z[i] = p[i].z();
    };
    if (o.bandwidth == AaBandwidth::kFixed) {
        impl_->grid = std::make_unique<UniformGrid>(cloud.positions, o.cutoff * o.h);
    } else {
        // The dense grid answers any radius; the sparse one only up to its cell, which must then
        // reach the largest scale's cutoff.
        float cell = o.cutoff * o.h;
        if (!UniformGrid::FitsDense(cloud.Bounds(), cloud.size(), cell)) cell *= kAdaptiveRange;
        impl_->grid = std::make_unique<UniformGrid>(cloud.positions, cell);
        fill_sorted_xyz();
        AdaptiveScales(*impl_->grid, cloud.positions,
                       {impl_->sorted_x.data(), impl_->sorted_y.data(), impl_->sorted_z.data()}, *impl_->kernels,
                       density, o.h, &impl_->scale);
        const std::size_t n = cloud.size();
        impl_->inv_h2.resize(n);
        for (std::size_t i = 0; i < n; ++i) impl_->inv_h2[i] = 1.0f / (impl_->scale[i] * impl_->scale[i]);
        impl_->max_scale = *std::max_element(impl_->scale.begin(), impl_->scale.end());
        // Gather scale of ball i: the largest h_j within cutoff x h_i + rho_i (+ the ball_h
        // widening) of its centre; a point farther out would need a scale that large to reach a
        // fit in the ball with a weight above exp(-cutoff^2). Computed per ball on first need.
        impl_->scale_maxima = std::make_unique<ScaleMaxima>(*impl_->grid, impl_->scale);
        impl_->reach.reset(new std::atomic<float>[n]);
        for (std::size_t i = 0; i < n; ++i) impl_->reach[i].store(0.0f, std::memory_order_relaxed);
    }
    fill_sorted_xyz();
    if (o.boundary > 0) {
        const float med = density.median_spacing > 0 ? density.median_spacing : 1.0f;
        impl_->boundary_unit = std::max(1.0f, kBoundarySpacings * density.median_spacing / o.h);
        impl_->relative_spacing.resize(cloud.size());
        for (std::size_t i = 0; i < cloud.size(); ++i) impl_->relative_spacing[i] = density.spacing[i] / med;
        impl_->boundary_scale.reset(new std::atomic<float>[cloud.size()]);
        for (std::size_t i = 0; i < cloud.size(); ++i) impl_->boundary_scale[i].store(0.0f, std::memory_order_relaxed);
    }
    if (o.ball_h > 0)
        for (std::size_t i = 0; i < cloud.size(); ++i)
            impl_->ball_radius[i] = std::max(impl_->ball_radius[i], o.ball_h * PointScale(static_cast<std::uint32_t>(i)));
    impl_->id = next_surface_id.fetch_add(1, std::memory_order_relaxed);
    impl_->centers.resize(cloud.size());
    impl_->center_state.reset(new std::atomic<std::uint8_t>[cloud.size()]);
    for (std::size_t i = 0; i < cloud.size(); ++i) impl_->center_state[i].store(0, std::memory_order_relaxed);
}

AaSurface::~AaSurface() {
    if (impl_->normals_job.valid()) impl_->normals_job.wait();
}

float AaSurface::h() const { return impl_->opt.h; }
float AaSurface::precision() const { return impl_->opt.precision; }
const AaOptions& AaSurface::options() const { return impl_->opt; }
const PointCloud& AaSurface::cloud() const { return impl_->cloud; }
float AaSurface::BallRadius(std::uint32_t i) const { return impl_->ball_radius[i]; }
float AaSurface::PointScale(std::uint32_t i) const { return impl_->scale.empty() ? impl_->opt.h : impl_->scale[i]; }

float AaSurface::BoundaryScale(std::uint32_t i) const {
    if (!impl_->boundary_scale) return PointScale(i);
    std::atomic<float>& cached = impl_->boundary_scale[i];
    const float c = cached.load(std::memory_order_relaxed);
    if (c > 0) return c;
    // h x sum theta_j eta_j / sum theta_j / median eta, theta_j = exp(-|p_j - p_i|^2 / h^2) within
    // 2 h (the same value whichever thread computes it).
    const float h = impl_->opt.h, inv = 1.0f / (h * h);
    const UniformGrid& g = *impl_->grid;
    double sw = 0, ss = 0;
    g.ForEachWithin(impl_->cloud.positions[i], std::min(2.0f * h, g.cell()), [&](std::uint32_t j, const Vec3f&, float d2) {
        const double w = std::exp(-double(d2) * inv);
        sw += w;
        ss += w * impl_->relative_spacing[j];
    });
    const float v = sw > 0 ? static_cast<float>(h * ss / sw) : h;
    cached.store(v, std::memory_order_relaxed);
    return v;
}
const std::vector<Vec3f>& AaSurface::WeightNormals() const {
    AwaitNormals();
    return impl_->weight_normals;
}

namespace {
// The points within `reach` of a centre c, in the grid's cell order, as structure of arrays: a
// per-thread superset of the neighbourhoods of the next gathers. The section-4 iterates of one
// ray lie a fraction of h apart, and so do the hits of neighbouring pixels of a tile; a gather
// within `radius` of o whose ball lies inside this one (|o - c| + radius <= reach) filters these
// points instead of walking the grid's columns (about 3 candidates an accepted neighbour there,
// against under 2 here). The dense grid visits its points in ascending cell order, so the
// filtered list is the one the grid walk gives, in the same order, with the same float test:
// the fits, and the image, are unchanged.
struct Superset {
    std::uint64_t owner = 0;  // AaSurface id the points belong to; 0 = empty
    Vec3f c = Vec3f::Zero();
    float reach = 0.0f;
    std::vector<float> x, y, z;
    std::vector<std::uint32_t> index;
    std::vector<float> nx, ny, nz;  // the points' weight normals (when the surface has them)
    std::size_t n = 0;
};
thread_local Superset tls_superset;

// The weight normals of the last gather's neighbours, in its order (normal-aware weights).
struct GatheredNormals {
    std::vector<float> x, y, z;
};
thread_local GatheredNormals tls_normals;

// The sorted points and, when the surface has weight normals, their normals (else null), as
// x/y/z arrays: what the superset is filled from.
struct SortedPoints {
    const float* p[3];
    const float* n[3];
    bool normals;
};

// How far (in units of h) the superset reaches beyond the gather that filled it.
constexpr float kSupersetMargin = 1.0f;

// Fills `s` with the points within `reach` of c, in ascending cell order (dense grid only), with
// their normals when `sorted` has them, eight candidates at a time (SelectWithin).
void FillSuperset(const UniformGrid& grid, const SortedPoints& sorted, const fit_kernels::Kernels& kernels,
                  std::uint64_t owner, const Vec3f& c, float reach, Superset& s) {
    s.owner = 0;
    s.n = 0;
    const float r2 = reach * reach;
    const std::uint32_t* idx = grid.sorted_indices();
    grid.ForEachCandidateRun(c, reach, [&](std::uint32_t first, std::uint32_t last) {
        const std::size_t need = s.n + (last - first) + 8;
        if (need > s.index.size()) {
            const std::size_t cap = std::max<std::size_t>(1024, 2 * need);
            for (auto* v : {&s.x, &s.y, &s.z, &s.nx, &s.ny, &s.nz}) v->resize(cap);
            s.index.resize(cap);
        }
        const float* const carry[3] = {sorted.n[0] + first, sorted.n[1] + first, sorted.n[2] + first};
        float* const carry_out[3] = {s.nx.data() + s.n, s.ny.data() + s.n, s.nz.data() + s.n};
        s.n += kernels.select_within(sorted.p[0] + first, sorted.p[1] + first, sorted.p[2] + first, idx + first,
                                     sorted.normals ? carry : nullptr, last - first, c.x(), c.y(), c.z(), r2,
                                     s.x.data() + s.n, s.y.data() + s.n, s.z.data() + s.n, s.index.data() + s.n,
                                     carry_out);
    });
    s.c = c;
    s.reach = reach;
    s.owner = owner;
}

// The neighbours within `radius` of o (a point in float, so that offsets are float
// differences), relative to o: the first step of both FitAt (eq. 8, 9) and Evaluate (eq. 1-4).
// From the thread's superset when it covers the ball (dense grids), else from the grid. `h`:
// how far beyond the gather a new superset reaches (kSupersetMargin x h).
// With `sorted.normals`, the neighbours' weight normals go to tls_normals (`normals`: all of them,
// for the grid walk's path).
void Gather(const UniformGrid& grid, const SortedPoints& sorted, const std::vector<Vec3f>& normals,
            std::uint64_t owner, const Vec3f& o, float radius, double h, NeighborBatch& nb,
            const fit_kernels::Kernels& kernels) {
    nb.clear();
    if (grid.dense()) {
        Superset& s = tls_superset;
        // Covered when |o - c| + radius <= reach, less a hair for the rounding of these floats.
        const auto covers = [&] { return s.owner == owner && (o - s.c).norm() + radius <= s.reach * (1.0f - 1e-4f); };
        if (!covers()) FillSuperset(grid, sorted, kernels, owner, o, radius + kSupersetMargin * static_cast<float>(h), s);
        // The candidates within `radius` of o, their float offsets and distances: d2 is Eigen's
        // squaredNorm of the float offset, x^2 + (y^2 + z^2), as PushWithin computes it, so the
        // test and the stored values are PushWithin's to the bit (fit_kernels.h's GatherWithin).
        const std::size_t m = s.n;
        nb.Reserve(m + 8);
        GatheredNormals& gn = tls_normals;
        if (sorted.normals && gn.x.size() < m + 8)
            for (auto* v : {&gn.x, &gn.y, &gn.z}) v->resize(std::max<std::size_t>(1024, 2 * (m + 8)));
        const float* const carry[3] = {s.nx.data(), s.ny.data(), s.nz.data()};
        float* const carry_out[3] = {gn.x.data(), gn.y.data(), gn.z.data()};
        const std::size_t n = kernels.gather_within(s.x.data(), s.y.data(), s.z.data(), s.index.data(),
                                                    sorted.normals ? carry : nullptr, m, o.x(), o.y(), o.z(),
                                                    radius * radius, nb.x.data(), nb.y.data(), nb.z.data(),
                                                    nb.d2.data(), nb.index.data(), carry_out);
        nb.Resize(n);
    } else {
        grid.ForEachCandidateRun(o, radius, [&](std::uint32_t first, std::uint32_t last) {
            nb.PushWithin(grid.sorted_points() + first, grid.sorted_indices() + first, last - first, o,
                          radius * radius);
        });
        if (!normals.empty()) {
            GatheredNormals& gn = tls_normals;
            const std::size_t n = nb.size();
            if (gn.x.size() < n)
                for (auto* v : {&gn.x, &gn.y, &gn.z}) v->resize(std::max<std::size_t>(1024, 2 * n));
            for (std::size_t k = 0; k < n; ++k) {
                const Vec3f& nrm = normals[nb.index[k]];
                gn.x[k] = nrm.x(), gn.y[k] = nrm.y(), gn.z[k] = nrm.z();
            }
        }
    }
}

// Gathers the neighbours of o and weighs them: theta(d) = exp(-d^2/h^2) with the one h, or
// theta_j with each point's h_j (adaptive), within cutoff x the scale; for a fit serving ball
// `ball` (-1: none) with normal-aware weights, times exp(-((1 - n_j . n_ball) / sigma)^2). Returns
// the weighted moments about o (zero weight when fewer than 3 points are near). (A template so
// that it can take the surface's private Impl.)
template <typename Impl>
WeightedMoments GatherWeighted(const Impl& im, const Vec3f& o, float cutoff, std::int64_t ball, NeighborBatch& nb) {
    const AaOptions& opt = im.opt;
    const float H = im.scale.empty() ? opt.h : ball >= 0 ? BallReach(im, std::size_t(ball)) : im.max_scale;
    const SortedPoints sorted{{im.sorted_x.data(), im.sorted_y.data(), im.sorted_z.data()},
                              {im.sorted_nx.data(), im.sorted_ny.data(), im.sorted_nz.data()},
                              !im.sorted_nx.empty()};
    Gather(*im.grid, sorted, im.weight_normals, im.id, o, cutoff * H, H, nb, *im.kernels);
    if (nb.size() < 3) return {};
    // nb.Weights(opt.h), through the kernels.
    if (im.scale.empty()) im.kernels->gauss_weights(nb.d2.data(), static_cast<float>(1.0 / (double(opt.h) * double(opt.h))), nb.w.data(), nb.size());
    else nb.WeightsPerPoint(im.inv_h2.data(), cutoff * cutoff, im.kernels->gauss_weights);
    if (ball >= 0 && !im.weight_normals.empty()) {
        // w_j *= exp(-c^2), c = (1 - n_j . n_ball) / sigma, through the kernels (fit_kernels.h).
        // The neighbours' normals came with them (tls_normals, filled by Gather).
        const Vec3f nr = im.weight_normals[std::size_t(ball)];
        const float ref[3] = {nr.x(), nr.y(), nr.z()};
        const GatheredNormals& gn = tls_normals;
        im.kernels->normal_factors(gn.x.data(), gn.y.data(), gn.z.data(), nb.size(), ref, 1.0f / opt.normal_sigma,
                                   nb.w.data());
    }
    double m[10];
    im.kernels->moments(nb.x.data(), nb.y.data(), nb.z.data(), nb.w.data(), nb.size(), m);
    return {m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8], m[9]};
}

}  // namespace

bool AaSurface::FitAt(const Vec3d& r, Fit* fit, float cutoff, bool attributes, std::uint32_t ball) const {
    AwaitNormals();
    const AaOptions& o = impl_->opt;
    const PointCloud& cloud = impl_->cloud;
    NeighborBatch& nb = tls_batch;
    fit->valid = false;
    // Step 1, support plane: B = sum theta_j (p_j - r)(p_j - r)^T (eq. 8, 9), about r rounded to
    // float (within 1e-7 relative of r; the frame's origin is that point).
    const Vec3f rf = RoundToFloat(r);
    const WeightedMoments wm = GatherWeighted(*impl_, rf, cutoff, ball, nb);
    if (!(wm.w > 1e-12)) return false;
    const std::size_t m = nb.size();
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
    es.computeDirect(wm.Second());
    const Vec3d lambda = es.eigenvalues();
    if (!(lambda[0] < o.normal_ratio * lambda[1])) return false;  // normal not well defined
    fit->frame = LocalFrame::FromNormal(Widen(rf), es.eigenvectors().col(0));
    fit->mean = Widen(rf) + Vec3d(wm.x, wm.y, wm.z) / wm.w;
    // Step 2, polynomial: minimise sum (a_i(x_j, y_j) - f_j)^2 theta_j (eq. 10).
    const double frame[12] = {0, 0, 0, fit->frame.u.x(), fit->frame.u.y(), fit->frame.u.z(),
                              fit->frame.v.x(), fit->frame.v.y(), fit->frame.v.z(),
                              fit->frame.n.x(), fit->frame.n.y(), fit->frame.n.z()};
    impl_->kernels->to_local(nb.x.data(), nb.y.data(), nb.z.data(), m, frame, nb.lx.data(), nb.ly.data(), nb.lz.data());
    PolyFit pf(o.degree, o.h);
    double sums[21];
    impl_->kernels->poly_sums(nb.lx.data(), nb.ly.data(), nb.lz.data(), nb.w.data(), m, pf.inv_h(), sums);
    pf.AddSums(sums);
    if (!pf.Solve(&fit->g)) return false;
    fit->valid = true;
    if (!attributes) return true;
    fit->normal_ref = WeightedNormal(cloud, nb);
    if (cloud.has_colors()) {
        Eigen::Vector4d col = Eigen::Vector4d::Zero();
        for (std::size_t j = 0; j < m; ++j) {
            const auto& c = cloud.colors[nb.index[j]];
            col += double(nb.w[j]) * Eigen::Vector4d(c[0], c[1], c[2], c[3]);
        }
        col /= wm.w;
        fit->color = {float(col[0]), float(col[1]), float(col[2]), float(col[3])};
    }
    return true;
}

AaEvaluation AaSurface::Evaluate(const Vec3d& x) const {
    AwaitNormals();
    const AaOptions& o = impl_->opt;
    AaEvaluation ev;
    NeighborBatch& nb = tls_batch;
    // eq. 1-4: the weighted mean a(x) and the covariances in directions through x.
    const Vec3f xf = RoundToFloat(x);
    const WeightedMoments wm = GatherWeighted(*impl_, xf, o.cutoff, -1, nb);
    if (!(wm.w > 1e-12)) return ev;
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
    es.computeDirect(wm.Second());
    ev.a = Widen(xf) + Vec3d(wm.x, wm.y, wm.z) / wm.w;
    ev.n = es.eigenvectors().col(0).normalized();
    if (WeightedNormal(impl_->cloud, nb).dot(ev.n) < 0) ev.n = -ev.n;
    ev.f = ev.n.dot(ev.a - x);
    ev.well_defined = es.eigenvalues()[0] < o.normal_ratio * es.eigenvalues()[1];
    return ev;
}

bool AaSurface::CenterFit(std::uint32_t ball, Fit* out, AaCounters* counters) const {
    auto& state = impl_->center_state[ball];
    CenterEntry& entry = impl_->centers[ball];
    const Vec3d center = impl_->cloud.positions[ball].cast<double>();
    // Every caller, the one that computes the entry included, reads the single-precision entry:
    // the image must not depend on which ray (thread) reached the ball first. The entry is read
    // through a volatile reference, so its floats are loaded from memory and widened: GCC 12
    // (Debian 12's, from -O2) folds a vectorised (double)(float)x back to x, and the caller that
    // had just filled `fresh` got some fields unrounded while the cache readers got them rounded
    // (1 ulp in a few pixels, depending on which thread reached a ball first).
    auto unpack = [&](const volatile CenterEntry& e) {
        out->frame.origin = center;
        out->frame.n = Vec3d(e.n[0], e.n[1], e.n[2]).normalized();
        out->frame.u = Vec3d(e.u[0], e.u[1], e.u[2]).normalized();
        out->frame.v = out->frame.n.cross(out->frame.u).normalized();
        for (int i = 0; i < 6; ++i) out->g.c[i] = e.c[i];
        out->valid = true;
    };
    const std::uint8_t s = state.load(std::memory_order_acquire);
    if (s >= 2) {
        ++counters->cache_hits;
        if (s == 3) return false;
        unpack(entry);
        return true;
    }
    CenterEntry fresh{};
    const bool ok = FitAt(center, out, kCenterCutoff, false, ball);
    if (ok) {
        for (int i = 0; i < 3; ++i) fresh.n[i] = static_cast<float>(out->frame.n[i]);
        for (int i = 0; i < 3; ++i) fresh.u[i] = static_cast<float>(out->frame.u[i]);
        for (int i = 0; i < 6; ++i) fresh.c[i] = static_cast<float>(out->g.c[i]);
    }
    // (Another thread computing the same ball computes the same values: the fit is deterministic.)
    // The thread that stores the entry counts the evaluation; one that computed it at the same
    // time counts a cache hit, so that the counters, like the image, do not depend on the timing
    // of the threads (each ball's centre fit is one evaluation, every other look-up a hit).
    std::uint8_t expected = 0;
    if (state.compare_exchange_strong(expected, 1, std::memory_order_acq_rel)) {
        entry = fresh;
        state.store(ok ? 2 : 3, std::memory_order_release);
        ++counters->evaluations;
    } else {
        ++counters->cache_hits;
    }
    if (!ok) return false;
    unpack(fresh);
    return true;
}

std::optional<AaHit> AaSurface::IntersectInBall(std::uint32_t ball, const Vec3d& o, const Vec3d& d, double tmin,
                                                double tmax, AaCounters* counters, double known_hit) const {
    const AaOptions& opt = impl_->opt;
    const Vec3d center = impl_->cloud.positions[ball].cast<double>();
    const double rho = impl_->ball_radius[ball];
    const double rho2 = rho * rho * (1.0 + 1e-9);
    auto inside = [&](double t) { return t >= tmin && t <= tmax && (o + t * d - center).squaredNorm() <= rho2; };

    // r_0: the ray against the ball centre's polynomial (section 5), cached per ball.
    // The same-sheet test below, decided before the centre fit: any root in [tmin, tmax] would
    // lie within kSameSheet * h in front of the known hit.
    if (tmin > known_hit - kSameSheet * opt.h) return std::nullopt;
    Fit center_fit;
    if (!CenterFit(ball, &center_fit, counters)) return std::nullopt;
    const Fit* cf = &center_fit;
    double r0, r1, t = 0;
    int nroots = IntersectPoly(cf->frame, cf->g, o, d, &r0, &r1);
    bool found = false;
    if (nroots >= 1 && inside(r0)) { t = r0; found = true; }
    else if (nroots == 2 && inside(r1)) { t = r1; found = true; }
    if (!found || t > known_hit - kSameSheet * opt.h) return std::nullopt;

    Fit fit;
    for (int it = 0; it < opt.max_iterations; ++it) {
        ++counters->iterations;
        ++counters->evaluations;
        const Vec3d r = o + t * d;
        if (!FitAt(r, &fit, opt.cutoff, true, ball)) return std::nullopt;
        nroots = IntersectPoly(fit.frame, fit.g, o, d, &r0, &r1);
        if (nroots == 0) return std::nullopt;
        double tn = r0;
        if (nroots == 2 && std::abs(r1 - t) < std::abs(r0 - t)) tn = r1;
        if (!inside(tn)) return std::nullopt;  // left the region of trust
        if (std::abs(fit.g.c[0]) < opt.precision) {
            AaHit hit;
            hit.t = tn;
            hit.position = o + tn * d;
            // The boundary (course notes, "surfaces from normals and weighted averages"): a hit
            // whose weighted average lies farther than boundary x h from it along the surface has
            // no points around it, only on one side: the fit extrapolates past the rim of a part.
            // The threshold is in units of the local scale where the samples lie farther apart
            // than h / 2: there an interior point's weighted average strays from it by chance
            // (about 0.2 spacings: 2.5 standard deviations of 0.5 h at a spacing of h). The
            // local scale of ball i is h times the Gaussian-weighted mean spacing around its
            // centre over the median spacing (the notes' adaptive h(x) = h / rho(x), smoothed),
            // never below h, so that the rims of evenly sampled parts keep the rule's threshold.
            // It is computed once per ball, and only for balls with a hit that fails against h.
            if (opt.boundary > 0) {
                const Vec3d e = hit.position - fit.mean;
                const Vec3d et = e - e.dot(fit.frame.n) * fit.frame.n;
                const double b2 = double(opt.boundary) * opt.boundary;
                const double u = impl_->boundary_unit, h0 = u * PointScale(ball);
                const double e2 = et.squaredNorm();
                if (e2 > b2 * h0 * h0) {
                    const double hl = std::max(h0, u * double(BoundaryScale(ball)));
                    if (e2 > b2 * hl * hl) return std::nullopt;
                }
            }
            const Vec3d l = fit.frame.ToLocal(hit.position);
            Vec3d n = fit.frame.NormalAt(fit.g, l.x(), l.y());
            const bool oriented = fit.normal_ref.squaredNorm() > 0;
            if (oriented ? n.dot(fit.normal_ref) < 0 : n.dot(d) > 0) n = -n;
            hit.normal = n;
            hit.color = fit.color;
            hit.iterations = it + 1;
            ++counters->converged;
            return hit;
        }
        t = tn;
    }
    return std::nullopt;
}

}  // namespace surfel
