#include "surfel/surface/local_analysis.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <cmath>
#include <limits>
#include <numbers>
#include <memory>
#include <numeric>
#include <optional>
#include <utility>

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/spatial/neighbor_radii.h"
#include "surfel/surface/poly_fit.h"

namespace surfel {

float SpacingFromRadius(float r, int k) {
    return r > 0 ? static_cast<float>(std::sqrt(std::numbers::pi * double(r) * r / k)) : 0.0f;
}

namespace {
SamplingDensity DensityFromRadii(std::vector<float> radius, int k) {
    SamplingDensity d;
    const std::size_t n = radius.size();
    d.radius = std::move(radius);
    d.density.resize(n);
    d.spacing.resize(n);
    for (std::size_t i = 0; i < n; ++i) {
        const float r = d.radius[i];
        d.density[i] = r > 0 ? static_cast<float>(k / (std::numbers::pi * r * r)) : std::numeric_limits<float>::infinity();
        d.spacing[i] = SpacingFromRadius(r, k);
    }
    std::vector<float> s = d.spacing;
    std::nth_element(s.begin(), s.begin() + s.size() / 2, s.end());
    d.median_spacing = s[s.size() / 2];
    return d;
}

SamplingDensity ComputeSamplingDensity(std::span<const Vec3f> points, int k, const KdTree* tree) {
    SURFEL_CHECK(k > 0);
    if (points.size() < 2) return {};
    k = std::min<int>(k, static_cast<int>(points.size()) - 1);
    return DensityFromRadii(KthNeighborDistances(points, k, tree), k);
}
}  // namespace

SamplingDensity ComputeSamplingDensity(const KdTree& tree, int k, const ProgressFn& progress) {
    ProgressTracker tracker(progress, 1.0, "sampling density");
    SamplingDensity d = ComputeSamplingDensity(tree.points(), k, &tree);
    tracker.Advance(1.0);
    return d;
}

SamplingDensity ComputeSamplingDensity(std::span<const Vec3f> points, int k) {
    return ComputeSamplingDensity(points, k, nullptr);
}

float MedianSpacing(const SamplingDensity& density, std::size_t max_samples) {
    const std::size_t n = density.spacing.size();
    if (n < 2) return 0.0f;
    if (n <= max_samples || max_samples == 0) return density.median_spacing;
    const std::size_t stride = (n + max_samples - 1) / max_samples;
    std::vector<float> spacing;
    spacing.reserve(n / stride + 1);
    for (std::size_t i = 0; i < n; i += stride) spacing.push_back(density.spacing[i]);
    std::nth_element(spacing.begin(), spacing.begin() + spacing.size() / 2, spacing.end());
    return spacing[spacing.size() / 2];
}

float MedianSpacing(const KdTree& tree, int k, std::size_t max_samples) {
    const std::size_t n = tree.size();
    if (n < 2) return 0.0f;
    if (n <= max_samples || max_samples == 0) return ComputeSamplingDensity(tree, k).median_spacing;
    const std::size_t stride = (n + max_samples - 1) / max_samples;
    std::vector<Vec3f> queries;
    for (std::size_t i = 0; i < n; i += stride) queries.push_back(tree.points()[i]);
    const int kk = std::min<int>(k, static_cast<int>(n) - 1);
    const KnnTable knn = tree.KnnBatch(queries, kk + 1);  // the query point itself comes first
    std::vector<float> spacing(queries.size());
    for (std::size_t i = 0; i < queries.size(); ++i) {
        spacing[i] = SpacingFromRadius(std::sqrt(knn.Dist2(i)[kk]), kk);
    }
    std::nth_element(spacing.begin(), spacing.begin() + spacing.size() / 2, spacing.end());
    return spacing[spacing.size() / 2];
}

float DefaultScale(const SamplingDensity& density) { return 2.0f * density.median_spacing; }

float DefaultScale(const KdTree& tree) {
    const float h = DefaultScale(ComputeSamplingDensity(tree));
    if (!(h > 0.0f))
        throw Error(ErrorCode::kInvalidArgument,
                    "cannot derive a scale h from the cloud (fewer than 2 distinct points); pass h explicitly");
    return h;
}

CovarianceFrame AnalyzeNeighborhood(std::span<const Vec3f> points, std::span<const std::uint32_t> indices,
                                    std::span<const float> weights) {
    CovarianceFrame f;
    double wsum = 0;
    Vec3d c = Vec3d::Zero();
    for (std::size_t j = 0; j < indices.size(); ++j) {
        if (indices[j] == UINT32_MAX) continue;
        const double w = weights.empty() ? 1.0 : weights[j];
        c += w * points[indices[j]].cast<double>();
        wsum += w;
    }
    c /= std::max(wsum, 1e-300);
    Eigen::Matrix3d C = Eigen::Matrix3d::Zero();
    for (std::size_t j = 0; j < indices.size(); ++j) {
        if (indices[j] == UINT32_MAX) continue;
        const double w = weights.empty() ? 1.0 : weights[j];
        const Vec3d d = points[indices[j]].cast<double>() - c;
        C.noalias() += w * d * d.transpose();
    }
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
    es.computeDirect(C);
    f.centroid = c;
    f.normal = es.eigenvectors().col(0).normalized();
    f.eigenvalues = es.eigenvalues().cwiseMax(0.0);
    return f;
}

namespace {
std::size_t OrientOverGraph(std::span<const Vec3f> pts, std::vector<Vec3f>& normals, const KnnTable& knn, int kk,
                            float crossing_weight, std::size_t* flipped, const ProgressFn& progress,
                            detail::SpanningTrees method = detail::SpanningTrees::kAuto, bool* by_kruskal = nullptr);
}  // namespace

void NormalOptions::Validate() const {
    CheckRange("k", k, kMinNormalNeighbors, kMaxNormalNeighbors);
    CheckAtLeast("h", h, 0.0);
    CheckRange("orient_k", orient_k, kMinOrientNeighbors, kMaxOrientNeighbors);
    CheckRange("orient_crossing_weight", orient_crossing_weight, 0.0, kMaxOrientCrossingWeight);
}

Vec3f NormalAt(std::span<const Vec3f> pts, std::size_t i, std::span<const std::uint32_t> row,
               std::span<const float> dist2, const NormalOptions& opt, NormalScratch& scratch,
               float* variation) {
    const int k = static_cast<int>(row.size());
    std::vector<std::uint32_t>& idx = scratch.indices;
    std::vector<float>& w = scratch.weights;
    idx.resize(k + 1);
    w.resize(k + 1);
    idx[0] = static_cast<std::uint32_t>(i);
    std::copy_n(row.begin(), k, idx.begin() + 1);
    std::span<const float> weights;
    if (opt.weighted) {
        const float kth = std::sqrt(dist2[k - 1]);
        const float h = opt.h > 0 ? opt.h : std::max(kth * 0.5f, 1e-30f);
        w[0] = 1.0f;
        for (int j = 0; j < k; ++j) w[j + 1] = std::exp(-dist2[j] / (h * h));
        weights = w;
    }
    const CovarianceFrame f = AnalyzeNeighborhood(pts, idx, weights);
    Vec3d normal = f.normal;
    if (opt.refine && k >= 6) {
        const Vec3d p = pts[i].cast<double>();
        const LocalFrame frame = LocalFrame::FromNormal(p, f.normal);
        PolyFit fit(2, std::max(std::sqrt(double(dist2[k - 1])), 1e-30));
        for (int j = 0; j <= k; ++j) {
            const Vec3d l = frame.ToLocal(pts[idx[j]].cast<double>());
            fit.Add(l.x(), l.y(), l.z(), weights.empty() ? 1.0 : weights[j]);
        }
        PolyCoeffs g;
        if (fit.Solve(&g)) normal = frame.NormalAt(g, 0.0, 0.0);
    }
    if (variation) *variation = static_cast<float>(f.SurfaceVariation());
    return normal.cast<float>();
}

Vec3f EstimateNormalAt(const KdTree& tree, std::size_t i, const NormalOptions& opt,
                       NormalScratch& scratch, float* variation) {
    const std::size_t n = tree.size();
    SURFEL_CHECK(n >= 3 && i < n, "i = " << i << ", n = " << n);
    const int k = std::min<int>(opt.k, static_cast<int>(n) - 1);
    scratch.row.resize(k);
    scratch.dist2.resize(k);
    tree.KnnRow(i, k, scratch.row.data(), scratch.dist2.data(), scratch.neighbors);  // KnnAll(k)'s row
    return NormalAt(tree.points(), i, scratch.row, scratch.dist2, opt, scratch, variation);
}

NormalResult EstimateNormals(const KdTree& tree, const NormalOptions& opt, const ProgressFn& progress) {
    opt.Validate();
    const std::size_t n = tree.size();
    if (n < 3) throw Error(ErrorCode::kInvalidArgument, "normal estimation needs at least 3 points, got " + std::to_string(n));
    const int k = std::min<int>(opt.k, static_cast<int>(n) - 1);
    const KnnTable knn = tree.KnnAll(k, progress ? ProgressFn([&](double f) { return progress(0.4 * f); }) : ProgressFn{});
    return EstimateNormals(tree, knn, opt, progress);
}

NormalResult EstimateNormals(const KdTree& tree, const KnnTable& knn, const NormalOptions& opt,
                             const ProgressFn& progress) {
    opt.Validate();
    const std::size_t n = tree.size();
    NormalResult res;
    if (n < 3) throw Error(ErrorCode::kInvalidArgument, "normal estimation needs at least 3 points, got " + std::to_string(n));
    SURFEL_CHECK(knn.size() == n && knn.k > 0, knn.size() << " rows of " << knn.k << " neighbours for " << n << " points");
    const int k = std::min({opt.k, static_cast<int>(n) - 1, knn.k});
    res.normals.resize(n);
    res.surface_variation.resize(n);
    const auto pts = tree.points();
    ProgressTracker tracker(progress ? ProgressFn([&](double f) { return progress(0.4 + 0.3 * f); }) : ProgressFn{},
                            static_cast<double>(n), "normal estimation");
    tbb::parallel_for(
        tbb::blocked_range<std::size_t>(0, n, 2048), [&](const tbb::blocked_range<std::size_t>& r) {
            NormalScratch scratch;
            for (std::size_t i = r.begin(); i != r.end(); ++i) {
                float variation = 0.0f;
                res.normals[i] = NormalAt(pts, i, knn.Row(i).first(k), knn.Dist2(i).first(k), opt,
                                          scratch, &variation);
                res.surface_variation[i] = variation;
            }
            tracker.Advance(static_cast<double>(r.size()));
        });
    if (opt.orient) {
        const ProgressFn hook = progress ? ProgressFn([&](double f) { return progress(0.7 + 0.3 * f); }) : ProgressFn{};
        const int kk = std::max(1, std::min<int>(opt.orient_k, static_cast<int>(n) - 1));
        // The orientation graph's neighbours are the first orient_k of the k already found.
        res.components = kk <= k ? OrientOverGraph(pts, res.normals, knn, kk, opt.orient_crossing_weight, &res.flipped, hook)
                                 : OrientNormals(tree, res.normals, opt, &res.flipped, hook);
    }
    return res;
}

namespace {

// The seed vote (OutwardVote): points per direction, and the mean vote per direction below which
// the component counts as flat.
constexpr std::size_t kSeedVotePoints = 8;
constexpr double kSeedVoteTie = 0.05;

// The directions the seed vote looks along: the 26 of the cube's faces, edges and corners.
std::array<Vec3d, 26> VoteDirections() {
    std::array<Vec3d, 26> dirs;
    std::size_t m = 0;
    for (int x = -1; x <= 1; ++x)
        for (int y = -1; y <= 1; ++y)
            for (int z = -1; z <= 1; ++z)
                if (x != 0 || y != 0 || z != 0) dirs[m++] = Vec3d(x, y, z).normalized();
    return dirs;
}

// Outward vote of one consistently oriented component (the seed rule of OrientNormals): > 0
// keeps its normals, < 0 turns them all over. Where a closed surface is extremal in a direction
// d, its outward normal is d, so each of the 26 directions votes with the mean of n . d over the
// component's kSeedVotePoints most extremal points in d. A single extremal point is not safe:
// the normal at the top of a thin feature (an ear, a fin, a spike of noise) lies nearly in the
// tangent plane, and its sign is what propagated there through the feature. Many directions and
// several points per direction outvote such points. A vote weaker than kSeedVoteTie per
// direction (a flat or nearly flat open sheet, whose votes along d and -d cancel) falls back to
// CGAL's rule (mst_orient_normals): the normal at the point of largest z points up.
// `negated` says which of `normals` stand turned over.
double OutwardVote(std::span<const Vec3f> pts, std::span<const Vec3f> normals, std::span<const std::uint8_t> negated,
                   std::span<const std::uint32_t> comp, std::uint32_t top) {
    const auto normal = [&](std::uint32_t i) -> Vec3f { return negated[i] ? Vec3f(-normals[i]) : normals[i]; };
    static const std::array<Vec3d, 26> kDirections = VoteDirections();
    const std::size_t m = std::min<std::size_t>(kSeedVotePoints, comp.size());
    // Per direction, the m least (height, index) pairs in increasing order — what a partial_sort
    // of every pair gives (the pairs are distinct) — in one pass over the points for all
    // directions, each kept sorted by insertion: most heights fail the one comparison with their
    // direction's m-th (26 partial_sorts were 29 M of the orientation's serial instructions on
    // the bunny, 26 passes 25 M). A large component's points are split between the threads and
    // the parts' lists merged by the same insertion: the m least of the union, whatever the split.
    constexpr std::size_t kDirs = std::tuple_size_v<decltype(kDirections)>;
    struct Least {
        std::array<std::array<std::pair<double, std::uint32_t>, kSeedVotePoints>, kDirs> l;
        std::array<std::size_t, kDirs> filled{};
        void Insert(std::size_t k, const std::pair<double, std::uint32_t>& h, std::size_t m) {
            auto& lk = l[k];
            if (filled[k] < m) ++filled[k];
            else if (!(h < lk[m - 1])) return;
            std::size_t s = filled[k] - 1;  // the new slot, or the m-th (dropped) when full
            for (; s > 0 && h < lk[s - 1]; --s) lk[s] = lk[s - 1];
            lk[s] = h;
        }
    };
    const auto add = [&](Least& least, std::span<const std::uint32_t> part) {
        for (const std::uint32_t i : part) {
            const Vec3d p = pts[i].cast<double>();
            for (std::size_t k = 0; k < kDirs; ++k) least.Insert(k, {-p.dot(kDirections[k]), i}, m);
        }
    };
    constexpr std::size_t kVoteGrain = 16384;  // points per part (the bunny's ~35 k: two parts)
    Least least;
    if (comp.size() < 2 * kVoteGrain) {
        add(least, comp);
    } else {
        least = tbb::parallel_reduce(
            tbb::blocked_range<std::size_t>(0, comp.size(), kVoteGrain), Least{},
            [&](const tbb::blocked_range<std::size_t>& r, Least part) {
                add(part, comp.subspan(r.begin(), r.size()));
                return part;
            },
            [&](Least a, const Least& b) {
                for (std::size_t k = 0; k < kDirs; ++k)
                    for (std::size_t j = 0; j < b.filled[k]; ++j) a.Insert(k, b.l[k][j], m);
                return a;
            });
    }
    double vote = 0;
    for (std::size_t k = 0; k < kDirs; ++k) {
        double sum = 0;
        for (std::size_t j = 0; j < m; ++j) sum += normal(least.l[k][j].second).cast<double>().dot(kDirections[k]);
        vote += sum / static_cast<double>(m);
    }
    if (std::abs(vote) >= kSeedVoteTie * static_cast<double>(kDirections.size())) return vote;
    return normal(top).z();
}

// A connected component of the orientation graph.
struct Comp {
    std::uint32_t top = UINT32_MAX;  // the tree's root: the point of largest z (the first such)
    std::uint32_t first = 0, count = 0;  // its points: members[first, first + count)
};

// The components' roots (tops) and sizes and their points in index order (a counting sort by
// component), from each point's component number `comp_of` (0..count - 1).
std::vector<Comp> ComponentsOf(std::span<const Vec3f> pts, std::span<const std::uint32_t> comp_of, std::size_t count,
                               std::vector<std::uint32_t>& members) {
    const std::size_t n = pts.size();
    std::vector<Comp> comps(count);
    for (std::size_t i = 0; i < n; ++i) {
        Comp& c = comps[comp_of[i]];
        ++c.count;
        if (c.top == UINT32_MAX || pts[i].z() > pts[c.top].z()) c.top = static_cast<std::uint32_t>(i);
    }
    members.resize(n);
    std::uint32_t offset = 0;
    for (Comp& c : comps) {
        c.first = offset;
        offset += c.count;
    }
    std::vector<std::uint32_t> next(comps.size());
    for (std::size_t c = 0; c < comps.size(); ++c) next[c] = comps[c].first;
    for (std::size_t i = 0; i < n; ++i) members[next[comp_of[i]]++] = static_cast<std::uint32_t>(i);
    return comps;
}

// The end of both orientations: each component's vote (OutwardVote) on the signs its tree gave,
// then the turned normals negated. Returns the number of components.
std::size_t FinishOrientation(std::span<const Vec3f> pts, std::vector<Vec3f>& normals, std::vector<std::uint8_t>& negated,
                              std::span<const Comp> comps, std::span<const std::uint32_t> members, std::size_t* flipped) {
    for (const Comp& c : comps) {
        const std::span<const std::uint32_t> comp(members.data() + c.first, c.count);
        if (OutwardVote(pts, normals, negated, comp, c.top) < 0)
            for (std::uint32_t i : comp) negated[i] ^= 1;
    }
    const std::size_t n = pts.size();
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 16384), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i)
            if (negated[i]) normals[i] = -normals[i];
    });
    std::size_t flips = 0;
    for (std::uint8_t f : negated) flips += f;
    if (flipped) *flipped = flips;
    return comps.size();
}

// The orientation graph's edge {u, v}: Hoppe's cost 1 - |ni . nj| plus the edge's tilt out of the
// two tangent planes (an edge across a thin part joins antiparallel normals, which the plain cost
// finds cheapest), and the sign of the estimates' ni . nj (1 negative, 2 positive, 0 neither).
// Neither depends on the normals' signs, which the propagation changes, nor on the order of u and
// v: the edge negated is exact, products commute and each sum keeps its order.
struct EdgeCost {
    float cost;
    std::uint8_t sign;
};
inline EdgeCost CostOf(std::span<const Vec3f> pts, std::span<const Vec3f> normals, std::uint32_t u, std::uint32_t v,
                       float crossing_weight) {
    const Vec3f edge = pts[v] - pts[u];
    const float len = edge.norm();
    const float tilt = len > 0 ? 0.5f * (std::abs(edge.dot(normals[u])) + std::abs(edge.dot(normals[v]))) / len : 0.0f;
    const float dot = normals[u].dot(normals[v]);
    return {1.0f - std::abs(dot) + crossing_weight * tilt, static_cast<std::uint8_t>(dot < 0 ? 1 : dot > 0 ? 2 : 0)};
}

// The orientation by Kruskal's algorithm over the edges sorted in parallel, when it gives the
// normals of Prim's trees; std::nullopt when it cannot tell (then OrientOverGraph runs Prim's).
//
// Prim's algorithm (OrientOverGraph) takes, at each step, a least-cost edge out of the tree, ties
// broken by the points' indices as seen from the tree, which is no order on the edges: with ties
// its tree is one of several minimum spanning trees. A minimum spanning forest is unique when no
// two spanning forests of least cost exist, and every algorithm then finds it; Kruskal's tells:
// over the edges in increasing cost, a group of equal costs has more than one choice exactly when
// one of its edges that joined two components at the group's start closes a cycle once others of
// the group are in (`swappable`). Without such edges the forest is Prim's, edge for edge, and so
// are the trees rooted at the same tops and the signs propagated along them. With them, the least
// forests are those that swap such edges for tree edges of their cost on their cycles; if each of
// them agrees with the signs propagated here (the oriented normals' dot product along it is
// positive) and no tree edge has a sign of 0 (whose rule resets rather than follows), the signs
// along every least forest's paths change alike, so Prim's forest, whichever it is, gives these
// normals; otherwise this returns std::nullopt. (Scans have such ties: flat regions with equal
// normals; 579,461 swappable edges in person_scan.ply, all agreeing.) The costs come per k-neighbour
// entry (`kcost`, `ksign`, finite). The sort and the edges run in parallel; what stays serial is
// the union-find over the sorted edges and the walk over the n - components tree edges, a fraction
// of Prim's heap (on the bunny about 3.5 of its ~25-30 ms).
std::optional<std::size_t> OrientByKruskal(std::span<const Vec3f> pts, std::vector<Vec3f>& normals, const KnnTable& knn,
                                           std::size_t cols, std::span<const float> kcost,
                                           std::span<const std::uint8_t> ksign, std::size_t* flipped,
                                           const ProgressFn& progress) {
    const std::size_t n = pts.size();
    auto row = [&](std::size_t i) { return knn.Row(i).first(cols); };
    // Each undirected edge once: from the row of i for j, unless j's row holds i too and j < i.
    const auto emits = [&](std::uint32_t i, std::uint32_t j) {
        if (j == UINT32_MAX || j == i) return false;
        if (i < j) return true;
        const auto rj = row(j);
        return std::find(rj.begin(), rj.end(), i) == rj.end();
    };
    struct Edge {
        float cost;
        std::uint32_t lo, hi;
        std::uint8_t sign;
    };
    // The edges of each block of rows in one pass, the blocks' lists then joined in order.
    constexpr std::size_t kRows = 2048;
    const std::size_t blocks = (n + kRows - 1) / kRows;
    std::vector<std::vector<Edge>> part(blocks);
    tbb::parallel_for(std::size_t(0), blocks, [&](std::size_t b) {
        std::vector<Edge>& out = part[b];
        out.reserve(kRows * cols);
        for (std::size_t i = b * kRows; i < std::min(n, (b + 1) * kRows); ++i)
            for (std::size_t c = 0; c < cols; ++c) {
                const auto u = static_cast<std::uint32_t>(i);
                const std::uint32_t j = row(i)[c];
                if (emits(u, j)) out.push_back({kcost[i * cols + c], std::min(u, j), std::max(u, j), ksign[i * cols + c]});
            }
    });
    // The cheapest eighth first (costs up to a threshold t from a sample), then the rest: Kruskal's
    // over the first part alone finds the ties of scans (equal costs on a regular grid, usually
    // among the cheapest edges) after sorting an eighth of the edges; the rest, all dearer than t,
    // follows in the same order as one sort would give.
    std::size_t m = 0;
    std::vector<float> sample;
    for (const auto& p : part) {
        m += p.size();
        for (std::size_t e = 0; e < p.size(); e += 16) sample.push_back(p[e].cost);
    }
    float t = std::numeric_limits<float>::infinity();
    if (sample.size() >= 64) {
        std::nth_element(sample.begin(), sample.begin() + sample.size() / 8, sample.end());
        t = sample[sample.size() / 8];
    }
    std::vector<std::size_t> low_at(blocks + 1, 0), high_at(blocks + 1, 0);
    tbb::parallel_for(std::size_t(0), blocks, [&](std::size_t b) {
        std::size_t c = 0;
        for (const Edge& e : part[b]) c += e.cost <= t;
        low_at[b + 1] = c;
        high_at[b + 1] = part[b].size() - c;
    });
    for (std::size_t b = 0; b < blocks; ++b) low_at[b + 1] += low_at[b], high_at[b + 1] += high_at[b];
    const std::size_t m_low = low_at[blocks];
    // Left uninitialised (a vector's zeroing, 16 bytes an edge, was one thread's page faults): the
    // split and each pass write every entry, in parallel.
    std::unique_ptr<Edge[]> edges(new Edge[m]), other(new Edge[m]);
    tbb::parallel_for(std::size_t(0), blocks, [&](std::size_t b) {
        Edge* low = edges.get() + low_at[b];
        Edge* high = edges.get() + m_low + high_at[b];
        for (const Edge& e : part[b]) *(e.cost <= t ? low++ : high++) = e;
        std::vector<Edge>().swap(part[b]);
    });
    // Sorted by cost: a stable radix sort of the costs' order-preserving bit patterns (11, 11 and
    // 10 bits, least significant first), so equal costs keep the blocks' order: the same whatever
    // the thread count. (Which of several equal costs comes first does not change the forest where
    // the check below lets it stand.) -0 and +0 are neighbours in this order, as equal as floats.
    // Each pass counts and moves fixed chunks of edges in parallel; the result lands in `to`.
    const auto key = [](float c) {
        const std::uint32_t bits = std::bit_cast<std::uint32_t>(c);
        return bits & 0x80000000u ? ~bits : bits | 0x80000000u;
    };
    const auto sort = [&](Edge* from, Edge* to, std::size_t size) {
        constexpr std::size_t kDigits = 2048, kChunk = 16384;
        const std::size_t chunks = (size + kChunk - 1) / kChunk;
        std::vector<std::uint32_t> bucket(chunks * kDigits);  // per chunk, each digit's next slot
        Edge* src = from;
        Edge* dst = to;
        for (const int shift : {0, 11, 22}) {
            const auto digit = [&](const Edge& e) { return (key(e.cost) >> shift) & (kDigits - 1); };
            tbb::parallel_for(std::size_t(0), chunks, [&](std::size_t c) {
                std::uint32_t* count = bucket.data() + c * kDigits;
                std::fill(count, count + kDigits, 0u);
                for (std::size_t e = c * kChunk; e < std::min(size, (c + 1) * kChunk); ++e) ++count[digit(src[e])];
            });
            std::uint32_t sum = 0;
            for (std::size_t d = 0; d < kDigits; ++d)
                for (std::size_t c = 0; c < chunks; ++c) sum += std::exchange(bucket[c * kDigits + d], sum);
            tbb::parallel_for(std::size_t(0), chunks, [&](std::size_t c) {
                std::uint32_t* next = bucket.data() + c * kDigits;
                for (std::size_t e = c * kChunk; e < std::min(size, (c + 1) * kChunk); ++e) dst[next[digit(src[e])]++] = src[e];
            });
            std::swap(src, dst);
        }
        return src;  // three passes: `to`
    };

    // Kruskal's, with the check of each group of equal costs.
    std::vector<std::uint32_t> parent(n), rank(n, 0);
    std::iota(parent.begin(), parent.end(), 0u);
    const auto find = [&](std::uint32_t x) {
        while (parent[x] != x) x = parent[x] = parent[parent[x]];
        return x;
    };
    const auto unite = [&](std::uint32_t a, std::uint32_t b) {  // roots a != b
        if (rank[a] < rank[b]) std::swap(a, b);
        parent[b] = a;
        rank[a] += rank[a] == rank[b];
    };
    std::vector<Edge> tree;
    tree.reserve(n);
    std::vector<std::uint8_t> useful;
    // The edges of a group of equal costs that joined two components at the group's start but
    // closed a cycle when their turn came: each could replace a tree edge of its cost on that cycle
    // (another least forest, which Prim's tie-break may have picked).
    std::vector<Edge> swappable;
    // Over sorted[0, size): false when a group of equal costs has a choice with a sign of 0.
    const auto kruskal = [&](const Edge* sorted, std::size_t size) {
        for (std::size_t a = 0; a < size && tree.size() + 1 < n;) {  // n - 1 edges: one tree, done
            std::size_t b = a + 1;
            while (b < size && sorted[b].cost == sorted[a].cost) ++b;
            if (b == a + 1) {
                const std::uint32_t x = find(sorted[a].lo), y = find(sorted[a].hi);
                if (x != y) {
                    unite(x, y);
                    tree.push_back(sorted[a]);
                }
            } else {
                useful.assign(b - a, 0);
                for (std::size_t e = a; e < b; ++e) useful[e - a] = find(sorted[e].lo) != find(sorted[e].hi);
                for (std::size_t e = a; e < b; ++e) {
                    if (!useful[e - a]) continue;
                    const std::uint32_t x = find(sorted[e].lo), y = find(sorted[e].hi);
                    if (x == y) {  // two least forests: checked once the signs are known
                        if (sorted[e].sign == 0) return false;
                        swappable.push_back(sorted[e]);
                        continue;
                    }
                    unite(x, y);
                    tree.push_back(sorted[e]);
                }
            }
            a = b;
        }
        return true;
    };
    if (!kruskal(sort(edges.get(), other.get(), m_low), m_low)) return std::nullopt;
    if (tree.size() + 1 < n && !kruskal(sort(edges.get() + m_low, other.get() + m_low, m - m_low), m - m_low))
        return std::nullopt;
    edges.reset();
    other.reset();

    // The components, numbered in the order of their least point (as OrientOverGraph's search).
    std::vector<std::uint32_t> comp_of(n), id_of_root(n, UINT32_MAX);
    std::size_t count = 0;
    for (std::size_t i = 0; i < n; ++i) {
        std::uint32_t& id = id_of_root[find(static_cast<std::uint32_t>(i))];
        if (id == UINT32_MAX) id = static_cast<std::uint32_t>(count++);
        comp_of[i] = id;
    }
    std::vector<std::uint32_t> members;
    const std::vector<Comp> comps = ComponentsOf(pts, comp_of, count, members);

    // The forest's adjacency, then each tree walked from its top: a point's sign follows its parent's
    // as Prim's propagation turns it (normals[from] . normals[to] < 0, by the estimates' sign).
    std::vector<std::uint32_t> start(n + 1, 0);
    for (const Edge& e : tree) ++start[e.lo + 1], ++start[e.hi + 1];
    for (std::size_t i = 0; i < n; ++i) start[i + 1] += start[i];
    struct Link {
        std::uint32_t to;
        std::uint8_t sign;
    };
    std::vector<Link> links(start[n]);
    {
        std::vector<std::uint32_t> fill(start.begin(), start.end() - 1);
        for (const Edge& e : tree) {
            links[fill[e.lo]++] = {e.hi, e.sign};
            links[fill[e.hi]++] = {e.lo, e.sign};
        }
    }
    std::vector<std::uint8_t> negated(n, 0), seen(n, 0);
    std::vector<std::uint32_t> queue;
    queue.reserve(n);
    for (const Comp& c : comps) {
        seen[c.top] = 1;
        queue.assign(1, c.top);
        for (std::size_t q = 0; q < queue.size(); ++q) {
            const std::uint32_t u = queue[q];
            const std::uint8_t turn = negated[u] ? 2 : 1;
            for (std::uint32_t l = start[u]; l < start[u + 1]; ++l) {
                const Link& k = links[l];
                if (seen[k.to]) continue;
                seen[k.to] = 1;
                negated[k.to] = k.sign == turn;
                queue.push_back(k.to);
            }
        }
    }
    // Where least forests are several, the signs still are the same in all of them when every edge
    // that could swap in agrees with these signs (the oriented normals' dot product along it
    // positive) and no tree edge has a sign of 0: the signs along any least forest's path then
    // change as along this one's, so Prim's forest gives these signs too. Otherwise Prim's runs.
    if (!swappable.empty()) {
        for (const Edge& e : tree)
            if (e.sign == 0) return std::nullopt;
        for (const Edge& e : swappable)
            if ((e.sign == 1) != (negated[e.lo] != negated[e.hi])) return std::nullopt;
    }
    ProgressTracker tracker(progress, 1.0, "normal orientation");
    tracker.Advance(1.0);
    return FinishOrientation(pts, normals, negated, comps, members, flipped);
}

// Orientation over the graph of the first kk columns of `knn` (rows sorted by distance): Kruskal's
// in parallel where it gives Prim's trees (OrientByKruskal), Prim's otherwise or when asked.
std::size_t OrientOverGraph(std::span<const Vec3f> pts, std::vector<Vec3f>& normals, const KnnTable& knn, int kk,
                            float crossing_weight, std::size_t* flipped, const ProgressFn& progress,
                            detail::SpanningTrees method, bool* by_kruskal) {
    const std::size_t n = pts.size();
    if (flipped) *flipped = 0;
    if (by_kruskal) *by_kruskal = false;
    if (n == 0) return 0;
    const std::size_t cols = static_cast<std::size_t>(std::min(kk, knn.k));
    auto row = [&](std::size_t i) { return knn.Row(i).first(cols); };
    // Each graph edge's cost and sign (CostOf), once per k-neighbour entry, in parallel, for both
    // algorithms (an edge's two adjacency entries share the entry's values: CostOf is symmetric).
    // The propagation's test of the signed normals' dot product is the sign, reversed where `from`
    // stands turned over (a negation is exact), so the serial loops read no normal.
    std::vector<float> kcost(knn.size() * cols);
    std::vector<std::uint8_t> ksign(knn.size() * cols);
    std::atomic<bool> finite{true};
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, knn.size(), 1024), [&](const tbb::blocked_range<std::size_t>& r) {
        bool ok = true;
        for (std::size_t i = r.begin(); i != r.end(); ++i)
            for (std::size_t c = 0; c < cols; ++c) {
                const std::uint32_t j = row(i)[c];
                if (j == UINT32_MAX) continue;
                const EdgeCost e = CostOf(pts, normals, static_cast<std::uint32_t>(i), j, crossing_weight);
                kcost[i * cols + c] = e.cost;
                ksign[i * cols + c] = e.sign;
                ok = ok && std::isfinite(e.cost);
            }
        if (!ok) finite.store(false, std::memory_order_relaxed);
    });
    if (method == detail::SpanningTrees::kAuto && finite.load()) {
        if (const auto comps = OrientByKruskal(pts, normals, knn, cols, kcost, ksign, flipped, progress)) {
            if (by_kruskal) *by_kruskal = true;
            return *comps;
        }
    }

    // Symmetric adjacency (CSR) of the k-neighbour graph.
    std::vector<std::uint32_t> degree(n + 1, 0);
    for (std::size_t i = 0; i < knn.size(); ++i)
        for (auto j : row(i))
            if (j != UINT32_MAX) {
                ++degree[i];
                ++degree[j];
            }
    std::vector<std::uint32_t> start(n + 1, 0);
    for (std::size_t i = 0; i < n; ++i) start[i + 1] = start[i] + degree[i];
    std::vector<std::uint32_t> adj(start[n]);
    std::vector<float> edge_cost(adj.size());
    std::vector<std::uint8_t> edge_sign(adj.size());
    std::vector<std::uint32_t> fill(start.begin(), start.end() - 1);
    for (std::size_t i = 0; i < knn.size(); ++i)
        for (std::size_t c = 0; c < cols; ++c) {
            const std::uint32_t j = row(i)[c];
            if (j == UINT32_MAX) continue;
            const float cost = kcost[i * cols + c];
            const std::uint8_t sign = ksign[i * cols + c];
            edge_cost[fill[i]] = cost, edge_sign[fill[i]] = sign;
            adj[fill[i]++] = j;
            edge_cost[fill[j]] = cost, edge_sign[fill[j]] = sign;
            adj[fill[j]++] = static_cast<std::uint32_t>(i);
        }

    // Connected components, numbered in the order of their least point (a search from each point
    // not yet reached, in index order: each adjacency entry read once; the union-find it replaces
    // numbered them the same way, its roots being each set's least point, at 19 M instructions on
    // the bunny against ~5), then each component's root (top) and size.
    std::vector<std::uint32_t> comp_of(n, UINT32_MAX);
    std::size_t count = 0;
    {
        std::vector<std::uint32_t> stack;
        for (std::size_t i = 0; i < n; ++i) {
            if (comp_of[i] != UINT32_MAX) continue;
            const auto id = static_cast<std::uint32_t>(count++);
            comp_of[i] = id;
            stack.assign(1, static_cast<std::uint32_t>(i));
            while (!stack.empty()) {
                const std::uint32_t u = stack.back();
                stack.pop_back();
                for (std::uint32_t e = start[u]; e < start[u + 1]; ++e)
                    if (comp_of[adj[e]] == UINT32_MAX) {
                        comp_of[adj[e]] = id;
                        stack.push_back(adj[e]);
                    }
            }
        }
    }
    std::vector<std::uint32_t> members;
    const std::vector<Comp> comps = ComponentsOf(pts, comp_of, count, members);

    // Prim's algorithm from each root, cost 1 - |ni . nj| + w tilt; ties broken by index (deterministic).
    // The frontier is an indexed heap of points keyed by (best cost, index), each point once, its
    // key lowered when a cheaper edge reaches it: the order of a heap of every improving edge
    // (cost, to, from) with stale entries skipped, since a point's least entry is its best edge
    // and `to` is unique per point, with a fraction of the heap traffic.
    // Each point's frontier state in one record (one cache line touched per edge instead of four
    // arrays' lines: the propagation's reads are random over the points).
    struct Frontier {
        float best = std::numeric_limits<float>::infinity();  // least cost of an edge from the tree
        std::uint32_t from = UINT32_MAX;                      // that edge's tree end
        std::uint32_t slot = UINT32_MAX;                      // the point's place in `heap`
        std::uint8_t visited = 0;                             // in the tree
        std::uint8_t sign = 0;  // of the estimates' ni . nj along that edge: 1 negative, 2 positive, 0 neither
    };
    std::vector<Frontier> state(n);
    // The heap holds each entry's key beside its point, so that its comparisons read no
    // per-point array.
    struct Entry {
        float best;
        std::uint32_t v;
        bool operator<(const Entry& o) const { return best < o.best || (best == o.best && v < o.v); }
    };
    std::vector<Entry> heap;  // a binary min-heap by (best, index)
    const auto place = [&](std::size_t i, const Entry& x) {
        heap[i] = x;
        state[x.v].slot = static_cast<std::uint32_t>(i);
    };
    const auto sift_up = [&](std::size_t i, const Entry x) {
        while (i > 0) {
            const std::size_t up = (i - 1) / 2;
            if (!(x < heap[up])) break;
            place(i, heap[up]);
            i = up;
        }
        place(i, x);
    };
    const auto pop = [&] {
        const std::uint32_t top = heap[0].v;
        state[top].slot = UINT32_MAX;
        const Entry x = heap.back();
        heap.pop_back();
        if (!heap.empty()) {
            std::size_t i = 0;
            const std::size_t size = heap.size();
            for (;;) {
                std::size_t c = 2 * i + 1;
                if (c >= size) break;
                if (c + 1 < size && heap[c + 1] < heap[c]) ++c;
                if (!(heap[c] < x)) break;
                place(i, heap[c]);
                i = c;
            }
            place(i, x);
        }
        return top;
    };
    ProgressTracker tracker(progress, static_cast<double>(n), "normal orientation");
    std::size_t done = 0;
    auto push_edges = [&](std::uint32_t u) {
        for (std::uint32_t e = start[u]; e < start[u + 1]; ++e) {
            const std::uint32_t v = adj[e];
            Frontier& f = state[v];
            if (f.visited) continue;
            const float cost = edge_cost[e];
            if (cost < f.best || (cost == f.best && u < f.from)) {
                f.best = cost;
                f.from = u;
                f.sign = edge_sign[e];
                if (f.slot == UINT32_MAX) {
                    heap.emplace_back();
                    sift_up(heap.size() - 1, Entry{cost, v});
                } else {
                    sift_up(f.slot, Entry{cost, v});  // a lower key (or the same key from a lower `from`)
                }
            }
        }
    };
    std::vector<std::uint8_t> negated(n, 0);  // whether normal i ends opposite to its estimate
    for (const Comp& c : comps) {
        // Propagation along the tree from the root, taking the root's sign as estimated; the
        // component's sign is settled afterwards by the vote (the tree does not depend on signs,
        // so this equals seeding the root with the sign the vote picks).
        const std::uint32_t root = c.top;
        state[root].visited = 1;
        push_edges(root);
        while (!heap.empty()) {
            const std::uint32_t to = pop();
            Frontier& t = state[to];
            t.visited = 1;
            // normals[from] . normals[to] < 0, normals[to] not yet turned
            if (t.sign == (negated[t.from] ? 2 : 1)) negated[to] = 1;
            push_edges(to);
            if ((++done & 0xFFFF) == 0) tracker.Advance(65536.0);
        }
    }
    return FinishOrientation(pts, normals, negated, comps, members, flipped);
}

}  // namespace

std::size_t OrientNormals(const KdTree& tree, std::vector<Vec3f>& normals, const NormalOptions& options,
                          std::size_t* flipped, const ProgressFn& progress) {
    options.Validate();
    const std::size_t n = tree.size();
    const int kk = std::max(1, std::min<int>(options.orient_k, static_cast<int>(n) - 1));
    return OrientNormals(tree.points(), n > 1 ? tree.KnnAll(kk) : KnnTable{}, normals, options, flipped, progress);
}

std::size_t OrientNormals(std::span<const Vec3f> points, const KnnTable& knn, std::vector<Vec3f>& normals,
                          const NormalOptions& options, std::size_t* flipped, const ProgressFn& progress) {
    options.Validate();
    const std::size_t n = points.size();
    SURFEL_CHECK(normals.size() == n, normals.size() << " normals for " << n << " points");
    const int kk = std::max(1, std::min<int>(options.orient_k, static_cast<int>(n) - 1));
    if (n <= 1) return OrientOverGraph(points, normals, KnnTable{}, kk, options.orient_crossing_weight, flipped, progress);
    SURFEL_CHECK(knn.size() == n && knn.k >= kk,
                 knn.size() << " rows of " << knn.k << " neighbours for " << n << " points, orient_k " << kk);
    return OrientOverGraph(points, normals, knn, kk, options.orient_crossing_weight, flipped, progress);
}

std::size_t detail::OrientNormals(const KdTree& tree, std::vector<Vec3f>& normals, const NormalOptions& options,
                                  SpanningTrees method, std::size_t* flipped, bool* by_kruskal) {
    options.Validate();
    const std::size_t n = tree.size();
    SURFEL_CHECK(normals.size() == n, normals.size() << " normals for " << n << " points");
    const int kk = std::max(1, std::min<int>(options.orient_k, static_cast<int>(n) - 1));
    const KnnTable knn = n > 1 ? tree.KnnAll(kk) : KnnTable{};
    return OrientOverGraph(tree.points(), normals, knn, kk, options.orient_crossing_weight, flipped, {}, method,
                           by_kruskal);
}

std::vector<float> NormalVariation(const KdTree& tree, std::span<const Vec3f> normals, int k) {
    const std::size_t n = tree.size();
    SURFEL_CHECK(normals.size() == n);
    std::vector<float> out(n, 0.0f);
    if (n < 2) return out;
    const KnnTable knn = tree.KnnAll(std::min<int>(k, static_cast<int>(n) - 1));
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 2048), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i) {
            Eigen::Matrix3d C = normals[i].cast<double>() * normals[i].cast<double>().transpose();
            for (auto j : knn.Row(i))
                if (j != UINT32_MAX) C += normals[j].cast<double>() * normals[j].cast<double>().transpose();
            Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
            es.computeDirect(C / static_cast<double>(knn.k + 1));
            out[i] = static_cast<float>(es.eigenvalues()[1]);
        }
    });
    return out;
}

}  // namespace surfel
