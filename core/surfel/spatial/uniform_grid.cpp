#include "surfel/spatial/uniform_grid.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <array>
#include <limits>
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
    dense_ = FitsDense(box, points.size(), cell);
    if (dense_) {
        for (int a = 0; a < 3; ++a) dims_[a] = static_cast<int>(std::floor(box.Extent()[a] / cell_)) + 1;
        BuildDense(points);
    } else {
        BuildSparse(points);
    }
}

bool UniformGrid::FitsDense(const BoundingBox& box, std::size_t n, float cell, std::uint64_t cells_per_point) {
    if (box.empty() || !(cell > 0.0f) || (box.Extent() / cell).maxCoeff() > float(1 << 20)) return false;
    const std::uint64_t budget = std::min(cells_per_point, kDenseCellsPerPoint) * n + 4096;
    std::uint64_t total = 1;
    for (int a = 0; a < 3; ++a) {
        total *= static_cast<std::uint64_t>(std::floor(box.Extent()[a] / cell)) + 1;
        if (total > budget) return false;
    }
    return true;
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

namespace {

// The k-th smallest of v[0..s) (s >= k), or -1 when none qualifies (NaNs): the value with fewer
// than k values below it and at least k at or below it (ties included). Counting is branch-free
// and vectorises; an insertion sort of the k smallest cost 1.5x more, in mispredicted branches.
// Each counted candidate also bounds the answer from below or above, so candidates outside the
// bounds are not counted.
inline float KthSmallestByRank(const float* v, std::size_t s, int k) {
    float lower = -1.0f, upper = std::numeric_limits<float>::infinity();
    for (std::size_t j = 0; j < s; ++j) {
        const float c = v[j];
        if (c < lower || c > upper) continue;
        int less = 0, at_most = 0;
#pragma omp simd reduction(+ : less, at_most)
        for (std::size_t l = 0; l < s; ++l) {
            less += v[l] < c ? 1 : 0;
            at_most += v[l] <= c ? 1 : 0;
        }
        if (less < k && at_most >= k) return c;
        if (at_most < k) lower = c;  // the k-th is above c
        else upper = c;              // at least k at or below c, the k-th below c
    }
    return -1.0f;
}
// The first threshold of a point's k-nearest search, on the previous point's squared k-th distance
// (1.2x the distance): when k candidates lie within it, the others need not be ranked (session 13:
// the triangle-inequality bound alone keeps ~60 candidates a point for k = 16 on the merged scans).
constexpr float kGuess = 1.44f;

// Squared distances from p to m candidates held as coordinate columns: dx * dx + dy * dy + dz * dz
// in float, in that order (FLANN's L2_Simple sums them so, and KdTree's rows must be matched to
// the bit), vectorised.
// (Without __restrict GCC 12 left the loop scalar: 276 against 146 M instructions for KnnAll on
// bunny_scan.)
inline void Distances2(const float* __restrict X, const float* __restrict Y, const float* __restrict Z,
                       std::size_t m, const Vec3f& p, float* __restrict D) {
    const float px = p.x(), py = p.y(), pz = p.z();
#pragma omp simd
    for (std::size_t j = 0; j < m; ++j) {
        const float dx = X[j] - px, dy = Y[j] - py, dz = Z[j] - pz;
        D[j] = dx * dx + dy * dy + dz * dz;
    }
}
}  // namespace

std::size_t UniformGrid::GatherBlock(int x, int y, int z, std::vector<float>& cx, std::vector<float>& cy,
                                     std::vector<float>& cz, std::vector<std::uint32_t>* ids) const {
    const int nx = dims_[0], ny = dims_[1], nz = dims_[2];
    const std::uint32_t first = starts_[(static_cast<std::size_t>(x) * ny + y) * nz + z];
    cx.clear(), cy.clear(), cz.clear();
    if (ids) ids->clear();
    std::size_t self = 0;
    for (int bx = std::max(0, x - 1); bx <= std::min(nx - 1, x + 1); ++bx)
        for (int by = std::max(0, y - 1); by <= std::min(ny - 1, y + 1); ++by) {
            const std::size_t column = (static_cast<std::size_t>(bx) * ny + by) * nz;
            const std::uint32_t b = starts_[column + std::max(0, z - 1)];
            const std::uint32_t e = starts_[column + std::min(nz - 1, z + 1) + 1];
            const std::size_t m0 = cx.size();
            if (bx == x && by == y) self = m0 + (first - b);
            // Sized once a run, then written without push_back's capacity checks (session 14:
            // ~0.23 G instructions of KnnAll on the merged scans with them).
            cx.resize(m0 + (e - b)), cy.resize(m0 + (e - b)), cz.resize(m0 + (e - b));
            float *X = cx.data() + m0, *Y = cy.data() + m0, *Z = cz.data() + m0;
            const Vec3f* src = sorted_.data() + b;
            for (std::uint32_t j = 0; j < e - b; ++j) X[j] = src[j].x(), Y[j] = src[j].y(), Z[j] = src[j].z();
            if (ids) ids->insert(ids->end(), order_.begin() + b, order_.begin() + e);
        }
    return self;
}

float UniformGrid::BlockReach(const Vec3f& p, const int at[3]) const {
    const Vec3f lo = origin_ + cell_ * Vec3f(float(at[0] - 1), float(at[1] - 1), float(at[2] - 1));
    const Vec3f hi = origin_ + cell_ * Vec3f(float(at[0] + 2), float(at[1] + 2), float(at[2] + 2));
    float reach = std::numeric_limits<float>::infinity();
    for (int a = 0; a < 3; ++a) {
        if (at[a] > 0) reach = std::min(reach, p[a] - lo[a]);
        if (at[a] < dims_[a] - 1) reach = std::min(reach, hi[a] - p[a]);
    }
    return reach - 1e-4f * cell_;
}

std::vector<float> UniformGrid::KthNeighborDist2InBlock(int k) const {
    SURFEL_CHECK(k >= 1 && k <= 64, "k must be 1..64, got " << k);
    if (!dense_) return {};
    const std::size_t n = sorted_.size();
    std::vector<float> out(n, -1.0f);
    const int nx = dims_[0], ny = dims_[1], nz = dims_[2];
    // One x-slab of cells per task: each cell's 3 x 3 x 3 block is 9 runs of the sorted points.
    tbb::parallel_for(tbb::blocked_range<int>(0, nx), [&](const tbb::blocked_range<int>& xs) {
        std::vector<float> cx, cy, cz, d2, kept;
        // The last point answered in this task and its k-th distance: by the triangle
        // inequality, any point p has k others within rho_prev + |p - p_prev| (p_prev itself
        // stands in for p when p is one of them), which bounds the candidates worth ranking.
        Vec3f prev = Vec3f::Zero();
        float prev_rho = -1.0f;
        for (int x = xs.begin(); x != xs.end(); ++x)
            for (int y = 0; y < ny; ++y)
                for (int z = 0; z < nz; ++z) {
                    const std::size_t cell = (static_cast<std::size_t>(x) * ny + y) * nz + z;
                    const std::uint32_t first = starts_[cell], last = starts_[cell + 1];
                    if (first == last) continue;
                    const std::size_t self = GatherBlock(x, y, z, cx, cy, cz, nullptr);
                    const std::size_t m = cx.size();
                    const int at[3] = {x, y, z};
                    if (d2.size() < m) d2.resize(m), kept.resize(m);
                    const float *X = cx.data(), *Y = cy.data(), *Z = cz.data();
                    float* D = d2.data();
                    float* K = kept.data();
                    for (std::uint32_t i = first; i < last; ++i) {
                        const Vec3f p = sorted_[i];
                        Distances2(X, Y, Z, m, p, D);
                        D[self + (i - first)] = std::numeric_limits<float>::infinity();  // not its own neighbour
                        // Only candidates within the triangle-inequality bound can be among the
                        // k nearest (kept branch-free; the bound is widened a hair for rounding).
                        std::size_t s = m;
                        const float* F = D;
                        if (prev_rho >= 0.0f) {
                            const float bound = prev_rho + (p - prev).norm();
                            const float b2 = bound * bound * 1.0001f;
                            // First the previous point's k-th distance, widened by kGuess: when k
                            // candidates lie within it, the k-th is among them.
                            auto keep = [&](float t) {
                                std::size_t kept_count = 0;
                                for (std::size_t j = 0; j < m; ++j) {
                                    K[kept_count] = D[j];
                                    kept_count += D[j] <= t ? 1 : 0;
                                }
                                return kept_count;
                            };
                            const float guess = prev_rho * prev_rho * kGuess;
                            s = guess < b2 ? keep(guess) : 0;
                            if (s < static_cast<std::size_t>(k)) s = keep(b2);
                            F = K;
                        }
                        if (s < static_cast<std::size_t>(k)) continue;
                        const float kth = KthSmallestByRank(F, s, k);
                        if (!(kth >= 0.0f) || std::isinf(kth)) continue;
                        prev = p;
                        prev_rho = std::sqrt(kth);  // k real points lie this close: a valid bound
                        const float reach = BlockReach(p, at);
                        if (reach > 0.0f && kth <= reach * reach) out[order_[i]] = kth;
                    }
                }
    });
    return out;
}

void UniformGrid::KnnInBlock(int k, std::uint32_t* indices, float* dist2, std::uint8_t* answered,
                             const std::function<void(std::size_t)>& done) const {
    SURFEL_CHECK(k >= 1 && k <= 64, "k must be 1..64, got " << k);
    if (!dense_) return;
    const int nx = dims_[0], ny = dims_[1], nz = dims_[2];
    struct Ranked {
        float d2;
        std::uint32_t index;
    };
    tbb::parallel_for(tbb::blocked_range<int>(0, nx), [&](const tbb::blocked_range<int>& xs) {
        std::vector<float> cx, cy, cz, d2, fd;
        std::vector<std::uint32_t> cid, fi, tie;
        std::array<Ranked, 64> best;
        // As in KthNeighborDist2InBlock: the last point ranked in this task and its k-th
        // distance bound the candidates of the next by the triangle inequality.
        Vec3f prev = Vec3f::Zero();
        float prev_rho = -1.0f;
        for (int x = xs.begin(); x != xs.end(); ++x) {
            std::size_t slab_points = 0;
            for (int y = 0; y < ny; ++y)
                for (int z = 0; z < nz; ++z) {
                    const std::size_t cell = (static_cast<std::size_t>(x) * ny + y) * nz + z;
                    const std::uint32_t first = starts_[cell], last = starts_[cell + 1];
                    if (first == last) continue;
                    slab_points += last - first;
                    const std::size_t self = GatherBlock(x, y, z, cx, cy, cz, &cid);
                    const std::size_t m = cx.size();
                    if (m <= static_cast<std::size_t>(k)) continue;  // fewer than k others
                    const int at[3] = {x, y, z};
                    if (d2.size() < m) d2.resize(m), fd.resize(m), fi.resize(m), tie.resize(m);
                    const float *X = cx.data(), *Y = cy.data(), *Z = cz.data();
                    float* D = d2.data();
                    float* FD = fd.data();
                    std::uint32_t* FI = fi.data();
                    for (std::uint32_t i = first; i < last; ++i) {
                        const Vec3f p = sorted_[i];
                        Distances2(X, Y, Z, m, p, D);
                        D[self + (i - first)] = std::numeric_limits<float>::infinity();  // not its own
                        // The k smallest by (distance, index) among the candidates within the
                        // threshold (the triangle-inequality bound): those candidates first, kept
                        // branch-free; the k-th distance by rank (as in KthNeighborDist2InBlock);
                        // then the ones below it and the lowest indices at it, sorted. The same
                        // rows as an insertion of every candidate into a sorted k-array (session
                        // 13: that insertion's shifts and mispredicted branches were ~60 % of
                        // this search).
                        float threshold = std::numeric_limits<float>::infinity();
                        if (prev_rho >= 0.0f) {
                            const float bound = prev_rho + (p - prev).norm();
                            threshold = bound * bound * 1.0001f;  // a hair wider for rounding
                        }
                        // A tighter first try: the previous point's k-th distance, widened by
                        // kGuess. When k candidates lie within it, the k smallest are among them.
                        auto keep = [&](float t) {
                            std::size_t kept = 0;
                            for (std::size_t j = 0; j < m; ++j) {
                                FD[kept] = D[j];
                                FI[kept] = cid[j];
                                kept += D[j] <= t ? 1 : 0;
                            }
                            return kept;
                        };
                        const float guess = prev_rho * prev_rho * kGuess;
                        std::size_t s = 0;
                        if (prev_rho >= 0.0f && guess < threshold) s = keep(guess);
                        if (s < static_cast<std::size_t>(k)) s = keep(threshold);
                        if (s < static_cast<std::size_t>(k)) continue;
                        const float kth = KthSmallestByRank(FD, s, k);
                        if (!(kth >= 0.0f) || std::isinf(kth)) continue;
                        int count = 0, ties = 0;
                        for (std::size_t j = 0; j < s; ++j) {
                            best[count] = {FD[j], FI[j]};
                            count += FD[j] < kth ? 1 : 0;
                            tie[ties] = FI[j];
                            ties += FD[j] == kth ? 1 : 0;
                        }
                        std::partial_sort(tie.begin(), tie.begin() + (k - count), tie.begin() + ties);
                        for (int t = 0; count < k; ++t) best[count++] = {kth, tie[t]};
                        for (int r = 1; r < k; ++r) {
                            const Ranked e = best[r];
                            int pos = r;
                            while (pos > 0 && (best[pos - 1].d2 > e.d2 || (best[pos - 1].d2 == e.d2 && best[pos - 1].index > e.index))) {
                                best[pos] = best[pos - 1];
                                --pos;
                            }
                            best[pos] = e;
                        }
                        prev = p;
                        prev_rho = std::sqrt(kth);
                        const float reach = BlockReach(p, at);
                        if (!(reach > 0.0f && kth <= reach * reach)) continue;
                        const std::size_t row = static_cast<std::size_t>(order_[i]) * k;
                        for (int r = 0; r < k; ++r) indices[row + r] = best[r].index, dist2[row + r] = best[r].d2;
                        answered[order_[i]] = 1;
                    }
                }
            if (done) done(slab_points);
        }
    });
}

void UniformGrid::KnnInWideBlock(std::span<const Vec3f> points, std::span<const std::uint32_t> rows, int k,
                                 int min_ring, int max_ring, std::uint32_t* indices, float* dist2, std::uint8_t* answered,
                                 const std::function<void(std::size_t)>& done) const {
    SURFEL_CHECK(k >= 1 && k <= 64, "k must be 1..64, got " << k);
    SURFEL_CHECK(min_ring >= 2 && max_ring <= (1 << 20), "rings " << min_ring << " .. " << max_ring);
    if (!dense_) return;
    const int nx = dims_[0], ny = dims_[1], nz = dims_[2];
    struct Ranked {
        float d2;
        std::uint32_t index;
    };
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, rows.size(), 16), [&](const tbb::blocked_range<std::size_t>& rs) {
        std::vector<float> cx, cy, cz, d2;
        std::vector<std::uint32_t> cid;
        std::vector<Ranked> ranked;
        for (std::size_t t = rs.begin(); t != rs.end(); ++t) {
            const std::uint32_t i = rows[t];
            const Vec3f p = points[i];
            int at[3];
            DenseCellOf(p, at);
            for (int r = min_ring; r <= max_ring; ++r) {
                // BlockReach for the (2 r + 1)^3 block: infinite when it holds the whole grid.
                const Vec3f lo = origin_ + cell_ * Vec3f(float(at[0] - r), float(at[1] - r), float(at[2] - r));
                const Vec3f hi = origin_ + cell_ * Vec3f(float(at[0] + r + 1), float(at[1] + r + 1), float(at[2] + r + 1));
                float reach = std::numeric_limits<float>::infinity();
                for (int a = 0; a < 3; ++a) {
                    if (at[a] - r > 0) reach = std::min(reach, p[a] - lo[a]);
                    if (at[a] + r < dims_[a] - 1) reach = std::min(reach, hi[a] - p[a]);
                }
                reach -= 1e-4f * cell_;
                if (!(reach > 0.0f)) continue;
                const float reach2 = reach * reach;
                cx.clear(), cy.clear(), cz.clear(), cid.clear();
                const int z0 = std::max(0, at[2] - r), z1 = std::min(nz - 1, at[2] + r);
                for (int bx = std::max(0, at[0] - r); bx <= std::min(nx - 1, at[0] + r); ++bx)
                    for (int by = std::max(0, at[1] - r); by <= std::min(ny - 1, at[1] + r); ++by) {
                        const std::size_t column = (static_cast<std::size_t>(bx) * ny + by) * nz;
                        const std::uint32_t b = starts_[column + z0], e = starts_[column + z1 + 1];
                        const std::size_t m0 = cx.size();
                        cx.resize(m0 + (e - b)), cy.resize(m0 + (e - b)), cz.resize(m0 + (e - b));
                        for (std::uint32_t j = b; j < e; ++j)
                            cx[m0 + (j - b)] = sorted_[j].x(), cy[m0 + (j - b)] = sorted_[j].y(), cz[m0 + (j - b)] = sorted_[j].z();
                        cid.insert(cid.end(), order_.begin() + b, order_.begin() + e);
                    }
                const std::size_t m = cx.size();
                if (m <= static_cast<std::size_t>(k)) continue;  // fewer than k others
                if (d2.size() < m) d2.resize(m);
                Distances2(cx.data(), cy.data(), cz.data(), m, p, d2.data());  // KnnInBlock's floats
                // Only candidates within the reach can make an accepted row: when k of them lie
                // within it, the k smallest of all are among them.
                ranked.clear();
                for (std::size_t j = 0; j < m; ++j)
                    if (d2[j] <= reach2 && cid[j] != i) ranked.push_back({d2[j], cid[j]});  // not its own neighbour
                if (ranked.size() < static_cast<std::size_t>(k)) continue;
                const auto less = [](const Ranked& x, const Ranked& y) {
                    return x.d2 < y.d2 || (x.d2 == y.d2 && x.index < y.index);
                };
                std::partial_sort(ranked.begin(), ranked.begin() + k, ranked.end(), less);
                const std::size_t row = static_cast<std::size_t>(i) * k;
                for (int c = 0; c < k; ++c) indices[row + c] = ranked[c].index, dist2[row + c] = ranked[c].d2;
                answered[i] = 1;
                break;
            }
        }
        if (done) done(rs.size());
    });
}

}  // namespace surfel
