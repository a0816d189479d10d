// Particle simulation (course notes, Pauly 2.3, after Turk 1992): particles spread by density,
// linear repulsion within radius r on a dynamic grid, kept on the surface by projection onto the
// tangent plane of the closest original point, final MLS projection.

#include "surfel/resample/particle_engine.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <numbers>
#include <numeric>

#include "surfel/base/error.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/spatial/uniform_grid.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/mls.h"

namespace surfel {

ParticleEngine::ParticleEngine(const PointCloud& input, std::span<const Vec3f> normals,
                               std::span<const float> variation, bool adaptive)
    : input_(input), normals_(normals) {
    const std::span<const Vec3f> points = input.positions;
    const std::size_t n = points.size();
    SURFEL_CHECK(n >= 2 && normals.size() == n, "n = " << n << ", normals = " << normals.size());
    tree_ = std::make_unique<KdTree>(points);
    const SamplingDensity density = ComputeSamplingDensity(*tree_, std::min<int>(6, static_cast<int>(n) - 1));
    reach_radius_ = density.radius;

    // Per original point: the area it represents (1 / rho, notes 2.3.1) and the radius scale. The
    // adaptive variant scales the repulsion radius with the inverse of the variation (2.3.4),
    // relative to the median and clamped to [1/2, 2] so flat regions keep some particles.
    scale_.assign(n, 1.0);
    if (adaptive && !variation.empty()) {
        std::vector<float> sorted(variation.begin(), variation.end());
        std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(n / 2), sorted.end());
        const double median = std::max(1e-12, static_cast<double>(sorted[n / 2]));
        for (std::size_t i = 0; i < n; ++i)
            scale_[i] = std::clamp(median / std::max(1e-12, static_cast<double>(variation[i])), 0.5, 2.0);
    }
    // Outliers (isolated samples: tiny density, so a huge area) would draw particles away from
    // the surface: an area counts at most 4x the median, a reach (below) at most 2x the median.
    std::vector<float> sorted_radius(density.radius);
    std::nth_element(sorted_radius.begin(), sorted_radius.begin() + static_cast<std::ptrdiff_t>(n / 2),
                     sorted_radius.end());
    median_radius_ = sorted_radius[n / 2];
    const double max_area = 4.0 * std::numbers::pi * double(median_radius_) * median_radius_ / 6.0;
    weight_.resize(n);
    total_ = 0.0;
    for (std::size_t i = 0; i < n; ++i) {
        const double area = std::min(max_area, 1.0 / std::max(1e-30, static_cast<double>(density.density[i])));
        weight_[i] = area / (scale_[i] * scale_[i]);  // expected particles ~ area / r^2
        total_ += weight_[i];
    }
}

ParticleEngine::~ParticleEngine() = default;

Vec3f ParticleEngine::OntoSurface(Vec3f moved) const {
    const std::span<const Vec3f> points = input_.positions;
    const std::uint32_t q = tree_->Nearest(moved).index;
    const Vec3f& nq = normals_[q];
    moved -= (moved - points[q]).dot(nq) * nq;
    // Stay on the sampled surface: at an open boundary (a scan's edge, a hole) the tangent plane
    // goes on where the samples stop, and particles pushed outward would drift along it. Keep
    // them within the 6-neighbour radius of the closest original point.
    const Vec3f off = moved - points[q];
    const float reach = std::min(reach_radius_[q], 2.0f * median_radius_), len_off = off.norm();
    if (len_off > reach) moved = points[q] + off * (reach / len_off);
    return moved;
}

void ParticleEngine::Relax(std::vector<Vec3f>& positions, double radius, int iterations) const {
    const std::size_t m = positions.size();
    const float r = static_cast<float>(radius);
    std::vector<Vec3f> next(m);
    for (int iter = 0; iter < iterations; ++iter) {
        const UniformGrid grid(positions, r);
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 512), [&](const auto& range) {
            for (std::size_t p = range.begin(); p != range.end(); ++p) {
                const Vec3f x = positions[p];
                Vec3d force = Vec3d::Zero();
                grid.ForEachWithin(x, r, [&](std::uint32_t j, const Vec3f& y, float d2) {
                    if (j == p) return;
                    force += ((r - std::sqrt(d2)) * (x - y)).cast<double>();
                });
                Vec3d step = force * (0.3 / r);  // as in Run
                const double len = step.norm();
                if (len > 0.5 * r) step *= 0.5 * r / len;
                next[p] = OntoSurface(x + step.cast<float>());
            }
        });
        positions.swap(next);
    }
}

void ParticleEngine::Run(const ParticleParams& params, std::vector<Vec3f>& positions,
                         std::vector<Vec3f>& out_normals, ProgressTracker& progress) const {
    const std::span<const Vec3f> points = input_.positions;
    const std::span<const Vec3f> normals = normals_;
    const KdTree& tree = *tree_;
    const std::size_t n = points.size();
    const std::size_t m = params.count;
    SURFEL_CHECK(m >= 1);
    // Uniform repulsion radius for this many particles: a bit above the hexagonal spacing of
    // total / m area per particle, so that neighbours push until the spacing is even.
    const double particles = static_cast<double>(params.fixed_input ? m + n : m);
    const double r0 = 2.0 * std::sqrt(total_ / (std::numbers::pi * particles));
    progress.Advance(0.05);

    // Spread: systematic sampling over the cumulative weights (seeded offset), plus a small
    // seeded tangential jitter so that particles on the same original point separate.
    detail::Random rng(params.seed);
    positions.resize(m);
    std::vector<std::uint32_t> home(m);
    {
        const double step = total_ / static_cast<double>(m);
        double next = rng.Uniform() * step, acc = 0.0;
        std::size_t i = 0;
        for (std::size_t p = 0; p < m; ++p) {
            while (i + 1 < n && acc + weight_[i] < next) acc += weight_[i++];
            home[p] = static_cast<std::uint32_t>(i);
            next += step;
        }
        for (std::size_t p = 0; p < m; ++p) {
            const Vec3f& nn = normals[home[p]];
            Vec3f t = nn.unitOrthogonal();
            const Vec3f b = nn.cross(t);
            const double angle = 2.0 * std::numbers::pi * rng.Uniform(), len = 0.25 * r0 * rng.Uniform();
            positions[p] = points[home[p]] + static_cast<float>(len * std::cos(angle)) * t +
                           static_cast<float>(len * std::sin(angle)) * b;
        }
    }

    std::vector<Vec3f> next(m);
    std::vector<float> radius(m);
    // With fixed input samples, the grid holds the particles followed by the samples.
    std::vector<Vec3f> all;
    if (params.fixed_input) all.resize(m + n);
    const double max_scale = *std::max_element(scale_.begin(), scale_.end());
    for (int iter = 0; iter < params.iterations; ++iter) {
        // Radius of each particle from its closest original point.
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 1024), [&](const auto& range) {
            for (std::size_t p = range.begin(); p != range.end(); ++p) {
                home[p] = tree.Nearest(positions[p]).index;
                radius[p] = static_cast<float>(r0 * scale_[home[p]]);
            }
        });
        if (params.fixed_input) {
            std::copy(positions.begin(), positions.end(), all.begin());
            std::copy(points.begin(), points.end(), all.begin() + static_cast<std::ptrdiff_t>(m));
        }
        const UniformGrid grid(params.fixed_input ? std::span<const Vec3f>(all) : std::span<const Vec3f>(positions),
                               static_cast<float>(r0 * max_scale));
        // Linear repulsion (eq. 2.2, 2.3), then back onto the tangent plane of the closest
        // original point (2.3.3). Jacobi update: every particle reads the previous positions.
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 512), [&](const auto& range) {
            for (std::size_t p = range.begin(); p != range.end(); ++p) {
                const Vec3f x = positions[p];
                const float r = radius[p];
                Vec3d force = Vec3d::Zero();
                grid.ForEachWithin(x, r, [&](std::uint32_t j, const Vec3f& y, float d2) {
                    if (j == p) return;
                    const float d = std::sqrt(d2);
                    force += ((r - d) * (x - y)).cast<double>();
                });
                // Step: a lone neighbour at distance d moves x by 0.3 (r - d) (k = 0.3 / r).
                Vec3d step = force * (0.3 / r);
                const double len = step.norm();
                if (len > 0.5 * r) step *= 0.5 * r / len;
                next[p] = OntoSurface(x + step.cast<float>());
            }
        });
        positions.swap(next);
        progress.Advance(0.85 / std::max(1, params.iterations));
    }

    // Final MLS projection (2.3.3); normals oriented like the closest original normal.
    const MlsSurface mls(input_, tree);
    const MlsSurface::Batch batch = mls.ProjectAll(positions);
    out_normals.resize(m);
    for (std::size_t p = 0; p < m; ++p) {
        const std::uint32_t q = tree.Nearest(positions[p]).index;
        Vec3f nrm = normals[q];
        if (batch.normals[p].allFinite() && batch.normals[p].squaredNorm() > 0.5f &&
            batch.positions[p].allFinite() && (batch.positions[p] - positions[p]).norm() < r0) {
            positions[p] = batch.positions[p];
            nrm = batch.normals[p].dot(normals[q]) < 0 ? Vec3f(-batch.normals[p]) : batch.normals[p];
        }
        out_normals[p] = nrm;
    }
    progress.Advance(0.1);
}

}  // namespace surfel
