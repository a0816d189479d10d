#include "surfel/spatial/neighbor_radii.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <memory>

#include "surfel/base/error.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/spatial/uniform_grid.h"

namespace surfel {

namespace {

constexpr int kMaxK = 64;  // the sorted array of the k smallest lives on the stack
// Grid cell = this x the median k-th distance: smaller cells send more points to the outward
// search, larger ones give each block more candidates.
// On the bunny (k = 6): 1.0 sends 10 % of the points outwards, 1.3 under 1 %, for about the
// same block time.
constexpr float kCellPerMedian = 1.3f;
// Memory cap of the grid: cells a point (4 bytes each), below the grid's own 32, so that large
// clouds do not pay 128 bytes a point for cell starts; coarser cells then take more candidates.
constexpr std::uint64_t kCellsPerPoint = 8;  // merged scans: 113 ms at 8, 153 ms at 32 (more cells to clear)

// Squared distance from point i to its k-th nearest other point, gathering within `radius` and
// doubling it until k others are found (`reach` bounds the doubling: beyond it every point of
// the box is within the radius).
float KthDist2(const UniformGrid& grid, std::span<const Vec3f> points, std::uint32_t i, int k, float radius,
               float reach) {
    std::array<float, kMaxK> best;
    for (;;) {
        int count = 0;
        grid.ForEachWithin(points[i], radius, [&](std::uint32_t j, const Vec3f&, float d2) {
            if (j == i) return;
            if (count == k) {
                if (d2 >= best[k - 1]) return;
                --count;  // the largest drops out
            }
            int at = count++;
            while (at > 0 && best[at - 1] > d2) {
                best[at] = best[at - 1];
                --at;
            }
            best[at] = d2;
        });
        if (count == k) return best[k - 1];
        if (radius > reach) return count ? best[count - 1] : 0.0f;  // not reached with finite points
        radius *= 2.0f;
    }
}

std::vector<float> ViaTree(std::span<const Vec3f> points, int k, const KdTree* tree) {
    std::unique_ptr<KdTree> own;
    if (!tree) {
        own = std::make_unique<KdTree>(points);
        tree = own.get();
    }
    const KnnTable knn = tree->KnnAll(k);
    std::vector<float> r(points.size());
    for (std::size_t i = 0; i < points.size(); ++i) r[i] = std::sqrt(knn.Dist2(i)[knn.k - 1]);
    return r;
}

}  // namespace

std::unique_ptr<UniformGrid> NeighborGrid(std::span<const Vec3f> points, int k) {
    const std::size_t n = points.size();
    if (n < 2 || k < 1 || k > kMaxK) return nullptr;
    BoundingBox box;
    for (const Vec3f& p : points) {
        if (!p.allFinite()) return nullptr;
        box.Extend(p);
    }
    const float diag = box.Diagonal();
    if (!(diag > 0.0f)) return nullptr;
    // The smallest cell >= c (in steps of 1.25x) that the dense layout fits, or 0.
    auto dense_cell = [&](float c) {
        c = std::max(c, diag * 1e-6f);
        for (int t = 0; t < 12; ++t, c *= 1.25f)
            if (UniformGrid::FitsDense(box, n, c, kCellsPerPoint)) return c;
        return 0.0f;
    };
    // A first cell from the box, as if the points sampled a surface of area ~ diag^2: spacing
    // diag / sqrt(n), and the k-th neighbour about sqrt(k / pi) spacings away.
    float cell = dense_cell(kCellPerMedian * diag * std::sqrt(static_cast<float>(k) / (3.14159265f * static_cast<float>(n))));
    if (cell == 0.0f) return nullptr;
    auto grid = std::make_unique<UniformGrid>(points, cell);
    const float reach = 2.0f * diag;
    // Refine the cell from the median k-th distance of an even sample (volumes, lines and very
    // uneven clouds are far from the surface guess) when it is off by more than 1.5x, as far as
    // the dense layout allows.
    const std::size_t samples = std::min<std::size_t>(n, 256), stride = n / samples;
    std::vector<float> d(samples);
    for (std::size_t s = 0; s < samples; ++s)
        d[s] = KthDist2(*grid, points, static_cast<std::uint32_t>(s * stride), static_cast<int>(std::min<std::size_t>(k, n - 1)),
                        grid->cell(), reach);
    std::nth_element(d.begin(), d.begin() + samples / 2, d.end());
    const float want = dense_cell(kCellPerMedian * std::sqrt(d[samples / 2]));
    if (want > 0.0f && (want > 1.5f * cell || want < cell / 1.5f)) grid = std::make_unique<UniformGrid>(points, want);
    return grid->dense() ? std::move(grid) : nullptr;
}

std::vector<float> KthNeighborDistances(std::span<const Vec3f> points, int k, const KdTree* tree) {
    SURFEL_CHECK(k > 0, "k must be positive, got " << k);
    const std::size_t n = points.size();
    if (n < 2) return std::vector<float>(n, 0.0f);
    k = static_cast<int>(std::min<std::size_t>(static_cast<std::size_t>(k), n - 1));
    BoundingBox box;
    for (const Vec3f& p : points) {
        if (!p.allFinite()) return ViaTree(points, k, tree);
        box.Extend(p);
    }
    const float diag = box.Diagonal();
    if (!(diag > 0.0f)) return std::vector<float>(n, 0.0f);  // all points coincide
    const auto grid = NeighborGrid(points, k);
    if (!grid) return ViaTree(points, k, tree);
    const float reach = 2.0f * diag;
    // Most points find their k-th neighbour in the block of cells around them; the rest search
    // outwards from there.
    std::vector<float> r = grid->KthNeighborDist2InBlock(k);
    const UniformGrid& g = *grid;
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 2048), [&](const tbb::blocked_range<std::size_t>& range) {
        for (std::size_t i = range.begin(); i != range.end(); ++i) {
            if (r[i] < 0.0f) r[i] = KthDist2(g, points, static_cast<std::uint32_t>(i), k, 2.0f * g.cell(), reach);
            r[i] = std::sqrt(r[i]);
        }
    });
    return r;
}

std::vector<float> NearestDistances(std::span<const Vec3f> points, const KnnTable& knn) {
    const std::size_t n = points.size();
    if (n < 2) return std::vector<float>(n, 0.0f);
    SURFEL_CHECK(knn.size() == n && knn.k >= 1, knn.size() << " rows of " << knn.k << " neighbours for " << n << " points");
    auto first_column = [&] {  // ViaTree's values: KnnAll(1)'s column is every KnnAll(K)'s first
        std::vector<float> r(n);
        for (std::size_t i = 0; i < n; ++i) r[i] = std::sqrt(knn.Dist2(i)[0]);
        return r;
    };
    // KthNeighborDistances' cases, in its order.
    BoundingBox box;
    for (const Vec3f& p : points) {
        if (!p.allFinite()) return first_column();
        box.Extend(p);
    }
    const float diag = box.Diagonal();
    if (!(diag > 0.0f)) return std::vector<float>(n, 0.0f);
    const auto grid = NeighborGrid(points, 1);
    if (!grid) return first_column();
    const float reach = 2.0f * diag;
    const UniformGrid& g = *grid;
    std::vector<float> r(n);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 2048), [&](const tbb::blocked_range<std::size_t>& range) {
        for (std::size_t i = range.begin(); i != range.end(); ++i) {
            // KthNeighborDist2InBlock answers row i exactly when its nearest lies within the
            // block's reach (the block's nearest is then the nearest of all: the table's).
            const float d2 = knn.Dist2(i)[0];
            int at[3];
            g.DenseCellOf(points[i], at);
            const float block = g.BlockReach(points[i], at);
            r[i] = std::sqrt(block > 0.0f && d2 <= block * block
                                 ? d2
                                 : KthDist2(g, points, static_cast<std::uint32_t>(i), 1, 2.0f * g.cell(), reach));
        }
    });
    return r;
}

}  // namespace surfel
