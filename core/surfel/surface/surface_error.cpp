#include "surfel/surface/surface_error.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <random>

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/mls.h"

namespace surfel {
namespace {

struct Sums {
    double max = 0, sum = 0;        // plain, per sample
    double area = 0, wsum = 0, wsum2 = 0;  // weighted by the area each sample stands for
    std::size_t n = 0, failed = 0;
};

// The area of S each sample of P stands for: 1 / rho = eta^2 (SpacingFromRadius, notes 1.1.1)
// from its k = 16 nearest other samples. Capped at kAreaCap times the median so that a stray
// sample far from the rest cannot dominate the mean. `tree` holds at least 2 points.
constexpr int kAreaNeighbors = 16;
constexpr double kAreaCap = 64.0;
std::vector<double> SampleAreas(const KdTree& tree, std::span<const Vec3f> samples) {
    if (samples.empty()) return {};
    const int k = std::min<int>(kAreaNeighbors, static_cast<int>(tree.size()) - 1);
    const KnnTable knn = tree.KnnBatch(samples, k + 1);  // the sample itself comes first
    std::vector<double> area(samples.size());
    for (std::size_t i = 0; i < samples.size(); ++i) {
        const double eta = SpacingFromRadius(std::sqrt(knn.Dist2(i)[k]), k);
        area[i] = eta * eta;
    }
    std::vector<double> sorted = area;
    std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(sorted.size() / 2), sorted.end());
    const double median = sorted[sorted.size() / 2];
    for (double& a : area) {
        if (median > 0) a = std::min(a, kAreaCap * median);
        else a = 1.0;  // half the samples coincide: no area to tell them apart, equal weights
    }
    return area;
}

Sums OneSided(const PointCloud& p, const PointCloud& p_prime, float h_src, float h_dst, int degree, std::size_t max_samples,
              std::uint64_t seed, const ProgressFn& progress) {
    if (p.size() < 3 || p_prime.size() < 3)
        throw Error(ErrorCode::kInvalidArgument, "surface error needs at least 3 points in each cloud");
    // Q: a subset of P, projected onto S.
    std::vector<std::uint32_t> idx(p.size());
    std::iota(idx.begin(), idx.end(), 0u);
    if (max_samples > 0 && max_samples < idx.size()) {
        std::mt19937_64 rng(seed);
        for (std::size_t i = 0; i < max_samples; ++i) {  // partial Fisher-Yates, portable
            const std::size_t j = i + static_cast<std::size_t>(rng() % (idx.size() - i));
            std::swap(idx[i], idx[j]);
        }
        idx.resize(max_samples);
        std::sort(idx.begin(), idx.end());
    }
    std::vector<Vec3f> q0(idx.size());
    for (std::size_t i = 0; i < idx.size(); ++i) q0[i] = p.positions[idx[i]];
    KdTree tree_src(p.positions);
    const std::vector<double> area = SampleAreas(tree_src, q0);
    MlsOptions src_opt;
    src_opt.h = h_src;
    MlsSurface s(p, tree_src, src_opt);
    auto q = s.ProjectAll(q0, progress ? ProgressFn([&](double f) { return progress(0.5 * f); }) : ProgressFn{});
    KdTree tree_dst(p_prime.positions);
    MlsOptions dst_opt;
    dst_opt.h = h_dst;
    dst_opt.degree = degree;
    MlsSurface s_prime(p_prime, tree_dst, dst_opt);
    auto proj = s_prime.ProjectAll(q.positions, progress ? ProgressFn([&](double f) { return progress(0.5 + 0.5 * f); }) : ProgressFn{});
    // d(q, S') = |q - Psi'(q)|. Where the projection onto S' fails (q farther than the cutoff
    // from P': a region the other cloud lost) or lands farther than the nearest sample of P' plus
    // h' (an extrapolating fit: the samples lie on S' up to about h'), the distance to that
    // nearest sample stands in. Samples whose projection onto S itself fails are left out.
    const double h_prime = s_prime.h();
    Sums sums;
    for (std::size_t i = 0; i < q0.size(); ++i) {
        if (q.normals[i].squaredNorm() == 0) {
            ++sums.failed;
            continue;
        }
        const double nearest = std::sqrt(double(tree_dst.Nearest(q.positions[i]).dist2));
        double d = nearest;
        const double mls = (q.positions[i] - proj.positions[i]).cast<double>().norm();
        if (proj.normals[i].squaredNorm() > 0 && mls <= nearest + h_prime) d = mls;
        else ++sums.failed;
        sums.max = std::max(sums.max, d);
        sums.sum += d;
        sums.area += area[i];
        sums.wsum += area[i] * d;
        sums.wsum2 += area[i] * d * d;
        ++sums.n;
    }
    return sums;
}

}  // namespace

void SurfaceErrorOptions::Validate() const {
    CheckAtLeast("h_source", h_source, 0.0);
    CheckAtLeast("h_target", h_target, 0.0);
    CheckRange("degree", degree, kMinMlsDegree, kMaxMlsDegree);
}

SurfaceError MeasureSurfaceError(const PointCloud& p, const PointCloud& p_prime, const SurfaceErrorOptions& o,
                                 const ProgressFn& progress) {
    o.Validate();
    Sums a = OneSided(p, p_prime, o.h_source, o.h_target, o.degree, o.max_samples, o.seed, progress);
    if (o.symmetric) {
        Sums b = OneSided(p_prime, p, o.h_target, o.h_source, o.degree, o.max_samples, o.seed + 1, {});
        // Pooled: the mean over both surfaces, each sample weighted by the area it stands for.
        a.max = std::max(a.max, b.max);
        a.sum += b.sum;
        a.area += b.area;
        a.wsum += b.wsum;
        a.wsum2 += b.wsum2;
        a.n += b.n;
        a.failed += b.failed;
    }
    SurfaceError e;
    e.max = a.max;
    e.avg = a.area > 0 ? a.wsum / a.area : 0.0;
    e.rms = a.area > 0 ? std::sqrt(a.wsum2 / a.area) : 0.0;
    e.avg_per_sample = a.n ? a.sum / static_cast<double>(a.n) : 0.0;
    e.diagonal = p.Bounds().Diagonal();
    e.samples = a.n;
    e.failed = a.failed;
    if (a.n == 0) throw Error(ErrorCode::kInvalidArgument, "surface error: no sample could be projected onto both surfaces");
    return e;
}

}  // namespace surfel
