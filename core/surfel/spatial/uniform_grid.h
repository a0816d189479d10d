#pragma once
/// \file
/// A uniform grid for fixed-radius neighbour queries (the "dynamic grid" of Pointshop3D, course
/// notes chapter 5). Queries never allocate: the renderer's per-ray surface evaluations use it.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <span>
#include <vector>

#include "surfel/base/point_cloud.h"

namespace surfel {

/// Points bucketed into cubic cells, stored cell by cell for locality; queries for a radius up
/// to `cell`.
///
/// Two layouts, chosen at construction:
/// - dense (when the box holds at most 32 cells per point): a full array of cell starts,
///   x-major and z fastest, so a z-column of cells is one contiguous run of points. A query
///   walks the 3 x 3 columns around it, each clipped to the sphere's z-extent: 9 array reads
///   instead of 27 hash probes. (Cells of cell / 2 or cell / 3 cut the candidates further but
///   cost more in column overhead than they saved, measured on the bunny render and MLS.)
/// - sparse (very elongated or sparse clouds): cells of side `cell` in an open-addressing hash
///   table (memory O(points) whatever the extent); a query visits the 27 cells around it.
/// Both visit the same points; the order differs, and is fixed for a given grid.
class UniformGrid {
public:
    UniformGrid(std::span<const Vec3f> points, float cell);

    float cell() const { return cell_; }

    /// Calls fn(index, point, dist2) for every point within `radius` (<= cell()) of q.
    template <typename Fn>
    void ForEachWithin(const Vec3f& q, float radius, Fn&& fn) const {
        const float r2 = radius * radius;
        ForEachCandidateRun(q, radius, [&](std::uint32_t first, std::uint32_t last) {
            for (std::uint32_t i = first; i < last; ++i) {
                const float d2 = (sorted_[i] - q).squaredNorm();
                if (d2 <= r2) fn(order_[i], sorted_[i], d2);
            }
        });
    }

    /// Calls fn(first, last) for runs [first, last) of the cell-sorted points (sorted_points(),
    /// sorted_indices()) that together hold every point within `radius` (<= cell()) of q, among
    /// others the caller filters out by distance (as ForEachWithin does, with the same float
    /// test). For callers that filter a whole run at once, without a branch per point.
    template <typename Fn>
    void ForEachCandidateRun(const Vec3f& q, float radius, Fn&& fn) const {
        const float r2 = radius * radius;
        if (dense_) {
            // Ranges are padded by a hair so rounding never drops a point at exactly `radius`
            // (the distance test is exact; padding only adds candidates).
            const float pad = 1e-4f * cell_, inv = 1.0f / cell_;
            const Vec3f ql = q - origin_;
            int b[3], e[3];
            for (int a = 0; a < 3; ++a) {
                b[a] = std::max(0, Cell((ql[a] - radius - pad) * inv));
                e[a] = std::min(dims_[a] - 1, Cell((ql[a] + radius + pad) * inv));
                if (b[a] > e[a]) return;
            }
            for (int x = b[0]; x <= e[0]; ++x) {
                const float gx = std::max({0.0f, x * cell_ - ql.x() - pad, ql.x() - (x + 1) * cell_ - pad});
                for (int y = b[1]; y <= e[1]; ++y) {
                    const float gy = std::max({0.0f, y * cell_ - ql.y() - pad, ql.y() - (y + 1) * cell_ - pad});
                    const float rem = r2 - gx * gx - gy * gy;
                    if (rem < 0.0f) continue;
                    const float zr = std::sqrt(rem) + pad;
                    const int z0 = std::max(b[2], Cell((ql.z() - zr) * inv));
                    const int z1 = std::min(e[2], Cell((ql.z() + zr) * inv));
                    if (z0 > z1) continue;
                    const std::size_t column = (static_cast<std::size_t>(x) * dims_[1] + y) * dims_[2];
                    const std::uint32_t first = starts_[column + z0], last = starts_[column + z1 + 1];
                    if (first < last) fn(first, last);
                }
            }
            return;
        }
        const Eigen::Vector3i c = CellOf(q);
        for (int dz = -1; dz <= 1; ++dz)
            for (int dy = -1; dy <= 1; ++dy)
                for (int dx = -1; dx <= 1; ++dx) {
                    const std::int64_t slot = Find(Key(c.x() + dx, c.y() + dy, c.z() + dz));
                    if (slot < 0) continue;
                    fn(starts_[slot], starts_[slot] + counts_[slot]);
                }
    }

    /// The points in cell order, and their indices in the input (for ForEachCandidateRun).
    const Vec3f* sorted_points() const { return sorted_.data(); }
    const std::uint32_t* sorted_indices() const { return order_.data(); }

    /// Dense layout only: for every point p_i, the squared distance to its k-th nearest other
    /// point (k <= 64) when that neighbour lies within the 3 x 3 x 3 block of cells around p_i's
    /// cell (then it is exact), and -1 where it does not (the caller searches further). All
    /// points of a cell share the block's candidates, gathered once from 9 contiguous z-runs.
    /// Indexed like the points the grid was built from; parallel. Empty for the sparse layout.
    std::vector<float> KthNeighborDist2InBlock(int k) const;

    /// Dense layout only: for every point p_i, its k nearest other points (k <= 64) ranked by
    /// (squared distance, index), where all k lie within the 3 x 3 x 3 block of cells around
    /// p_i's cell, so that no point outside the block is as near as the k-th (then the row is
    /// exact). Squared distances are dx * dx + dy * dy + dz * dz in float, in that order, as
    /// FLANN's L2_Simple computes them, so that the values equal KdTree's. Row i (indexed like
    /// the points the grid was built from) is written to indices[i * k ...] and dist2[i * k ...]
    /// and `answered[i]` set to 1; the other rows are left alone for the caller to search
    /// another way. `done(points)` is called from the worker threads as cells are finished (for
    /// progress and cancellation; it may throw). Parallel; no row depends on the thread count.
    /// Does nothing for the sparse layout.
    void KnnInBlock(int k, std::uint32_t* indices, float* dist2, std::uint8_t* answered,
                    const std::function<void(std::size_t)>& done) const;

    /// Dense layout only: the rows KnnInBlock leaves (points whose k-th neighbour may lie outside
    /// the 3 x 3 x 3 block), searched in wider blocks: the (2 r + 1)^3 cells around the point's
    /// cell for r = min_ring .. max_ring (min_ring >= 2; a ring of 1 << 20 holds the whole grid,
    /// where every row with k others is answered). The same float distances and ranking by
    /// (squared distance, index) as KnnInBlock; a row is accepted when k candidates lie within
    /// the wider block's reach (BlockReach's, so no point outside it is as near), and is then
    /// the exact one. `points` are the points the grid was built from, `rows` the indices to
    /// answer; the table and `answered` as in KnnInBlock; rows not answered within max_ring are
    /// left alone (far outliers: the caller searches them another way). `done(rows)` is called
    /// from the worker threads as rows are finished. Parallel; no row depends on the thread
    /// count. Does nothing for the sparse layout.
    void KnnInWideBlock(std::span<const Vec3f> points, std::span<const std::uint32_t> rows, int k, int min_ring,
                        int max_ring, std::uint32_t* indices, float* dist2, std::uint8_t* answered,
                        const std::function<void(std::size_t)>& done) const;

    /// Whether a grid of `n` points in `box` with this cell gets the dense layout (at most
    /// `cells_per_point` cells a point, 4 bytes each; the constructor allows 32).
    static bool FitsDense(const BoundingBox& box, std::size_t n, float cell,
                          std::uint64_t cells_per_point = kDenseCellsPerPoint);

    /// True when the dense layout was chosen (for tests and diagnostics).
    bool dense() const { return dense_; }

    /// Dense layout only: the cell (x, y, z) the constructor put p in (the same float
    /// arithmetic, clamped to the grid), for a finite p.
    void DenseCellOf(const Vec3f& p, int at[3]) const {
        const float inv = 1.0f / cell_;
        for (int a = 0; a < 3; ++a)
            at[a] = std::clamp(static_cast<int>(std::floor((p[a] - origin_[a]) * inv)), 0, dims_[a] - 1);
    }
    /// Dense layout only: calls fn(first, last) for the runs of the cell-sorted points that make
    /// up the 3 x 3 x 3 block of cells around cell `at` (clipped to the grid): 9 z-runs at most,
    /// in ascending order, so the block's points come in the order a query walk visits them.
    template <typename Fn>
    void ForEachBlockRun(const int at[3], Fn&& fn) const {
        const int nx = dims_[0], ny = dims_[1], nz = dims_[2];
        const int z0 = std::max(0, at[2] - 1), z1 = std::min(nz - 1, at[2] + 1);
        for (int bx = std::max(0, at[0] - 1); bx <= std::min(nx - 1, at[0] + 1); ++bx)
            for (int by = std::max(0, at[1] - 1); by <= std::min(ny - 1, at[1] + 1); ++by) {
                const std::size_t column = (static_cast<std::size_t>(bx) * ny + by) * nz;
                const std::uint32_t first = starts_[column + z0], last = starts_[column + z1 + 1];
                if (first < last) fn(first, last);
            }
    }
    /// Dense layout only: how far the 3 x 3 x 3 block around cell `at` reaches from p (a point
    /// of that cell) on every side that has a neighbour cell, less a hair (1e-4 x cell: cell
    /// assignment and these bounds round differently). A ball around p no larger than this
    /// holds no point outside the block.
    float BlockReach(const Vec3f& p, const int at[3]) const;

private:
    // floor(v) as a cell index, saturated (far or non-finite queries must not overflow the cast).
    static int Cell(float v) {
        if (!(v > -1.0f)) return -1;
        if (!(v < float(1 << 30))) return 1 << 30;
        return static_cast<int>(std::floor(v));
    }
    Eigen::Vector3i CellOf(const Vec3f& p) const {
        const Vec3f s = ((p - origin_) / cell_).array().floor();
        return s.cast<int>();
    }
    static std::uint64_t Key(std::int64_t x, std::int64_t y, std::int64_t z) {
        return (static_cast<std::uint64_t>(x & 0x1FFFFF) << 42) | (static_cast<std::uint64_t>(y & 0x1FFFFF) << 21) |
               static_cast<std::uint64_t>(z & 0x1FFFFF);
    }
    static std::uint64_t Hash(std::uint64_t k) {
        k ^= k >> 33;
        k *= 0xff51afd7ed558ccdULL;
        k ^= k >> 33;
        return k;
    }
    std::int64_t Find(std::uint64_t key) const {
        std::uint64_t h = Hash(key) & mask_;
        for (;;) {
            if (keys_[h] == kEmpty) return -1;
            if (keys_[h] == key) return static_cast<std::int64_t>(h);
            h = (h + 1) & mask_;
        }
    }

    // Dense layout: the points of the 3 x 3 x 3 block of cells around cell (x, y, z), as
    // coordinate columns (and their input indices when `ids` is given; every vector cleared
    // first); returns where the cell's own points start among them.
    std::size_t GatherBlock(int x, int y, int z, std::vector<float>& cx, std::vector<float>& cy,
                            std::vector<float>& cz, std::vector<std::uint32_t>* ids) const;

    void BuildDense(std::span<const Vec3f> points);
    void BuildSparse(std::span<const Vec3f> points);

    static constexpr std::uint64_t kEmpty = ~0ULL;
    static constexpr std::uint64_t kDenseCellsPerPoint = 32;  // dense layout's memory cap (4 bytes a cell)
    float cell_;
    bool dense_ = false;
    int dims_[3] = {0, 0, 0};             // dense: cells per axis
    Vec3f origin_;
    std::uint64_t mask_ = 0;
    std::vector<std::uint64_t> keys_;     // hash table of occupied cells
    std::vector<std::uint32_t> starts_;   // first point of the cell in sorted_ (dense: all cells + 1)
    std::vector<std::uint32_t> counts_;   // points in the cell
    std::vector<Vec3f> sorted_;           // positions, cell by cell
    std::vector<std::uint32_t> order_;    // original index of sorted_[i]
};

}  // namespace surfel
