#pragma once
/// \file
/// A uniform grid for fixed-radius neighbour queries (the "dynamic grid" of Pointshop3D, course
/// notes chapter 5). Queries never allocate: the renderer's per-ray surface evaluations use it.

#include <cstdint>
#include <span>
#include <vector>

#include "surfel/base/point_cloud.h"

namespace surfel {

/// Points bucketed into cubic cells of side `cell`, stored cell by cell for locality. A query for
/// radius <= cell visits the 27 cells around the query point. Occupied cells are found through an
/// open-addressing hash table, so memory is O(points) whatever the extent.
class UniformGrid {
public:
    UniformGrid(std::span<const Vec3f> points, float cell);

    float cell() const { return cell_; }

    /// Calls fn(index, point, dist2) for every point within `radius` (<= cell()) of q.
    template <typename Fn>
    void ForEachWithin(const Vec3f& q, float radius, Fn&& fn) const {
        const float r2 = radius * radius;
        const Eigen::Vector3i c = CellOf(q);
        for (int dz = -1; dz <= 1; ++dz)
            for (int dy = -1; dy <= 1; ++dy)
                for (int dx = -1; dx <= 1; ++dx) {
                    const std::int64_t slot = Find(Key(c.x() + dx, c.y() + dy, c.z() + dz));
                    if (slot < 0) continue;
                    const std::uint32_t b = starts_[slot], e = starts_[slot] + counts_[slot];
                    for (std::uint32_t i = b; i < e; ++i) {
                        const float d2 = (sorted_[i] - q).squaredNorm();
                        if (d2 <= r2) fn(order_[i], sorted_[i], d2);
                    }
                }
    }

private:
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

    static constexpr std::uint64_t kEmpty = ~0ULL;
    float cell_;
    Vec3f origin_;
    std::uint64_t mask_ = 0;
    std::vector<std::uint64_t> keys_;     // hash table of occupied cells
    std::vector<std::uint32_t> starts_;   // first point of the cell in sorted_
    std::vector<std::uint32_t> counts_;   // points in the cell
    std::vector<Vec3f> sorted_;           // positions, cell by cell
    std::vector<std::uint32_t> order_;    // original index of sorted_[i]
};

}  // namespace surfel
