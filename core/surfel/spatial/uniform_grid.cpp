#include "surfel/spatial/uniform_grid.h"

#include <algorithm>
#include <numeric>

#include "surfel/base/error.h"

namespace surfel {

UniformGrid::UniformGrid(std::span<const Vec3f> points, float cell) : cell_(cell) {
    if (!(cell > 0.0f) || !std::isfinite(cell))
        throw Error(ErrorCode::kInvalidArgument, "grid cell size must be positive, got " + std::to_string(cell));
    BoundingBox box;
    for (const auto& p : points) box.Extend(p);
    origin_ = box.empty() ? Vec3f::Zero() : box.min;
    if (!box.empty() && (box.Extent() / cell).maxCoeff() > float(1 << 20))
        throw Error(ErrorCode::kInvalidArgument, "grid cell size " + std::to_string(cell) + " is too small for the cloud's extent");
    const std::size_t n = points.size();
    if (!box.empty()) {
        std::uint64_t total = 1;
        for (int a = 0; a < 3; ++a) {
            dims_[a] = static_cast<int>(std::floor(box.Extent()[a] / cell_)) + 1;
            total *= static_cast<std::uint64_t>(dims_[a]);
            if (total > kDenseCellsPerPoint * n + 4096) break;
        }
        dense_ = total <= kDenseCellsPerPoint * n + 4096;
    }
    if (dense_) BuildDense(points);
    else BuildSparse(points);
}

void UniformGrid::BuildDense(std::span<const Vec3f> points) {
    // Counting sort by cell: x-major, z fastest, so each z-column is contiguous.
    const std::size_t n = points.size();
    const std::size_t cells = static_cast<std::size_t>(dims_[0]) * dims_[1] * dims_[2];
    std::vector<std::uint32_t> cell_of(n);
    starts_.assign(cells + 1, 0);
    const float inv = 1.0f / cell_;
    for (std::size_t i = 0; i < n; ++i) {
        int c[3];
        for (int a = 0; a < 3; ++a)
            c[a] = std::clamp(static_cast<int>(std::floor((points[i][a] - origin_[a]) * inv)), 0, dims_[a] - 1);
        cell_of[i] = static_cast<std::uint32_t>((static_cast<std::size_t>(c[0]) * dims_[1] + c[1]) * dims_[2] + c[2]);
        ++starts_[cell_of[i] + 1];
    }
    for (std::size_t c = 0; c < cells; ++c) starts_[c + 1] += starts_[c];
    std::vector<std::uint32_t> fill(starts_.begin(), starts_.end() - 1);
    order_.resize(n);
    sorted_.resize(n);
    for (std::size_t i = 0; i < n; ++i) {
        const std::uint32_t at = fill[cell_of[i]]++;
        order_[at] = static_cast<std::uint32_t>(i);
        sorted_[at] = points[i];
    }
}

void UniformGrid::BuildSparse(std::span<const Vec3f> points) {
    const std::size_t n = points.size();
    std::vector<std::uint64_t> key(n);
    for (std::size_t i = 0; i < n; ++i) {
        const Eigen::Vector3i c = CellOf(points[i]);
        key[i] = Key(c.x(), c.y(), c.z());
    }
    order_.resize(n);
    std::iota(order_.begin(), order_.end(), 0u);
    std::stable_sort(order_.begin(), order_.end(), [&](std::uint32_t a, std::uint32_t b) { return key[a] < key[b]; });
    sorted_.resize(n);
    for (std::size_t i = 0; i < n; ++i) sorted_[i] = points[order_[i]];
    std::size_t cells = 0;
    for (std::size_t i = 0; i < n; ++i)
        if (i == 0 || key[order_[i]] != key[order_[i - 1]]) ++cells;
    std::size_t cap = 16;
    while (cap < 2 * cells) cap <<= 1;
    mask_ = cap - 1;
    keys_.assign(cap, kEmpty);
    starts_.assign(cap, 0);
    counts_.assign(cap, 0);
    for (std::size_t i = 0; i < n;) {
        const std::uint64_t k = key[order_[i]];
        std::size_t j = i;
        while (j < n && key[order_[j]] == k) ++j;
        std::uint64_t h = Hash(k) & mask_;
        while (keys_[h] != kEmpty) h = (h + 1) & mask_;
        keys_[h] = k;
        starts_[h] = static_cast<std::uint32_t>(i);
        counts_[h] = static_cast<std::uint32_t>(j - i);
        i = j;
    }
}

}  // namespace surfel
