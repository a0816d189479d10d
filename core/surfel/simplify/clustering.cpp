// Clustering simplification (course notes, Pauly 2.1): hierarchical and incremental clustering,
// the voxel-grid baseline, and the exact-count adjustment they share.

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <map>
#include <memory>
#include <new>
#include <numeric>
#include <queue>

#if defined(__linux__)
#include <sys/mman.h>
#endif

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>
#include <tbb/parallel_sort.h>

#include "surfel/base/error.h"
#include "surfel/simplify/simplify_internal.h"
#include "surfel/simplify/split_pass.h"
#include "surfel/spatial/kd_tree.h"

namespace surfel::detail {

Spread Analyze(const Moments& m) {
    Spread s;
    if (m.n < 2) return s;
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver;
    solver.computeDirect(m.Covariance());
    s.eigenvalues = solver.eigenvalues().cwiseMax(0.0);
    s.v0 = solver.eigenvectors().col(0);
    s.v2 = solver.eigenvectors().col(2);
    return s;
}

std::size_t Compact(std::vector<std::uint32_t>& label, std::size_t bound) {
    constexpr std::uint32_t kUnset = std::numeric_limits<std::uint32_t>::max();
    std::vector<std::uint32_t> remap(bound, kUnset);
    std::uint32_t next = 0;
    if (bound > 0) {
        for (auto& l : label) {
            SURFEL_CHECK(l < bound);
            if (remap[l] == kUnset) remap[l] = next++;
            l = remap[l];
        }
        return next;
    }
    for (auto& l : label) {
        if (l >= remap.size()) remap.resize(static_cast<std::size_t>(l) + 1, kUnset);
        if (remap[l] == kUnset) remap[l] = next++;
        l = remap[l];
    }
    return next;
}

namespace {

// ---------------------------------------------------------------------------------------------
// Binary splits shared by hierarchical clustering and AdjustCount.

struct Item {
    Vec3f p;  // relative to the cloud's reference point (better conditioned moments)
    std::uint32_t id;
};
static_assert(sizeof(Item) == 16, "split_pass.h reads items as {float x, y, z; uint32 id}");

Moments MomentsOf(std::span<const Item> items) {
    Moments m;
    for (const Item& it : items) m.Add(it.p);
    return m;
}

// Splits items at the centroid across v2 (notes 2.1.2). Returns the split position (relative to
// items.begin()), or 0 when the set cannot be split (fewer than 2 distinct points).
std::size_t SplitItems(std::span<Item> items, const Moments& m, const Spread& s) {
    if (items.size() < 2 || s.eigenvalues[2] <= 0.0) return 0;
    const Eigen::Vector3d c = m.Centroid();
    const Vec3f cf = c.cast<float>();
    const Vec3f axis = s.v2.cast<float>();
    auto mid = std::partition(items.begin(), items.end(),
                              [&](const Item& it) { return (it.p - cf).dot(axis) < 0.0f; });
    std::size_t k = static_cast<std::size_t>(mid - items.begin());
    if (k == 0 || k == items.size()) {
        // All on one side in float arithmetic: split at the median projection instead.
        k = items.size() / 2;
        std::nth_element(items.begin(), items.begin() + static_cast<std::ptrdiff_t>(k), items.end(),
                         [&](const Item& a, const Item& b) {
                             const float pa = a.p.dot(axis), pb = b.p.dot(axis);
                             return pa < pb || (pa == pb && a.id < b.id);
                         });
        if (items[k].p == items[0].p && items[k].p == items[items.size() - 1].p) return 0;
    }
    return k;
}

// Large scratch arrays (the item buffers, the node lists) are aligned to 2 MiB and offered to the
// kernel for transparent huge pages (madvise; a no-op where THP is off or unavailable): at 362k
// points the two item buffers alone are 11.6 MB, and a fresh process touched them 4 KiB page by page
// (about 2,900 page faults, a sixth of a call's CPU time at 1 %). Smaller ones come from malloc.
void* AllocateLarge(std::size_t bytes) {
    constexpr std::size_t kHuge = std::size_t(2) << 20;
    void* p = nullptr;
    if (bytes >= kHuge) {
        const std::size_t rounded = (bytes + kHuge - 1) / kHuge * kHuge;
        p = std::aligned_alloc(kHuge, rounded);
#if defined(__linux__) && defined(MADV_HUGEPAGE)
        if (p) madvise(p, rounded, MADV_HUGEPAGE);
#endif
    } else {
        p = std::malloc(std::max<std::size_t>(bytes, 1));
    }
    if (!p) throw std::bad_alloc();
    return p;
}

// The allocator of the node lists (AllocateLarge; std::free releases both kinds).
template <typename T>
struct LargeAllocator {
    using value_type = T;
    LargeAllocator() = default;
    template <typename U>
    LargeAllocator(const LargeAllocator<U>&) {}
    T* allocate(std::size_t n) { return static_cast<T*>(AllocateLarge(n * sizeof(T))); }
    void deallocate(T* p, std::size_t) { std::free(p); }
    friend bool operator==(const LargeAllocator&, const LargeAllocator&) { return true; }
};

// An uninitialised item array (every item is written before it is read).
class ItemBuffer {
public:
    explicit ItemBuffer(std::size_t n) : data_(static_cast<Item*>(AllocateLarge(n * sizeof(Item)))) {}
    ~ItemBuffer() { std::free(data_); }
    ItemBuffer(const ItemBuffer&) = delete;
    ItemBuffer& operator=(const ItemBuffer&) = delete;
    Item* get() const { return data_; }

private:
    Item* data_;
};

// A node of the split tree: items[begin, end), their centroid c and scatter S = sum (p - c)(p - c)^T
// (the covariance times n), both computed about the parent's centroid in the parent's split pass,
// so each node's statistics are exact sums over its own items, well conditioned at every depth.
// 104 bytes (it was 200 with a cached Spread): the node lists are written, copied and queued
// by the ten thousand. Only S's lower triangle is kept: Eigen's direct 3x3 solver reads no other
// (selfadjointView<Lower>), so the solves give the bits they gave with the whole matrix.
struct Node {
    std::uint32_t begin = 0, end = 0;
    bool in_scratch = false;  // which of the two item buffers holds items[begin, end) (splits alternate)
    bool has_axis = false;    // `axis` is the split axis v2 (adaptive: from the priority's solve)
    float axis[3] = {1.0f, 0.0f, 0.0f};
    double priority = 0.0;
    double c[3] = {0.0, 0.0, 0.0};
    double S[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0};  // S00, S10, S20, S11, S21, S22
    std::size_t size() const { return end - begin; }
    Eigen::Vector3d Centroid() const { return Eigen::Vector3d(c[0], c[1], c[2]); }
    Eigen::Matrix3d Scatter() const {
        Eigen::Matrix3d m;
        m << S[0], S[1], S[2], S[1], S[3], S[4], S[2], S[4], S[5];
        return m;
    }
};
static_assert(sizeof(Node) == 104);

using NodeList = std::vector<Node, LargeAllocator<Node>>;

Spread AnalyzeScatter(const Eigen::Matrix3d& S, std::size_t n) {
    Spread s;
    if (n < 2) return s;
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver;
    solver.computeDirect(S / static_cast<double>(n));
    s.eigenvalues = solver.eigenvalues().cwiseMax(0.0);
    s.v0 = solver.eigenvectors().col(0);
    s.v2 = solver.eigenvectors().col(2);
    return s;
}

Spread SpreadOf(const Node& node) { return AnalyzeScatter(node.Scatter(), node.size()); }

// The split axis of a node (v2 of S / n) and whether it has a spread at all (largest eigenvalue
// > 0): the operations of Eigen's computeDirect (Eigen 3.4, direct_selfadjoint_eigenvalues<.., 3,
// false>::run) as far as v2, so the bits of AnalyzeScatter's v2 and eigenvalues[2], without the
// eigenvectors a split does not use (one kernel extraction instead of two, no cross product).
bool SplitAxis(const Node& node, Eigen::Vector3d& v2) {
    using Direct = Eigen::internal::direct_selfadjoint_eigenvalues<Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>, 3, false>;
    if (node.size() < 2) return false;
    const Eigen::Matrix3d mat = node.Scatter() / static_cast<double>(node.size());
    const double shift = mat.trace() / 3.0;
    Eigen::Matrix3d scaled = mat.selfadjointView<Eigen::Lower>();
    scaled.diagonal().array() -= shift;
    const double scale = scaled.cwiseAbs().maxCoeff();
    if (scale > 0) scaled /= scale;
    Eigen::Vector3d eivals;
    Direct::computeRoots(scaled, eivals);
    Eigen::Vector3d lambda = eivals;  // the solver's eigenvalues, clamped as AnalyzeScatter does
    lambda *= scale;
    lambda.array() += shift;
    if (lambda.cwiseMax(0.0)[2] <= 0.0) return false;  // all points equal
    if ((eivals(2) - eivals(0)) <= Eigen::NumTraits<double>::epsilon()) {
        v2 = Eigen::Vector3d::UnitZ();  // the solver's identity
        return true;
    }
    Eigen::Matrix3d tmp = scaled, vecs;
    double d0 = eivals(2) - eivals(1);
    const double d1 = eivals(1) - eivals(0);
    Eigen::Index k = 0, l = 2;
    if (d0 > d1) {
        std::swap(k, l);
        d0 = d1;
    }
    tmp.diagonal().array() -= eivals(k);
    Direct::extract_kernel(tmp, vecs.col(k), vecs.col(l));
    if (l == 2) {  // v2 from the saved representative or its own kernel
        if (d0 <= 2 * Eigen::NumTraits<double>::epsilon() * d1) {
            vecs.col(l) -= vecs.col(k).dot(vecs.col(l)) * vecs.col(l);
            vecs.col(l).normalize();
        } else {
            tmp = scaled;
            tmp.diagonal().array() -= eivals(l);
            Eigen::Vector3d dummy;
            Direct::extract_kernel(tmp, vecs.col(l), dummy);
        }
    }
    v2 = vecs.col(2);
    return true;
}

// Uniform: split the largest cluster; its spread (the eigen solve) waits until the node is split
// or becomes a leaf whose normal is wanted, and a node with all points equal (no spread) is found
// out when it is split. Adaptive: weight by surface variation, with a small floor so that flat
// regions are still split by size once curved ones are fine enough.
void Finish(Node& node, bool adaptive) {
    const double n = static_cast<double>(node.size());
    node.has_axis = false;
    if (!adaptive) {
        node.priority = node.size() < 2 ? -1.0 : n;
        return;
    }
    const Spread sp = SpreadOf(node);
    node.has_axis = true;
    for (int k = 0; k < 3; ++k) node.axis[k] = static_cast<float>(sp.v2[k]);
    node.priority = node.size() < 2 || sp.eigenvalues[2] <= 0.0 ? -1.0  // cannot split
                                                                : n * (sp.Variation() + 1e-3);
}

// Sums of d = p - o and d d^T over items (double accumulators), for a node's exact statistics.
struct Sums {
    double n = 0;
    double d[3] = {0, 0, 0};
    double dd[6] = {0, 0, 0, 0, 0, 0};  // xx xy xz yy yz zz
    void Add(const Vec3f& p, const Vec3f& o, double w = 1.0) {
        const double x = double(p.x() - o.x()), y = double(p.y() - o.y()), z = double(p.z() - o.z());
        const double wx = w * x, wy = w * y, wz = w * z;
        n += w;
        d[0] += wx, d[1] += wy, d[2] += wz;
        dd[0] += wx * x, dd[1] += wx * y, dd[2] += wx * z, dd[3] += wy * y, dd[4] += wy * z, dd[5] += wz * z;
    }
    // Centroid and scatter about it, for sums taken about o.
    void To(const Vec3f& o, Node& node) const {
        const Eigen::Vector3d m(d[0] / n, d[1] / n, d[2] / n);
        const Eigen::Vector3d c = o.cast<double>() + m;
        Eigen::Matrix3d S;
        S << dd[0], dd[1], dd[2], dd[1], dd[3], dd[4], dd[2], dd[4], dd[5];
        S -= n * m * m.transpose();
        for (int k = 0; k < 3; ++k) node.c[k] = c[k];
        node.S[0] = S(0, 0), node.S[1] = S(1, 0), node.S[2] = S(2, 0);
        node.S[3] = S(1, 1), node.S[4] = S(2, 1), node.S[5] = S(2, 2);
    }
};

Node MakeNode(std::span<const Item> items, std::uint32_t begin, std::uint32_t end, bool adaptive) {
    Node node;
    node.begin = begin;
    node.end = end;
    if (end > begin) {
        // About the first item (the items are relative to the cloud's mean), by the split pass's
        // kernel: the terms and order of Sums::Add, the same bits.
        const Vec3f o = items[begin].p;
        const float of[3] = {o.x(), o.y(), o.z()};
        double s[9];
        split_pass::Best().sums(items.data() + begin, end - begin, of, s);
        Sums sums;
        sums.n = double(end - begin);
        std::copy(s, s + 3, sums.d), std::copy(s + 3, s + 9, sums.dd);
        sums.To(o, node);
    }
    Finish(node, adaptive);
    return node;
}

// The items (points relative to their mean, a better conditioned frame for the moments) and the
// root node over them. (Adding the root's sums while the items are written, in the same order,
// gave different last bits of the root's scatter: not done, the outputs stay identical.)
Node FillItemsAndRoot(std::span<const Vec3f> points, std::span<Item> items, bool adaptive) {
    Vec3d ref = Vec3d::Zero();
    for (const Vec3f& p : points) ref += p.cast<double>();
    if (!points.empty()) ref /= static_cast<double>(points.size());
    const Vec3f r = ref.cast<float>();
    const auto n = static_cast<std::uint32_t>(points.size());
    for (std::uint32_t i = 0; i < n; ++i) items[i] = {points[i] - r, i};
    return MakeNode(items, 0, n, adaptive);
}

// The buffer that holds a node's items.
std::span<Item> BufferOf(const Node& node, std::span<Item> items, std::span<Item> scratch) {
    return node.in_scratch ? scratch : items;
}

// Splits `node` at its centroid across v2 (notes 2.1.2) in one pass over its items: the side
// test, a branch-free partition into the other buffer (the same index range: concurrent splits of
// disjoint nodes never share it; the children live there, so nothing is copied back), and each
// child's sums about the node's centroid over its own items (exact statistics at every depth:
// deriving one side as the node's minus the other's doubles the centroid's error at every level).
// Each side's sums add its own items' terms in the order they are visited (split_pass.h: an AVX2
// build and a baseline one, the same bits).
bool SplitNode(std::span<Item> items, std::span<Item> scratch, Node& node, bool adaptive, Node& left, Node& right) {
    if (node.priority < 0) return false;
    Vec3f axis(node.axis[0], node.axis[1], node.axis[2]);
    if (!node.has_axis) {  // adaptive nodes that cannot split have priority < 0
        Eigen::Vector3d v2;
        if (!SplitAxis(node, v2)) return false;  // all points equal
        axis = v2.cast<float>();
    }
    const Vec3f c = node.Centroid().cast<float>();
    const std::span<Item> src = BufferOf(node, items, scratch);
    const std::span<Item> dst = node.in_scratch ? items : scratch;
    // The side test as p . axis < c . axis (one dot product a point); the sums about c.
    const float o[3] = {c.x(), c.y(), c.z()}, ax[3] = {axis.x(), axis.y(), axis.z()};
    double sums[18];
    std::uint32_t k = split_pass::Best().split(src.data() + node.begin, node.end - node.begin, dst.data() + node.begin,
                                               o, ax, c.dot(axis), sums);
    const std::uint32_t size = node.end - node.begin;
    if (k == 0 || k == size) {
        // All on one side in float arithmetic: split at the median projection instead (in the
        // node's own buffer).
        std::span<Item> span = src.subspan(node.begin, size);
        k = size / 2;
        std::nth_element(span.begin(), span.begin() + k, span.end(), [&](const Item& a, const Item& b) {
            const float pa = a.p.dot(axis), pb = b.p.dot(axis);
            return pa < pb || (pa == pb && a.id < b.id);
        });
        if (span[k].p == span[0].p && span[k].p == span[size - 1].p) return false;
        left = MakeNode(src, node.begin, node.begin + k, adaptive);
        right = MakeNode(src, node.begin + k, node.end, adaptive);
        left.in_scratch = right.in_scratch = node.in_scratch;
        return true;
    }
    Sums neg, pos;
    neg.n = double(k), pos.n = double(size - k);
    std::copy(sums, sums + 3, neg.d), std::copy(sums + 3, sums + 9, neg.dd);
    std::copy(sums + 9, sums + 12, pos.d), std::copy(sums + 12, sums + 18, pos.dd);
    left.begin = node.begin, left.end = node.begin + k;
    right.begin = node.begin + k, right.end = node.end;
    left.in_scratch = right.in_scratch = !node.in_scratch;
    neg.To(c, left);
    pos.To(c, right);
    Finish(left, adaptive);
    Finish(right, adaptive);
    return true;
}

double MaxPlaneDistance(std::span<const Item> items, const Node& node) {
    const Vec3f c = node.Centroid().cast<float>();
    const Vec3f n = SpreadOf(node).v0.cast<float>();
    double d = 0.0;
    for (std::uint32_t i = node.begin; i < node.end; ++i) d = std::max(d, std::abs(double((items[i].p - c).dot(n))));
    return d;
}

// Each leaf's points labelled, numbered by their smallest input index (the numbering Compact gives:
// it depends only on which points share a leaf, not on the order the leaves are visited in); each
// cluster's normal is its covariance's v0 (notes 1.2: the direction of least variation of the
// cluster's points), unoriented. The leaves are disjoint, so both passes run in parallel: each
// point gets its leaf's index (and each leaf its smallest input index), then the leaves' ranks by
// smallest input index replace the indices.
Clustering LabelsFromNodes(std::span<const Item> items, std::span<const Item> scratch, const NodeList& leaves,
                           std::size_t n, bool normals) {
    const auto buffer = [&](const Node& leaf) { return leaf.in_scratch ? scratch : items; };
    Clustering out;
    out.label.resize(n);
    const std::size_t m = leaves.size();
    std::vector<std::uint64_t> first(m);  // (smallest input index << 32) | leaf; empty leaves last
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 256), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t c = r.begin(); c != r.end(); ++c) {
            const Node& leaf = leaves[c];
            const std::span<const Item> buf = buffer(leaf);
            std::uint32_t lowest = std::numeric_limits<std::uint32_t>::max();
            for (std::uint32_t i = leaf.begin; i < leaf.end; ++i) {
                out.label[buf[i].id] = static_cast<std::uint32_t>(c);
                lowest = std::min(lowest, buf[i].id);
            }
            first[c] = (std::uint64_t(leaf.size() ? lowest : std::numeric_limits<std::uint32_t>::max()) << 32) | c;
        }
    });
    tbb::parallel_sort(first.begin(), first.end());  // distinct keys: one order whatever the threads
    std::vector<std::uint32_t> rank(m);
    out.count = 0;
    for (std::size_t k = 0; k < m; ++k) {
        const auto c = static_cast<std::uint32_t>(first[k]);
        rank[c] = static_cast<std::uint32_t>(k);
        out.count += leaves[c].size() > 0;
    }
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 16384), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i) out.label[i] = rank[out.label[i]];
    });
    if (!normals) return out;
    // Compact numbers clusters by their smallest input index; normals follow that numbering (each
    // leaf writes its own cluster's, in parallel).
    out.normals.assign(out.count, Vec3f::Zero());
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, leaves.size(), 256), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t c = r.begin(); c != r.end(); ++c) {
            const Node& leaf = leaves[c];
            if (leaf.size() == 0) continue;
            const Spread sp = SpreadOf(leaf);
            // A normal needs a patch: leave small (under 5 points), elongated (lambda_1 < lambda_2 / 10)
            // or thick (lambda_0 > lambda_1 / 2) clusters to the caller's estimate (zero here).
            const bool planar = leaf.size() >= 5 && sp.eigenvalues[1] > 0.1 * sp.eigenvalues[2] &&
                                sp.eigenvalues[0] < 0.5 * sp.eigenvalues[1];
            out.normals[out.label[buffer(leaf)[leaf.begin].id]] = planar ? Vec3f(sp.v0.cast<float>()) : Vec3f::Zero();
        }
    });
    return out;
}

// Phase 1 of the uniform priority queue: every splittable node larger than `threshold` split,
// subtrees in parallel. The uniform queue pops nodes in order of non-increasing size (children
// are smaller than their parent), so while fewer than the target clusters exist it splits every
// node above any size it has not reached yet: the queue run from these leaves gives the clusters
// the queue run from the root gives, whatever the thread count.
void SplitAbove(std::span<Item> items, std::span<Item> scratch, Node node, std::size_t threshold,
                tbb::enumerable_thread_specific<NodeList>& leaves) {
    while (node.size() > threshold) {
        Node a, b;
        if (!SplitNode(items, scratch, node, false, a, b)) break;
        if (b.size() > threshold && b.size() >= 4096) {
            tbb::parallel_invoke([&] { SplitAbove(items, scratch, a, threshold, leaves); },
                                 [&] { SplitAbove(items, scratch, b, threshold, leaves); });
            return;
        }
        SplitAbove(items, scratch, b, threshold, leaves);
        node = a;
    }
    leaves.local().push_back(node);
}

// Phase 2 of the uniform priority queue, without the queue. Uniform priorities are sizes and a
// child is smaller than its parent, so the queue pops every node of one size (in order of first
// item, its tie-break) before any smaller one, and all nodes of that size exist when the first of
// them is popped. So the queue splits whole size classes, the largest first, and of the class where
// the count reaches the target the first (target - count) by first item, skipping nodes that
// cannot be split (all points equal) as the queue does. The splits of one batch touch disjoint
// item ranges and nodes and run in parallel; the second children join `nodes` in the batch's
// order. The same clusters as the queue, whatever the thread count.
void SplitBySizeClass(std::span<Item> items, std::span<Item> scratch, NodeList& nodes, std::size_t target,
                      ProgressTracker& progress) {
    // size -> (first item << 32 | node index) of the nodes of that size
    std::map<std::uint32_t, std::vector<std::uint64_t>, std::greater<>> by_size;
    const auto add = [&](std::uint32_t i) {
        if (nodes[i].size() >= 2)
            by_size[static_cast<std::uint32_t>(nodes[i].size())].push_back(std::uint64_t(nodes[i].begin) << 32 | i);
    };
    for (std::uint32_t i = 0; i < nodes.size(); ++i) add(i);
    std::size_t count = nodes.size();
    std::vector<Node> second;
    std::vector<char> split;
    while (count < target && !by_size.empty()) {
        std::vector<std::uint64_t> batch = std::move(by_size.begin()->second);
        by_size.erase(by_size.begin());
        std::sort(batch.begin(), batch.end());  // by first item
        for (std::size_t next = 0; next < batch.size() && count < target;) {
            const std::size_t take = std::min(batch.size() - next, target - count);
            second.resize(take);
            split.assign(take, 0);
            tbb::parallel_for(tbb::blocked_range<std::size_t>(0, take, 64), [&](const tbb::blocked_range<std::size_t>& r) {
                for (std::size_t j = r.begin(); j != r.end(); ++j) {
                    Node& node = nodes[static_cast<std::uint32_t>(batch[next + j])];
                    Node a;
                    if (!SplitNode(items, scratch, node, false, a, second[j])) continue;  // stays a leaf
                    node = a;
                    split[j] = 1;
                }
            });
            for (std::size_t j = 0; j < take; ++j) {
                if (!split[j]) continue;
                const auto a = static_cast<std::uint32_t>(batch[next + j]), b = static_cast<std::uint32_t>(nodes.size());
                nodes.push_back(second[j]);
                add(a), add(b);
                ++count;
            }
            progress.Advance(0.5 * static_cast<double>(take) / static_cast<double>(target));
            next += take;
        }
    }
}

}  // namespace

Clustering HierarchicalClustering(std::span<const Vec3f> points, const SimplifyOptions& options,
                                  ProgressTracker& progress) {
    const auto n = static_cast<std::uint32_t>(points.size());
    // The two item buffers, not zeroed first (every item is written before it is read).
    const ItemBuffer item_buffer(n), scratch_buffer(n);
    const std::span<Item> items(item_buffer.get(), n), scratch(scratch_buffer.get(), n);
    const Node root = FillItemsAndRoot(points, items, options.adaptive);
    NodeList leaves;
    if (options.target > 0) {
        // Priority-queue variant (notes 2.1.2, [BW00, SG01]): always split the cluster of highest
        // priority until there are exactly `target` clusters. The queue holds indices into `nodes`.
        NodeList nodes;
        nodes.reserve(options.target + 1);  // the queue ends with target nodes: no regrowth
        if (!options.adaptive) {
            // Uniform: phase 1 in parallel up to a size the queue surely passes (leaves of at
            // most 2.5 n / target points, which makes at most about target / 1.7 clusters).
            const std::size_t threshold = std::max<std::size_t>(16, 5 * std::size_t(n) / (2 * options.target));
            // Room for every leaf in each thread's list (address space only: the pages are touched
            // as it fills), so no list is copied as it grows.
            tbb::enumerable_thread_specific<NodeList> local([&] {
                NodeList v;
                v.reserve(options.target + 1);
                return v;
            });
            SplitAbove(items, scratch, root, threshold, local);
            for (auto& l : local) nodes.insert(nodes.end(), l.begin(), l.end());
            if (nodes.size() > options.target) {  // an unbalanced cloud overshot: start over
                nodes.assign(1, FillItemsAndRoot(points, items, false));
            }
            progress.Advance(0.5);
        } else {
            nodes.push_back(root);
        }
        if (!options.adaptive) {
            SplitBySizeClass(items, scratch, nodes, options.target, progress);
        } else {
            // The node's first item rides in the entry (a node's range does not change while it is
            // queued): the tie-break of equal priorities, frequent with sizes, reads no node.
            struct Entry {
                double priority;
                std::uint32_t begin, node;
            };
            const auto by_priority = [](const Entry& a, const Entry& b) {
                if (a.priority != b.priority) return a.priority < b.priority;
                return a.begin > b.begin;  // deterministic tie-break
            };
            std::vector<Entry> heap;
            heap.reserve(options.target + 1);
            for (std::uint32_t i = 0; i < nodes.size(); ++i) heap.push_back({nodes[i].priority, nodes[i].begin, i});
            std::make_heap(heap.begin(), heap.end(), by_priority);
            std::size_t done_since_check = 0, count = heap.size();
            while (!heap.empty() && count < options.target) {
                std::pop_heap(heap.begin(), heap.end(), by_priority);
                const std::uint32_t top = heap.back().node;
                heap.pop_back();
                Node a, b;
                if (!SplitNode(items, scratch, nodes[top], options.adaptive, a, b)) continue;  // stays a leaf
                nodes[top] = a;
                nodes.push_back(b);
                heap.push_back({a.priority, a.begin, top});
                std::push_heap(heap.begin(), heap.end(), by_priority);
                heap.push_back({b.priority, b.begin, static_cast<std::uint32_t>(nodes.size() - 1)});
                std::push_heap(heap.begin(), heap.end(), by_priority);
                ++count;
                if (++done_since_check == 4096) {
                    progress.Advance(0.5 * 4096.0 / static_cast<double>(options.target));
                    done_since_check = 0;
                }
            }
        }
        // Every node is a leaf now (split ones were replaced by their first child): the queued
        // ones and those that could not be split. No copy: LabelsFromNodes takes them in any order.
        leaves = std::move(nodes);
    } else {
        // Recursive variant: split while larger than n_max, more varied than sigma_max
        // (adaptive) or farther from the cluster plane than the error bound.
        const std::size_t n_max = options.max_cluster_size;
        NodeList stack{root};
        std::size_t covered = 0;
        while (!stack.empty()) {
            Node node = std::move(stack.back());
            stack.pop_back();
            bool split = node.size() > n_max;
            if (!split && options.adaptive) split = SpreadOf(node).Variation() > options.max_variation;
            if (!split && options.error > 0) split = MaxPlaneDistance(BufferOf(node, items, scratch), node) > options.error;
            Node a, b;
            if (split && SplitNode(items, scratch, node, options.adaptive, a, b)) {
                stack.push_back(std::move(b));
                stack.push_back(std::move(a));
                continue;
            }
            covered += node.size();
            if (leaves.size() % 4096 == 0) progress.Advance(static_cast<double>(covered) / n), covered = 0;
            leaves.push_back(std::move(node));
        }
    }
    return LabelsFromNodes(items, scratch, leaves, n, !options.positions_only);
}

// ---------------------------------------------------------------------------------------------

void AdjustCount(std::span<const Vec3f> points, Clustering& clusters, std::size_t target, bool adaptive) {
    if (clusters.count == target || target == 0) return;
    const std::size_t m = clusters.count;
    std::vector<Moments> moments(m);
    for (std::size_t i = 0; i < points.size(); ++i) moments[clusters.label[i]].Add(points[i]);

    if (m > target) {
        std::vector<double> weight(m);
        for (std::size_t c = 0; c < m; ++c)
            weight[c] = moments[c].n * (adaptive ? Analyze(moments[c]).Variation() + 1e-3 : 1.0);
        std::vector<std::uint32_t> order(m);
        std::iota(order.begin(), order.end(), 0u);
        std::sort(order.begin(), order.end(), [&](std::uint32_t a, std::uint32_t b) {
            return weight[a] != weight[b] ? weight[a] < weight[b] : a < b;
        });
        std::vector<char> dissolved(m, 0);
        for (std::size_t i = 0; i < m - target; ++i) dissolved[order[i]] = 1;
        std::vector<Vec3f> centroids;
        std::vector<std::uint32_t> survivor;
        for (std::uint32_t c = 0; c < m; ++c)
            if (!dissolved[c]) {
                centroids.push_back(moments[c].Centroid().cast<float>());
                survivor.push_back(c);
            }
        const KdTree tree(centroids);
        for (std::size_t i = 0; i < points.size(); ++i)
            if (dissolved[clusters.label[i]]) clusters.label[i] = survivor[tree.Nearest(points[i]).index];
        clusters.count = Compact(clusters.label);
        return;
    }

    // Too few: split the largest clusters.
    std::vector<std::vector<Item>> members(m);
    for (std::size_t i = 0; i < points.size(); ++i)
        members[clusters.label[i]].push_back({points[i], static_cast<std::uint32_t>(i)});
    using Entry = std::pair<std::size_t, std::uint32_t>;  // (size, cluster)
    std::priority_queue<Entry> queue;
    for (std::uint32_t c = 0; c < m; ++c) queue.push({members[c].size(), c});
    while (members.size() < target && !queue.empty()) {
        const std::uint32_t c = queue.top().second;
        queue.pop();
        auto& items = members[c];
        const Moments mom = MomentsOf(items);
        const std::size_t k = SplitItems(items, mom, Analyze(mom));
        if (k == 0) continue;
        std::vector<Item> second(items.begin() + static_cast<std::ptrdiff_t>(k), items.end());
        items.resize(k);
        const auto d = static_cast<std::uint32_t>(members.size());
        members.push_back(std::move(second));
        queue.push({members[c].size(), c});
        queue.push({members[d].size(), d});
    }
    for (std::uint32_t c = 0; c < members.size(); ++c)
        for (const Item& it : members[c]) clusters.label[it.id] = c;
    clusters.count = Compact(clusters.label);
}

// ---------------------------------------------------------------------------------------------
// Incremental clustering (notes 2.1.1).

namespace {

struct GrowParams {
    std::size_t n_max;
    double sigma_max;  // <= 0: no variation bound
};

Clustering GrowClusters(std::span<const Vec3f> points, const KnnTable& graph, const GrowParams& params,
                        std::uint64_t seed) {
    const std::size_t n = points.size();
    constexpr std::uint32_t kNone = std::numeric_limits<std::uint32_t>::max();
    std::vector<std::uint32_t> label(n, kNone), pushed(n, kNone);
    std::vector<Moments> moments;
    std::vector<double> variation;
    std::vector<std::uint32_t> frontier;  // seeds for the next clusters: neighbours of finished ones
    std::size_t frontier_head = 0, scan = 0;
    Random rng(seed);
    std::uint32_t seed_point = static_cast<std::uint32_t>(rng.Index(n));
    using Candidate = std::pair<float, std::uint32_t>;
    std::priority_queue<Candidate, std::vector<Candidate>, std::greater<>> heap;
    for (;;) {
        // Next seed: a neighbour of an earlier cluster, else the next unassigned point.
        while (seed_point == kNone || label[seed_point] != kNone) {
            if (frontier_head < frontier.size()) {
                seed_point = frontier[frontier_head++];
                continue;
            }
            while (scan < n && label[scan] != kNone) ++scan;
            if (scan == n) break;
            seed_point = static_cast<std::uint32_t>(scan);
        }
        if (seed_point == kNone || label[seed_point] != kNone) break;
        const auto c = static_cast<std::uint32_t>(moments.size());
        Moments m;
        double sigma = 0.0;
        heap = {};
        heap.push({0.0f, seed_point});
        pushed[seed_point] = c;
        const Vec3f s = points[seed_point];
        while (!heap.empty() && m.n < static_cast<double>(params.n_max)) {
            const std::uint32_t i = heap.top().second;
            heap.pop();
            if (label[i] != kNone) continue;
            if (params.sigma_max > 0 && m.n >= 3) {
                Moments trial = m;
                trial.Add(points[i]);
                const double v = Analyze(trial).Variation();
                if (v > params.sigma_max) {
                    sigma = v;  // stopped by the variation bound: this cluster reached it
                    break;
                }
                m = trial;
                sigma = v;
            } else {
                m.Add(points[i]);
            }
            label[i] = c;
            for (const std::uint32_t j : graph.Row(i))
                if (label[j] == kNone && pushed[j] != c) {
                    pushed[j] = c;
                    heap.push({(points[j] - s).squaredNorm(), j});
                }
        }
        while (!heap.empty()) {
            const std::uint32_t j = heap.top().second;
            heap.pop();
            if (label[j] == kNone) frontier.push_back(j);
        }
        moments.push_back(m);
        variation.push_back(sigma);
        seed_point = kNone;
    }

    // Stray clusters (below half of both bounds) go to the cluster with the closest centroid.
    const std::size_t m = moments.size();
    std::vector<char> stray(m, 0);
    std::vector<Vec3f> centroids;
    std::vector<std::uint32_t> keep;
    for (std::uint32_t c = 0; c < m; ++c) {
        const bool small = moments[c].n < 0.5 * static_cast<double>(params.n_max);
        const bool flat = params.sigma_max <= 0 || variation[c] < 0.5 * params.sigma_max;
        stray[c] = small && flat;
        if (!stray[c]) {
            centroids.push_back(moments[c].Centroid().cast<float>());
            keep.push_back(c);
        }
    }
    if (!keep.empty() && keep.size() < m) {
        const KdTree tree(centroids);
        for (std::size_t i = 0; i < n; ++i)
            if (stray[label[i]]) label[i] = keep[tree.Nearest(points[i]).index];
    }
    Clustering out;
    out.label = std::move(label);
    out.count = Compact(out.label);
    return out;
}

}  // namespace

namespace {

// Searches a parameter for a target count when the count falls as the parameter grows and goes
// about as parameter^slope (the voxel method's cell size: -2 on a surface; incremental
// clustering's n_max: -1), on log(parameter) against log(count). `lo` and `hi` bracket it: at
// lo the count is at least the target, at hi below it (assumed until measured). While only one
// side has been measured, Next() follows the slope through the last two measurements (the
// given slope before there are two; it may then leave the bracket: the caller decides); then
// regula falsi between lo and hi, Illinois variant (an end that stays again has its distance
// to the target halved each time, so that a one-sided approach still closes in), the midpoint
// where that would land within 2 % of either end (a count at the target has no slope to follow).
class LogCountSearch {
public:
    LogCountSearch(double lo, double hi, std::size_t target, double slope)
        : lo_(lo), hi_(hi), log_target_(std::log(static_cast<double>(target))), target_(target),
          default_slope_(slope), slope_(slope) {}
    double lo() const { return lo_; }
    double hi() const { return hi_; }
    /// Only counts at or above the target measured so far.
    bool OnlyAtLeast() const { return lo_measured_ && !hi_measured_; }

    /// The count at log parameter x.
    void Measure(double x, std::size_t count) {
        const double log_count = std::log(std::max<double>(1.0, static_cast<double>(count)));
        if (count >= target_) {
            lo_ = x;
            log_lo_count_ = log_count;
            lo_measured_ = true;
            ++hi_kept_;
            lo_kept_ = 0;
        } else {
            hi_ = x;
            log_hi_count_ = log_count;
            hi_measured_ = true;
            ++lo_kept_;
            hi_kept_ = 0;
        }
        slope_ = default_slope_;
        if (measured_ > 0 && x != last_x_ && log_count != last_log_count_)
            slope_ = std::min(-0.05, (log_count - last_log_count_) / (x - last_x_));
        last_x_ = x;
        last_log_count_ = log_count;
        ++measured_;
    }

    /// The log parameter to measure next.
    double Next() const {
        if (lo_measured_ != hi_measured_) return last_x_ + (log_target_ - last_log_count_) / slope_;
        const double dl = std::ldexp(log_lo_count_ - log_target_, -std::max(0, lo_kept_ - 1));
        const double dh = std::ldexp(log_target_ - log_hi_count_, -std::max(0, hi_kept_ - 1));
        const double f = dl + dh > 0 ? dl / (dl + dh) : 0.5;
        return lo_ + (hi_ - lo_) * (f > 0.02 && f < 0.98 ? f : 0.5);
    }

private:
    double lo_, hi_, log_target_;
    std::size_t target_;
    double default_slope_, slope_;
    double log_lo_count_ = 0.0, log_hi_count_ = 0.0, last_x_ = 0.0, last_log_count_ = 0.0;
    bool lo_measured_ = false, hi_measured_ = false;
    int lo_kept_ = 0, hi_kept_ = 0;  // measurements in a row the end has stayed where it was
    int measured_ = 0;
};

}  // namespace

Clustering IncrementalClustering(std::span<const Vec3f> points, const SimplifyOptions& options,
                                 ProgressTracker& progress) {
    const std::size_t n = points.size();
    const KdTree tree(points);
    const KnnTable graph = tree.KnnAll(std::max(2, std::min<int>(options.neighbors, static_cast<int>(n) - 1)));
    progress.Advance(0.1);
    if (options.target == 0) {
        GrowParams params{options.max_cluster_size,
                          options.adaptive ? options.max_variation : 0.0};
        Clustering c = GrowClusters(points, graph, params, options.seed);
        progress.Advance(0.9);
        return c;
    }
    // Exact target: search the bound whose clustering comes closest from above, then dissolve
    // the surplus smallest clusters into their neighbours.
    const double mean = static_cast<double>(n) / static_cast<double>(options.target);
    Clustering best;
    best.label.resize(n);
    std::iota(best.label.begin(), best.label.end(), 0u);
    best.count = n;
    // The size bound n_max is searched; the adaptive variant keeps its variation bound sigma_max
    // throughout, so curved regions get smaller clusters at every n_max.
    const double sigma_max = options.adaptive ? options.max_variation : 0.0;
    auto consider = [&](Clustering c) {
        if (c.count >= options.target && c.count < best.count) best = std::move(c);
    };
    // The count goes about as n / n_max (the clusters grow to n_max nearly always). The search
    // (LogCountSearch, slope -1, from the mean cluster size n / target) finds the largest n_max in
    // [1, 4 mean + 2) whose count is at least the target, as the bisection before it did (where
    // the count falls with n_max, the same n_max and so the same clustering), in fewer passes. A
    // guess on an end takes its neighbour inside (or, below the sizes measured at or above the
    // target, twice the largest), and after 8 passes the search bisects. Session 16: the
    // bisection's 6-9 region growings were ~60 % of the method's CPU on the merged scans; this
    // takes 2-3 there.
    constexpr int kSteps = 24;
    std::size_t lo = 1, hi = static_cast<std::size_t>(4.0 * mean) + 2;
    LogCountSearch search(std::log(static_cast<double>(lo)), std::log(static_cast<double>(hi)), options.target, -1.0);
    std::size_t mid = std::clamp<std::size_t>(static_cast<std::size_t>(std::llround(mean)), lo + 1,
                                              std::max(lo + 1, hi - 1));
    for (int s = 0; s < kSteps && lo + 1 < hi; ++s) {
        Clustering c = GrowClusters(points, graph, {mid, sigma_max}, options.seed);
        search.Measure(std::log(static_cast<double>(mid)), c.count);
        if (c.count >= options.target) {
            lo = mid;
            consider(std::move(c));
        } else {
            hi = mid;
        }
        progress.Advance(0.8 / kSteps);
        if (lo + 1 >= hi) break;
        std::size_t next = static_cast<std::size_t>(std::llround(std::exp(std::clamp(search.Next(), -1.0, 60.0))));
        // Measured only at or above the target and told to stay (a count flat at the target, as
        // for the few largest clusters): twice as large. Otherwise a guess on an end takes its
        // neighbour inside.
        if (search.OnlyAtLeast() && next <= lo) next = 2 * lo;
        next = std::clamp(next, lo + 1, hi - 1);
        if (s >= 8) next = (lo + hi) / 2;
        mid = next;
    }
    AdjustCount(points, best, options.target, options.adaptive);
    return best;
}

// ---------------------------------------------------------------------------------------------
// Voxel grid baseline.

namespace {

// Open-addressing map from cell key to a dense index.
class CellMap {
public:
    explicit CellMap(std::size_t n) {
        std::size_t cap = 16;
        while (cap < 2 * n + 1) cap <<= 1;
        keys_.assign(cap, kEmpty);
        values_.resize(cap);
        mask_ = cap - 1;
    }
    std::uint32_t Insert(std::uint64_t key) {
        std::uint64_t h = (key * 0x9E3779B97F4A7C15ull) >> 17;
        for (;; ++h) {
            const std::size_t slot = h & mask_;
            if (keys_[slot] == key) return values_[slot];
            if (keys_[slot] == kEmpty) {
                keys_[slot] = key;
                return values_[slot] = size_++;
            }
        }
    }
    std::uint32_t size() const { return size_; }

private:
    static constexpr std::uint64_t kEmpty = ~0ull;
    std::vector<std::uint64_t> keys_;
    std::vector<std::uint32_t> values_;
    std::size_t mask_ = 0;
    std::uint32_t size_ = 0;
};

std::uint64_t CellKey(const Vec3f& p, const Vec3f& origin, double inv) {
    const auto q = [&](int a) {
        return static_cast<std::uint64_t>(static_cast<std::int64_t>(std::floor((p[a] - origin[a]) * inv))) & 0x1FFFFF;
    };
    return (q(0) << 42) | (q(1) << 21) | q(2);
}

Clustering VoxelLabels(std::span<const Vec3f> points, const Vec3f& origin, double cell) {
    CellMap map(points.size());
    Clustering c;
    c.label.resize(points.size());
    const double inv = 1.0 / cell;
    for (std::size_t i = 0; i < points.size(); ++i) c.label[i] = map.Insert(CellKey(points[i], origin, inv));
    c.count = map.size();
    return c;
}

}  // namespace

Clustering VoxelClustering(std::span<const Vec3f> points, const SimplifyOptions& options, ProgressTracker& progress) {
    BoundingBox box;
    for (const Vec3f& p : points) box.Extend(p);
    const double diag = std::max(1e-30, static_cast<double>(box.Diagonal()));
    // Cells are at least diag / 2^20 so that keys fit 21 bits per axis.
    const double min_cell = diag / 1.0e6;
    const std::size_t target = options.target;
    if (target == 0) throw Error(ErrorCode::kInvalidArgument, "voxel simplification needs --target");
    // The smallest count not below the target, searched on the cell size (LogCountSearch: a
    // surface's count goes about as cell^-2), from the size where a surface as wide as the box's
    // diagonal would hold the target; a guess outside the bracket takes its middle. The count is
    // not monotone in the size near the target (the cells' alignment moves it by a few tenths of
    // a per cent), so the search stops within 0.25 % above the target or once the two sizes
    // agree to 0.1 %, and keeps the smallest count it saw at or above the target; AdjustCount
    // merges the rest. Session 16: plain bisection took about 15 passes over the points, up to
    // 41 (about half the voxel method's time on the merged scans); this takes 2-8.
    constexpr double kSettled = 1e-3;  // sizes 0.1 % apart: the count moves by the cells' alignment
    LogCountSearch search(std::log(min_cell), std::log(diag * 2.0), target, -2.0);
    Clustering best;
    best.count = std::numeric_limits<std::size_t>::max();
    double next = std::clamp(std::log(diag / std::sqrt(static_cast<double>(target))), search.lo(), search.hi());
    for (int s = 0; s < 40 && search.hi() - search.lo() > kSettled; ++s) {
        Clustering c = VoxelLabels(points, box.min, std::exp(next));
        search.Measure(next, c.count);
        if (c.count >= target) {
            if (c.count < best.count) best = std::move(c);
            if (best.count <= target + target / 400) break;
        }
        next = search.Next();
        if (!(next > search.lo() && next < search.hi())) next = 0.5 * (search.lo() + search.hi());
        progress.Advance(0.02);
    }
    if (best.count == std::numeric_limits<std::size_t>::max()) best = VoxelLabels(points, box.min, min_cell);
    best.count = Compact(best.label);
    AdjustCount(points, best, target, false);
    return best;
}

}  // namespace surfel::detail
