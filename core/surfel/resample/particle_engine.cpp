// Particle simulation (course notes, Pauly 2.3, after Turk 1992): particles spread by density,
// linear repulsion within radius r on a dynamic grid, kept on the surface by projection onto the
// tangent plane of the closest original point, final MLS projection.

#include "surfel/resample/particle_engine.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <numeric>
#include <optional>
#include <thread>

#include "surfel/base/error.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/spatial/uniform_grid.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/mls.h"

namespace surfel {
namespace {
// Neighbours per input point in the graph WalkNearest follows.
constexpr int kWalkNeighbors = 8;
// Verlet lists (Allen & Tildesley): each particle's neighbours within its radius plus a skin of
// kSkin r0, rebuilt only when some particle may have come within its radius of one not listed.
constexpr double kSkin = 0.5;
// Particles per block of the neighbour-list build (each block one output buffer).
constexpr std::size_t kListBlock = 1024;
// Relax with rim directions: how far past a rim sample of the input (along its outward
// direction, in units of its reach) a move may go. On the open square of the split tests
// (1500 samples to spacing 0.02): 0 (not past it) squeezed the samples against the rim samples'
// jagged tangent lines (NN CV 0.227, 32 rounds); 0.25: 15 rounds, CV 0.063, 75 samples more
// than a spacing past the square's edge; none (only the reach): 20 rounds, CV 0.049, 748 past it.
constexpr float kRimMargin = 0.25f;
}  // namespace

std::vector<double> CommonScaleVariation(const KdTree& tree, std::span<const float> variation) {
    const std::size_t n = tree.size();
    SURFEL_CHECK(variation.size() == n && n >= 2, "variation = " << variation.size() << ", n = " << n);
    return CommonScaleVariation(
        tree.KnnAll(std::min<int>(kVariationNeighbors, static_cast<int>(n) - 1)), variation);
}

std::vector<double> CommonScaleVariation(const KnnTable& knn, std::span<const float> variation) {
    const std::size_t n = knn.size();
    SURFEL_CHECK(variation.size() == n && n >= 2,
                 "variation = " << variation.size() << ", n = " << n);
    const int k = std::min<int>(kVariationNeighbors, static_cast<int>(n) - 1);
    SURFEL_CHECK(knn.k >= k, "knn.k = " << knn.k << ", k = " << k);
    // sigma_n / r_n^2: on a smooth surface lambda_0 ~ r_n^4 (curvature)^2 and the tangent
    // variation ~ r_n^2, so this is sigma_n at one radius for every point, free of the k-nearest
    // radius's sampling noise.
    std::vector<double> at_scale(n);
    for (std::size_t i = 0; i < n; ++i)
        at_scale[i] = static_cast<double>(variation[i]) / std::max(1e-30, static_cast<double>(knn.Dist2(i)[k - 1]));
    // Averaged over the point and its n-neighbourhood: the smoothing a larger neighbourhood
    // gives (notes 1.2, fig. 1.2), at the cost of one pass.
    std::vector<double> out(n);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 2048), [&](const auto& range) {
        for (std::size_t i = range.begin(); i != range.end(); ++i) {
            double sum = at_scale[i];
            int count = 1;
            for (const std::uint32_t j : knn.Row(i).first(static_cast<std::size_t>(k)))
                if (j != UINT32_MAX) sum += at_scale[j], ++count;
            out[i] = sum / count;
        }
    });
    return out;
}

ParticleEngine::ParticleEngine(const PointCloud& input, std::span<const Vec3f> normals,
                               std::span<const float> variation, bool adaptive)
    : ParticleEngine(input, normals, variation, adaptive, Shared{}) {}

ParticleEngine::ParticleEngine(const PointCloud& input, std::span<const Vec3f> normals,
                               std::span<const float> variation, bool adaptive,
                               const Shared& shared)
    : input_(input), normals_(normals) {
    const std::span<const Vec3f> points = input.positions;
    const std::size_t n = points.size();
    SURFEL_CHECK(n >= 2 && (normals.size() == n || (normals.empty() && shared.tree && n >= 3)),
                 "n = " << n << ", normals = " << normals.size());
    if (shared.tree) {
        SURFEL_CHECK(shared.tree->size() == n, "tree = " << shared.tree->size() << ", n = " << n);
        tree_ = shared.tree;
    } else {
        own_tree_ = std::make_unique<KdTree>(points);
        tree_ = own_tree_.get();
    }
    const int density_k = std::min<int>(6, static_cast<int>(n) - 1);
    graph_k_ = std::min<int>(kWalkNeighbors, static_cast<int>(n) - 1);
    if (shared.knn) {
        SURFEL_CHECK(shared.tree && shared.knn->size() == n && shared.knn->k >= graph_k_,
                     "knn = " << shared.knn->size() << " x " << shared.knn->k << ", n = " << n);
        shared_knn_ = shared.knn;
    }
    // Sampling density (notes 1.1.1, k = 6): from the shared table's 6th column (the distances
    // KthNeighborDistances finds), else from the tree.
    SamplingDensity density;
    if (shared_knn_) {
        density.radius.resize(n);
        density.density.resize(n);
        density.spacing.resize(n);
        for (std::size_t i = 0; i < n; ++i) {
            const float r = std::sqrt(shared_knn_->Dist2(i)[density_k - 1]);
            density.radius[i] = r;
            density.density[i] = r > 0 ? static_cast<float>(density_k / (std::numbers::pi * r * r))
                                       : std::numeric_limits<float>::infinity();
            density.spacing[i] = SpacingFromRadius(r, density_k);
        }
        std::vector<float> spacing(density.spacing);
        std::nth_element(spacing.begin(), spacing.begin() + static_cast<std::ptrdiff_t>(n / 2),
                         spacing.end());
        density.median_spacing = spacing[n / 2];
    } else {
        density = ComputeSamplingDensity(*tree_, density_k);
    }
    reach_radius_ = density.radius;
    // The final projection's scale as MlsSurface derives it by default (2 x MedianSpacing(tree),
    // the k = 6 spacing's median over at most 20000 strided points), from this density.
    mls_h_ = 2.0f * MedianSpacing(density);

    // Per original point: the area it represents (1 / rho, notes 2.3.1) and the radius scale. The
    // adaptive variant scales the repulsion radius with the inverse of the variation (2.3.4),
    // relative to the median and clamped to [1/2, 2] so flat regions keep some particles.
    scale_.assign(n, 1.0);
    if (adaptive && !variation.empty()) {
        SURFEL_CHECK(variation.size() == n, "variation = " << variation.size() << ", n = " << n);
        const int vk = std::min<int>(kVariationNeighbors, static_cast<int>(n) - 1);
        const std::vector<double> v = shared_knn_ && shared_knn_->k >= vk
                                          ? CommonScaleVariation(*shared_knn_, variation)
                                          : CommonScaleVariation(*tree_, variation);
        std::vector<double> sorted(v);
        std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(n / 2), sorted.end());
        const double median = std::max(1e-30, sorted[n / 2]);
        for (std::size_t i = 0; i < n; ++i) scale_[i] = std::clamp(median / std::max(1e-30, v[i]), 0.5, 2.0);
    }
    // Outliers (isolated samples: tiny density, so a huge area) would draw particles away from
    // the surface: an area counts at most 4x the median, a reach (below) at most 2x the median.
    std::vector<float> sorted_radius(density.radius);
    std::nth_element(sorted_radius.begin(), sorted_radius.begin() + static_cast<std::ptrdiff_t>(n / 2),
                     sorted_radius.end());
    median_radius_ = sorted_radius[n / 2];
    const double max_area = 4.0 * std::numbers::pi * double(median_radius_) * median_radius_ / 6.0;
    weight_.resize(n);
    area_.resize(n);
    total_ = 0.0;
    for (std::size_t i = 0; i < n; ++i) {
        const double area = std::min(max_area, 1.0 / std::max(1e-30, static_cast<double>(density.density[i])));
        area_[i] = area;
        weight_[i] = area / (scale_[i] * scale_[i]);  // expected particles ~ area / r^2
        total_ += weight_[i];
    }
    // The walk graph: the shared table's first columns; else, when the normals are estimated
    // lazily (a few particles over a large input), rows filled as the walks reach them; else the
    // whole KnnAll (every row is visited when there are many particles).
    if (!shared_knn_) {
        if (normals.empty()) {
            graph_.k = graph_k_;
            graph_.indices.assign(n * static_cast<std::size_t>(graph_k_), UINT32_MAX);
            graph_state_ = std::make_unique<std::atomic<std::uint8_t>[]>(n);
        } else {
            graph_ = tree_->KnnAll(graph_k_);
        }
    }
    if (normals.empty()) {
        lazy_options_ = shared.lazy_normals;
        lazy_normals_.resize(n);
        normal_state_ = std::make_unique<std::atomic<std::uint8_t>[]>(n);
    }
}

const Vec3f& ParticleEngine::Normal(std::uint32_t i) const {
    if (!normal_state_) return normals_[i];
    if (normal_state_[i].load(std::memory_order_acquire) == 2) return lazy_normals_[i];
    // First use: estimate it (a pure function of i, so whichever thread wins writes the same
    // value); a thread that loses the race waits for the winner's write.
    std::uint8_t expected = 0;
    if (normal_state_[i].compare_exchange_strong(expected, 1, std::memory_order_acq_rel)) {
        thread_local NormalScratch scratch;
        lazy_normals_[i] = EstimateNormalAt(*tree_, i, lazy_options_, scratch);
        normal_state_[i].store(2, std::memory_order_release);
    } else {
        while (normal_state_[i].load(std::memory_order_acquire) != 2) std::this_thread::yield();
    }
    return lazy_normals_[i];
}

std::span<const std::uint32_t> ParticleEngine::GraphRow(std::uint32_t i,
                                                        std::vector<std::uint32_t>& buffer) const {
    const std::size_t k = static_cast<std::size_t>(graph_k_);
    if (shared_knn_) return shared_knn_->Row(i).first(k);
    if (!graph_state_ || graph_state_[i].load(std::memory_order_acquire) == 2) return graph_.Row(i);
    thread_local std::vector<Neighbor> near;
    buffer.resize(k);
    tree_->KnnRow(i, graph_k_, buffer.data(), nullptr, near);  // KnnAll(graph_k_)'s row
    std::uint8_t expected = 0;
    if (graph_state_[i].compare_exchange_strong(expected, 1, std::memory_order_acq_rel)) {
        std::copy(buffer.begin(), buffer.end(),
                  graph_.indices.begin() + static_cast<std::ptrdiff_t>(i * k));
        graph_state_[i].store(2, std::memory_order_release);
    }
    return buffer;
}

ParticleEngine::~ParticleEngine() = default;

Vec3f ParticleEngine::OntoSurface(Vec3f moved, std::span<const Vec3f> rim_outward) const {
    const std::span<const Vec3f> points = input_.positions;
    const std::uint32_t q = tree_->Nearest(moved).index;
    const Vec3f& nq = Normal(q);
    moved -= (moved - points[q]).dot(nq) * nq;
    // Stay on the sampled surface: at an open boundary (a scan's edge, a hole) the tangent plane
    // goes on where the samples stop, and particles pushed outward would drift along it. Keep
    // them within the 6-neighbour radius of the closest original point.
    const float reach = std::min(reach_radius_[q], 2.0f * median_radius_);
    // Past a rim sample of the input by at most kRimMargin of that radius along its outward
    // direction (Relax with rim directions).
    if (!rim_outward.empty())
        moved -= std::max(0.0f, (moved - points[q]).dot(rim_outward[q]) - kRimMargin * reach) *
                 rim_outward[q];
    const Vec3f off = moved - points[q];
    const float len_off = off.norm();
    if (len_off > reach) moved = points[q] + off * (reach / len_off);
    return moved;
}

std::uint32_t ParticleEngine::WalkNearest(const Vec3f& x, std::uint32_t start,
                                          float* margin) const {
    const std::span<const Vec3f> points = input_.positions;
    std::uint32_t cur = start;
    float best = (points[cur] - x).squaredNorm();
    thread_local std::vector<std::uint32_t> buffer;
    for (;;) {
        std::uint32_t next = cur;
        float row_min = INFINITY;  // the nearest of cur's graph neighbours
        for (const std::uint32_t j : GraphRow(cur, buffer)) {
            if (j == UINT32_MAX) continue;
            const float d2 = (points[j] - x).squaredNorm();
            row_min = std::min(row_min, d2);
            if (d2 < best || (d2 == best && j < next)) best = d2, next = j;
        }
        if (next == cur) {
            // No graph neighbour of cur is nearer than cur by less than this: while x moves by
            // under half of it, a walk from cur stays at cur (triangle inequality). A relative
            // 1e-4 of the distances covers the float rounding of the squared distances.
            if (margin) {
                const float d_cur = std::sqrt(best), d_row = std::sqrt(row_min);
                *margin = std::max(0.0f, d_row - d_cur - 1e-4f * (d_row + d_cur));
            }
            return cur;
        }
        cur = next;
    }
}

Vec3f ParticleEngine::OntoSurface(Vec3f moved, std::uint32_t& home) const {
    const std::uint32_t q = home = WalkNearest(moved, home);
    return OntoPlane(moved, q);
}

Vec3f ParticleEngine::OntoPlane(Vec3f moved, std::uint32_t q) const {
    const std::span<const Vec3f> points = input_.positions;
    const Vec3f& nq = Normal(q);
    moved -= (moved - points[q]).dot(nq) * nq;
    const Vec3f off = moved - points[q];  // within reach, as OntoSurface(moved)
    const float reach = std::min(reach_radius_[q], 2.0f * median_radius_), len_off = off.norm();
    if (len_off > reach) moved = points[q] + off * (reach / len_off);
    return moved;
}

void ParticleEngine::Relax(std::vector<Vec3f>& positions, double radius, int iterations,
                           const std::vector<std::uint8_t>* movable,
                           std::span<const Vec3f> rim_outward) const {
    SURFEL_CHECK(rim_outward.empty() || rim_outward.size() == input_.size(), rim_outward.size());
    const std::size_t m = positions.size();
    const float r = static_cast<float>(radius);
    std::vector<Vec3f> next(m);
    for (int iter = 0; iter < iterations; ++iter) {
        const UniformGrid grid(positions, r);
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 512), [&](const auto& range) {
            for (std::size_t p = range.begin(); p != range.end(); ++p) {
                const Vec3f x = positions[p];
                if (movable && !(*movable)[p]) {
                    next[p] = x;
                    continue;
                }
                Vec3d force = Vec3d::Zero();
                grid.ForEachWithin(x, r, [&](std::uint32_t j, const Vec3f& y, float d2) {
                    if (j == p) return;
                    force += ((r - std::sqrt(d2)) * (x - y)).cast<double>();
                });
                Vec3d step = force * (kRepulsionGain / r);  // as in Run
                const double len = step.norm();
                if (len > kMaxStep * r) step *= kMaxStep * r / len;
                next[p] = OntoSurface(x + step.cast<float>(), rim_outward);
            }
        });
        positions.swap(next);
    }
}

void ParticleEngine::Run(const ParticleParams& params, std::vector<Vec3f>& positions,
                         std::vector<Vec3f>& out_normals, ProgressTracker& progress, ParticleStats* stats) const {
    const std::span<const Vec3f> points = input_.positions;
    const KdTree& tree = *tree_;
    const std::size_t n = points.size();
    const std::size_t m = params.count;
    SURFEL_CHECK(m >= 1);
    ParticleStats local_stats;
    ParticleStats& st = stats ? *stats : local_stats;
    st = ParticleStats{};
    // Uniform repulsion radius for this many particles: a bit above the hexagonal spacing of
    // total / m area per particle, so that neighbours push until the spacing is even.
    const double particles = static_cast<double>(params.fixed_input ? m + n : m);
    const double r0 = 2.0 * std::sqrt(total_ / (std::numbers::pi * particles));
    progress.Advance(0.05);

    // Spread (2.3.1): systematic sampling over the cumulative weights (seeded offset) gives each
    // original point its share of particles, in particle order.
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
        // The homes' tangent planes, in parallel where they are estimated on first use.
        if (normal_state_)
            tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 256), [&](const auto& range) {
                for (std::size_t p = range.begin(); p != range.end(); ++p) Normal(home[p]);
            });
        if (params.spread == ParticleParams::Spread::kJitter) {
            // A small seeded tangential jitter, so that particles on the same point separate.
            for (std::size_t p = 0; p < m; ++p) {
                const Vec3f& nn = Normal(home[p]);
                Vec3f t = nn.unitOrthogonal();
                const Vec3f b = nn.cross(t);
                const double angle = 2.0 * std::numbers::pi * rng.Uniform(), len = 0.25 * r0 * rng.Uniform();
                positions[p] = points[home[p]] + static_cast<float>(len * std::cos(angle)) * t +
                               static_cast<float>(len * std::sin(angle)) * b;
            }
        } else {
            // The c particles of a sample split its tangent disk of area 1 / rho (radius R) on a
            // Vogel spiral, R sqrt((j + 1/2) / c) at angles j x the golden angle from a seeded
            // phase: about equal areas per particle, no two on the same spot.
            constexpr double kGolden = 2.399963229728653;  // pi (3 - sqrt 5)
            for (std::size_t p = 0; p < m;) {
                std::size_t e = p;
                while (e < m && home[e] == home[p]) ++e;
                const std::uint32_t s = home[p];
                const double c = static_cast<double>(e - p), R = std::sqrt(area_[s] / std::numbers::pi);
                const Vec3f& nn = Normal(s);
                const Vec3f t = nn.unitOrthogonal(), b = nn.cross(t);
                const double phase = 2.0 * std::numbers::pi * rng.Uniform();
                for (std::size_t j = 0; j < e - p; ++j) {
                    const double len = R * std::sqrt((static_cast<double>(j) + 0.5) / c);
                    const double angle = phase + kGolden * static_cast<double>(j);
                    positions[p + j] = points[s] + static_cast<float>(len * std::cos(angle)) * t +
                                       static_cast<float>(len * std::sin(angle)) * b;
                }
                p = e;
            }
        }
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 1024), [&](const auto& range) {
            for (std::size_t p = range.begin(); p != range.end(); ++p) home[p] = WalkNearest(positions[p], home[p]);
        });
    }

    std::vector<Vec3f> next(m);
    std::vector<float> radius(m), list_radius(m);
    std::vector<float> moved(m, 0.0f);  // distance from the position at the last list build
    std::vector<Vec3f> built(m);        // positions at the last list build
    // Verlet lists in CSR form: neighbours of particle p are nbr[first[p] .. first[p + 1]); with
    // fixed input samples, index m + i is sample i.
    std::vector<std::uint32_t> first(m + 1), nbr;
    std::vector<std::vector<std::uint32_t>> block_nbr;
    std::vector<Vec3f> all;
    if (params.fixed_input) all.resize(m + n);
    std::optional<UniformGrid>
        list_grid;  // of the positions at the last build, kept for the fast ones
    for (std::size_t p = 0; p < m; ++p) radius[p] = static_cast<float>(r0 * scale_[home[p]]);
    const float skin = static_cast<float>(kSkin * r0);
    const auto build_lists = [&] {
        ++st.neighbor_rebuilds;
        float max_list = 0.0f;
        for (std::size_t p = 0; p < m; ++p) {
            list_radius[p] = radius[p] + skin;
            max_list = std::max(max_list, list_radius[p]);
        }
        if (params.fixed_input) {
            std::copy(positions.begin(), positions.end(), all.begin());
            std::copy(points.begin(), points.end(), all.begin() + static_cast<std::ptrdiff_t>(m));
        }
        const std::span<const Vec3f> pts = params.fixed_input ? std::span<const Vec3f>(all) : std::span<const Vec3f>(positions);
        const UniformGrid& grid = list_grid.emplace(pts, max_list);
        // One query per particle into fixed blocks of kListBlock particles (the blocks, not the
        // threads, fix the layout), then the blocks concatenated in particle order.
        const std::size_t blocks = (m + kListBlock - 1) / kListBlock;
        block_nbr.resize(blocks);
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, blocks, 1), [&](const auto& range) {
            for (std::size_t b = range.begin(); b != range.end(); ++b) {
                std::vector<std::uint32_t>& out = block_nbr[b];
                out.clear();
                for (std::size_t p = b * kListBlock; p < std::min(m, (b + 1) * kListBlock); ++p) {
                    grid.ForEachWithin(positions[p], list_radius[p], [&](std::uint32_t j, const Vec3f&, float) {
                        if (j != p) out.push_back(j);
                    });
                    first[p + 1] = static_cast<std::uint32_t>(out.size());  // within the block, for now
                }
            }
        });
        first[0] = 0;
        std::uint32_t base = 0;
        for (std::size_t b = 0; b < blocks; ++b) {
            for (std::size_t p = b * kListBlock; p < std::min(m, (b + 1) * kListBlock); ++p) first[p + 1] += base;
            base += static_cast<std::uint32_t>(block_nbr[b].size());
        }
        nbr.resize(base);
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, blocks, 1), [&](const auto& range) {
            for (std::size_t b = range.begin(); b != range.end(); ++b)
                std::copy(block_nbr[b].begin(), block_nbr[b].end(), nbr.begin() + first[b * kListBlock]);
        });
        built = positions;
        std::fill(moved.begin(), moved.end(), 0.0f);
    };
    build_lists();
    const auto neighbor = [&](std::uint32_t j) -> const Vec3f& { return j < m ? positions[j] : points[j - m]; };
    std::vector<float> step_len(m);
    std::vector<float> walk_margin(m, 0.0f);  // of each particle's last walk (0: walk next step)
    std::vector<Vec3f> walked_at(positions);  // where that walk looked from
    std::vector<std::uint8_t> fast(m, 0);
    std::vector<std::uint32_t> fast_ids, extra_first(m + 1), extra;
    std::vector<std::vector<std::uint32_t>> fast_nbrs;
    // Above kDefaultParticleGain the particles do not come to rest (at 0.5 on the sphere the mean
    // step stays ~2 % of r0: they bounce within their neighbours' reach), yet end more evenly
    // spaced; relax_tolerance then stops only above that level.
    const float gain = static_cast<float>(params.gain);
    for (int iter = 0; iter < params.iterations; ++iter) {
        // The lists hold every neighbour within radius[a] of a particle a for the pairs of
        // "slow" particles, those that moved less than half the smallest slack
        // (list_radius - radius) since the lists were built. The few "fast" ones (a particle
        // jumping to another sample's tangent plane at a scan's edge) find their neighbours
        // anew, and their pushes on slow particles are scattered to those; when more than 3 %
        // are fast, every list is rebuilt.
        float min_slack = INFINITY, max_radius = 0.0f;
        for (std::size_t p = 0; p < m; ++p) {
            min_slack = std::min(min_slack, list_radius[p] - radius[p]);
            max_radius = std::max(max_radius, radius[p]);
        }
        fast_ids.clear();
        for (std::size_t p = 0; p < m; ++p)
            if (2.0f * moved[p] >= min_slack) fast_ids.push_back(static_cast<std::uint32_t>(p));
        // A slow particle within max_radius of a fast one now was within max_radius + min_slack / 2
        // of it at the build (a hair more for rounding), which the lists' grid must reach.
        const float slow_reach = max_radius + 0.5f * min_slack * 1.001f;
        if (fast_ids.size() * 33 > m || min_slack <= 0.0f || !(slow_reach <= list_grid->cell())) {
            build_lists();
            fast_ids.clear();
        }
        std::fill(fast.begin(), fast.end(), 0);
        for (const std::uint32_t f : fast_ids) fast[f] = 1;
        std::fill(extra_first.begin(), extra_first.end(), 0);
        extra.clear();
        if (!fast_ids.empty()) {
            // Every particle (and fixed sample) within max_radius of a fast one: the slow ones and
            // the samples from the lists' grid (positions at the build, within slow_reach),
            // tested at their current positions; the fast ones from a small grid of theirs.
            std::vector<Vec3f> fast_positions(fast_ids.size());
            for (std::size_t k = 0; k < fast_ids.size(); ++k)
                fast_positions[k] = positions[fast_ids[k]];
            const UniformGrid fast_grid(fast_positions, max_radius);
            const float r2 = max_radius * max_radius;
            fast_nbrs.assign(fast_ids.size(), {});
            tbb::parallel_for(tbb::blocked_range<std::size_t>(0, fast_ids.size(), 16), [&](const auto& range) {
                for (std::size_t k = range.begin(); k != range.end(); ++k) {
                    const std::uint32_t f = fast_ids[k];
                    const Vec3f& xf = positions[f];
                    list_grid->ForEachWithin(xf, slow_reach,
                                             [&](std::uint32_t j, const Vec3f&, float) {
                                                 if (j == f || (j < m && fast[j])) return;
                                                 if ((neighbor(j) - xf).squaredNorm() <= r2)
                                                     fast_nbrs[k].push_back(j);
                                             });
                    fast_grid.ForEachWithin(xf, max_radius,
                                            [&](std::uint32_t i, const Vec3f&, float) {
                                                if (fast_ids[i] != f)
                                                    fast_nbrs[k].push_back(fast_ids[i]);
                                            });
                }
            });
            // Pushes of fast particles on slow ones, grouped by the slow particle (stable: in
            // the order of the fast particles).
            std::vector<std::pair<std::uint32_t, std::uint32_t>> pairs;
            for (std::size_t k = 0; k < fast_ids.size(); ++k)
                for (const std::uint32_t j : fast_nbrs[k])
                    if (j < m && !fast[j]) pairs.emplace_back(j, fast_ids[k]);
            std::stable_sort(pairs.begin(), pairs.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
            for (const auto& pr : pairs) ++extra_first[pr.first + 1];
            for (std::size_t p = 0; p < m; ++p) extra_first[p + 1] += extra_first[p];
            extra.resize(pairs.size());
            for (std::size_t k = 0; k < pairs.size(); ++k) extra[k] = pairs[k].second;
        }
        // Linear repulsion (eq. 2.2, 2.3), then back onto the tangent plane of the closest
        // original point (2.3.3). Jacobi update: every particle reads the previous positions.
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 512), [&](const auto& range) {
            for (std::size_t p = range.begin(); p != range.end(); ++p) {
                const Vec3f x = positions[p];
                const float r = radius[p], r2 = r * r;
                Vec3f force = Vec3f::Zero();
                const auto push = [&](std::uint32_t j) {
                    const Vec3f d = x - neighbor(j);
                    const float d2 = d.squaredNorm();
                    if (d2 <= r2) force += (r - std::sqrt(d2)) * d;
                };
                if (fast[p]) {
                    const std::size_t k = static_cast<std::size_t>(
                        std::lower_bound(fast_ids.begin(), fast_ids.end(), static_cast<std::uint32_t>(p)) - fast_ids.begin());
                    for (const std::uint32_t j : fast_nbrs[k]) push(j);
                } else {
                    if (fast_ids.empty())
                        for (std::uint32_t k = first[p]; k < first[p + 1]; ++k) push(nbr[k]);
                    else
                        for (std::uint32_t k = first[p]; k < first[p + 1]; ++k)
                            if (nbr[k] >= m || !fast[nbr[k]]) push(nbr[k]);
                    for (std::uint32_t k = extra_first[p]; k < extra_first[p + 1]; ++k) push(extra[k]);
                }
                // Step: a lone neighbour at distance d moves x by params.gain (r - d).
                Vec3f step = force * (gain / r);
                const float len = step.norm();
                const float max_step = static_cast<float>(kMaxStep) * r;
                if (len > max_step) step *= max_step / len;
                // The closest original point: the last one while the moved point stays within
                // half the last walk's margin of where that walk ended (the walk would not leave
                // it), else a new walk from it.
                const Vec3f y = x + step;
                if (!(2.0f * (y - walked_at[p]).norm() < walk_margin[p])) {
                    home[p] = WalkNearest(y, home[p], &walk_margin[p]);
                    walked_at[p] = y;
                }
                next[p] = OntoPlane(y, home[p]);
                step_len[p] = (next[p] - x).norm();
            }
        });
        positions.swap(next);
        double sum = 0.0;
        for (std::size_t p = 0; p < m; ++p) {
            sum += step_len[p];
            moved[p] = (positions[p] - built[p]).norm();
            radius[p] = static_cast<float>(r0 * scale_[home[p]]);
        }
        ++st.iterations;
        st.last_mean_step = sum / static_cast<double>(m) / r0;
        progress.Advance(0.85 / std::max(1, params.iterations));
        if (st.last_mean_step < params.tolerance) {
            progress.Advance(0.85 / std::max(1, params.iterations) * (params.iterations - iter - 1));
            break;
        }
    }

    // Final MLS projection (2.3.3); normals oriented like the closest original normal. With
    // cached fits: the MLS fit at each original point once (n fits rather than m projections),
    // every particle moved onto the polynomial of its closest original point; where that point
    // has no fit, the particle's own MLS projection.
    MlsOptions mls_options;
    mls_options.h =
        mls_h_ > 0.0f ? mls_h_ : 0.0f;  // 0 (fewer than 2 distinct points): MlsSurface says so
    const MlsSurface mls(input_, tree, mls_options);
    MlsSurface::Batch batch;
    std::vector<std::uint32_t> nearest(m);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 1024), [&](const auto& range) {
        for (std::size_t p = range.begin(); p != range.end(); ++p) nearest[p] = WalkNearest(positions[p], home[p]);
    });
    if (params.cached_fits) {
        std::vector<std::optional<MlsPatch>> patches(n);
        std::vector<std::uint8_t> used(n, 0);
        for (std::size_t p = 0; p < m; ++p) used[nearest[p]] = 1;
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 256), [&](const auto& range) {
            for (std::size_t i = range.begin(); i != range.end(); ++i)
                if (used[i]) patches[i] = mls.Fit(points[i]);
        });
        batch.positions.resize(m);
        batch.normals.resize(m);
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 1024), [&](const auto& range) {
            for (std::size_t p = range.begin(); p != range.end(); ++p) {
                const std::optional<MlsPatch>& patch = patches[nearest[p]];
                std::optional<MlsPoint> q = patch ? std::optional<MlsPoint>(patch->Project(positions[p])) : mls.Project(positions[p]);
                batch.positions[p] = q ? q->position : positions[p];
                batch.normals[p] = q ? q->normal : Vec3f::Zero();
            }
        });
    } else {
        batch = mls.ProjectAll(positions);
    }
    out_normals.resize(m);
    for (std::size_t p = 0; p < m; ++p) {
        const std::uint32_t q = nearest[p];
        const Vec3f& nq = Normal(q);
        Vec3f nrm = nq;
        if (batch.normals[p].allFinite() && batch.normals[p].squaredNorm() > 0.5f &&
            batch.positions[p].allFinite() && (batch.positions[p] - positions[p]).norm() < r0) {
            positions[p] = batch.positions[p];
            nrm = batch.normals[p].dot(nq) < 0 ? Vec3f(-batch.normals[p]) : batch.normals[p];
        }
        out_normals[p] = nrm;
    }
    progress.Advance(0.1);
}

}  // namespace surfel
