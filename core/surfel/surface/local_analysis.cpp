#include "surfel/surface/local_analysis.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <numbers>
#include <numeric>

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
                            float crossing_weight, std::size_t* flipped, const ProgressFn& progress);
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

// Orientation over the graph of the first kk columns of `knn` (rows sorted by distance).
std::size_t OrientOverGraph(std::span<const Vec3f> pts, std::vector<Vec3f>& normals, const KnnTable& knn, int kk,
                            float crossing_weight, std::size_t* flipped, const ProgressFn& progress) {
    const std::size_t n = pts.size();
    if (flipped) *flipped = 0;
    if (n == 0) return 0;
    auto row = [&](std::size_t i) { return knn.Row(i).first(static_cast<std::size_t>(std::min(kk, knn.k))); };

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
    std::vector<std::uint32_t> fill(start.begin(), start.end() - 1);
    for (std::size_t i = 0; i < knn.size(); ++i)
        for (auto j : row(i))
            if (j != UINT32_MAX) {
                adj[fill[i]++] = j;
                adj[fill[j]++] = static_cast<std::uint32_t>(i);
            }

    // Connected components, numbered in the order of their least point (a search from each point
    // not yet reached, in index order: each adjacency entry read once; the union-find it replaces
    // numbered them the same way, its roots being each set's least point, at 19 M instructions on
    // the bunny against ~5), then each component's root (top) and size.
    struct Comp {
        std::uint32_t top = UINT32_MAX;  // the tree's root: the point of largest z
        std::uint32_t first = 0, count = 0;  // its points: members[first, first + count)
    };
    std::vector<std::uint32_t> comp_of(n, UINT32_MAX);
    std::vector<Comp> comps;
    {
        std::vector<std::uint32_t> stack;
        for (std::size_t i = 0; i < n; ++i) {
            if (comp_of[i] != UINT32_MAX) continue;
            const auto id = static_cast<std::uint32_t>(comps.size());
            comps.emplace_back();
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
    for (std::size_t i = 0; i < n; ++i) {
        Comp& c = comps[comp_of[i]];
        ++c.count;
        if (c.top == UINT32_MAX || pts[i].z() > pts[c.top].z()) c.top = static_cast<std::uint32_t>(i);
    }
    // The points of each component, in index order (a counting sort by component).
    std::vector<std::uint32_t> members(n);
    {
        std::uint32_t offset = 0;
        for (Comp& c : comps) {
            c.first = offset;
            offset += c.count;
        }
        std::vector<std::uint32_t> next(comps.size());
        for (std::size_t c = 0; c < comps.size(); ++c) next[c] = comps[c].first;
        for (std::size_t i = 0; i < n; ++i) members[next[comp_of[i]]++] = static_cast<std::uint32_t>(i);
    }

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
    std::size_t flips = 0, done = 0;
    // Each edge's cost, computed in parallel before the serial propagation: Hoppe's
    // 1 - |ni . nj| plus the edge's tilt out of the two tangent planes (an edge across a thin part
    // joins antiparallel normals, which the plain cost finds cheapest). It does not depend on the
    // normals' signs, which the propagation changes.
    // With it, the sign of the estimates' dot product along the edge: the propagation's test of
    // the signed normals' dot product is this sign, reversed where `from` stands turned over (a
    // negation is exact), so the serial loop reads no normal.
    std::vector<float> edge_cost(adj.size());
    std::vector<std::uint8_t> edge_sign(adj.size());
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t u = r.begin(); u != r.end(); ++u)
            for (std::uint32_t e = start[u]; e < start[u + 1]; ++e) {
                const std::uint32_t v = adj[e];
                const Vec3f edge = pts[v] - pts[u];
                const float len = edge.norm();
                const float tilt =
                    len > 0 ? 0.5f * (std::abs(edge.dot(normals[u])) + std::abs(edge.dot(normals[v]))) / len : 0.0f;
                const float dot = normals[u].dot(normals[v]);
                edge_cost[e] = 1.0f - std::abs(dot) + crossing_weight * tilt;
                edge_sign[e] = dot < 0 ? 1 : dot > 0 ? 2 : 0;
            }
    });
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
        const std::span<const std::uint32_t> comp(members.data() + c.first, c.count);
        if (OutwardVote(pts, normals, negated, comp, root) < 0)
            for (std::uint32_t i : comp) negated[i] ^= 1;
    }
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 16384), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i)
            if (negated[i]) normals[i] = -normals[i];
    });
    for (std::uint8_t f : negated) flips += f;
    if (flipped) *flipped = flips;
    return comps.size();
}

}  // namespace

std::size_t OrientNormals(const KdTree& tree, std::vector<Vec3f>& normals, const NormalOptions& options,
                          std::size_t* flipped, const ProgressFn& progress) {
    options.Validate();
    const std::size_t n = tree.size();
    SURFEL_CHECK(normals.size() == n, normals.size() << " normals for " << n << " points");
    const int kk = std::max(1, std::min<int>(options.orient_k, static_cast<int>(n) - 1));
    const KnnTable knn = n > 1 ? tree.KnnAll(kk) : KnnTable{};
    return OrientOverGraph(tree.points(), normals, knn, kk, options.orient_crossing_weight, flipped, progress);
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
