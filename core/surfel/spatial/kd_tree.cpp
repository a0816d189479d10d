#include "surfel/spatial/kd_tree.h"

#include <tbb/blocked_range.h>
#include <tbb/global_control.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>

#include <algorithm>
#include <array>
#include <limits>
#include <map>
#include <sstream>

#include "surfel/base/error.h"

#if defined(__SANITIZE_THREAD__)
#define SURFEL_UNDER_TSAN 1
#elif defined(__has_feature)
#if __has_feature(thread_sanitizer)
#define SURFEL_UNDER_TSAN 1
#endif
#endif

namespace surfel {
namespace {

#if defined(SURFEL_UNDER_TSAN)
// Under ThreadSanitizer only (make tsan-test; docs/testing.md): Debian's libtbb is not
// instrumented, so the hand-off from a TBB worker's parallel_for body back to the caller is
// invisible to TSan, and every later write to memory a worker touched (a stack slot, a freed
// vector) is reported as a race. Run every TBB loop on its calling thread instead: the races TSan
// is here for, between the job manager's, gRPC's and the HTTP front's own threads, are untouched,
// and results do not depend on the thread count (tests assert that separately). This object is in
// kd_tree.cpp because every binary that runs a TBB loop links the k-d tree.
const tbb::global_control tsan_serial_tbb(tbb::global_control::max_allowed_parallelism, 1);
#endif

// Points per leaf at most (a leaf's points are contiguous, scanned without branches per node).
constexpr std::uint32_t kLeafSize = 12;
// Subtrees at least this large are built in parallel (disjoint ranges, fixed node numbers: the
// same tree whatever the thread count).
constexpr std::uint32_t kParallelBuild = 32768;

// Squared distance, summed x, y, z in this order (as FLANN's L2_Simple did: the same floats).
inline float Dist2(const float* a, const Vec3f& q) {
    const float dx = a[0] - q.x(), dy = a[1] - q.y(), dz = a[2] - q.z();
    return dx * dx + dy * dy + dz * dz;
}

// A cell's lower bound may round a hair above a point's own rounded distance: prune only clearly.
constexpr float kPruneSlack = 1.0f + 1e-5f;

}  // namespace

// The tree: nodes in depth-first order (a node's left child follows it), every split at the
// median of the widest side of the node's box, so the shape depends on the count alone; the
// points reordered leaf by leaf (`xyz`, with `order` back to the input's indices).
struct KdTree::Impl {
    struct Node {
        // Inner: split dimension 0..2, split value, right child (the left one is this + 1).
        // Leaf: dim 3, points [begin, end) of xyz / order.
        std::uint32_t dim;
        float split;
        std::uint32_t a, b;  // inner: right child, unused; leaf: begin, end
    };
    std::vector<Vec3f> points;         // the input, in its order (points())
    std::vector<float> xyz;            // reordered, 3 floats a point
    std::vector<std::uint32_t> order;  // xyz's point -> input index
    std::vector<Node> nodes;

    static std::uint32_t NodeCount(std::uint32_t count, std::map<std::uint32_t, std::uint32_t>& memo) {
        if (count <= kLeafSize) return 1;
        const auto it = memo.find(count);
        if (it != memo.end()) return it->second;
        const std::uint32_t c = 1 + NodeCount(count / 2, memo) + NodeCount(count - count / 2, memo);
        memo.emplace(count, c);
        return c;
    }

    // A point while building: its coordinates and input index side by side (the median search
    // then walks contiguous memory).
    struct Item {
        float c[3];
        std::uint32_t index;
    };

    // Builds the subtree of items [begin, end) as node `id`; `sizes` gives each count's node count.
    // `lo`, `hi`: a box around the items (the root's bounding box, cut by the splits above: the
    // widest side of that box picks the split dimension).
    void BuildNode(std::vector<Item>& items, std::uint32_t id, std::uint32_t begin, std::uint32_t end,
                   const std::map<std::uint32_t, std::uint32_t>& sizes, std::array<float, 3> lo, std::array<float, 3> hi) {
        Node& nd = nodes[id];
        if (end - begin <= kLeafSize) {
            nd = {3, 0.0f, begin, end};
            return;
        }
        int dim = 0;
        if (hi[1] - lo[1] > hi[dim] - lo[dim]) dim = 1;
        if (hi[2] - lo[2] > hi[dim] - lo[dim]) dim = 2;
        const std::uint32_t mid = begin + (end - begin) / 2;
        // The median by (coordinate, index): a total order, so the split does not depend on the
        // partial order std::nth_element leaves.
        std::nth_element(items.begin() + begin, items.begin() + mid, items.begin() + end,
                         [dim](const Item& x, const Item& y) {
                             return x.c[dim] < y.c[dim] || (x.c[dim] == y.c[dim] && x.index < y.index);
                         });
        const float split = items[mid].c[dim];
        const std::uint32_t left_nodes = (mid - begin) <= kLeafSize ? 1 : sizes.at(mid - begin);
        const std::uint32_t right = id + 1 + left_nodes;
        nd = {static_cast<std::uint32_t>(dim), split, right, 0};
        std::array<float, 3> left_hi = hi, right_lo = lo;
        left_hi[dim] = split;
        right_lo[dim] = split;
        if (end - begin >= kParallelBuild) {
            tbb::parallel_invoke([&] { BuildNode(items, id + 1, begin, mid, sizes, lo, left_hi); },
                                 [&] { BuildNode(items, right, mid, end, sizes, right_lo, hi); });
        } else {
            BuildNode(items, id + 1, begin, mid, sizes, lo, left_hi);
            BuildNode(items, right, mid, end, sizes, right_lo, hi);
        }
    }

        // k nearest, kept sorted by insertion into a caller-owned buffer (ties by index: deterministic).
    struct KnnVisit {
        const Impl* t;
        const Vec3f& q;
        Neighbor* buf;
        std::size_t k, count = 0;
        float worst = std::numeric_limits<float>::infinity();
        float Worst() const { return worst; }
        void Leaf(std::uint32_t begin, std::uint32_t end) {
            for (std::uint32_t i = begin; i < end; ++i) {
                const float d = Dist2(&t->xyz[3 * static_cast<std::size_t>(i)], q);
                if (count == k && d > worst) continue;
                const std::uint32_t idx = t->order[i];
                if (count == k && d == worst && idx > buf[k - 1].index) continue;
                std::size_t j = count < k ? count++ : k - 1;
                while (j > 0 && (buf[j - 1].dist2 > d || (buf[j - 1].dist2 == d && buf[j - 1].index > idx))) {
                    buf[j] = buf[j - 1];
                    --j;
                }
                buf[j] = {idx, d};
                if (count == k) worst = buf[k - 1].dist2;
            }
        }
    };
    
    struct RadiusVisit {
        const Impl* t;
        const Vec3f& q;
        float r2;
        std::vector<Neighbor>* out;
        float Worst() const { return r2; }
        void Leaf(std::uint32_t begin, std::uint32_t end) {
            for (std::uint32_t i = begin; i < end; ++i) {
                const float d = Dist2(&t->xyz[3 * static_cast<std::size_t>(i)], q);
                if (d <= r2) out->push_back({t->order[i], d});
            }
        }
    };

    // k nearest into buf[0..count) sorted by (dist2, index); `off` holds the query's offset from
    // the cell along each axis (0 inside), `rd` their squared sum (the cell's lower bound).
    template <typename Visit>
    void Search(std::uint32_t id, const Vec3f& q, float rd, float off[3], Visit& visit) const {
        const Node& nd = nodes[id];
        if (nd.dim == 3) {
            visit.Leaf(nd.a, nd.b);
            return;
        }
        const float diff = q[static_cast<int>(nd.dim)] - nd.split;
        // Points at the split value lie on both sides' boundary: the left subtree holds values <=
        // split, the right >= split.
        const std::uint32_t near = diff < 0 ? id + 1 : nd.a, far = diff < 0 ? nd.a : id + 1;
        Search(near, q, rd, off, visit);
        const float old = off[nd.dim];
        const float rd_far = rd - old * old + diff * diff;
        if (rd_far <= visit.Worst() * kPruneSlack) {
            off[nd.dim] = diff;
            Search(far, q, rd_far, off, visit);
            off[nd.dim] = old;
        }
    }
};

namespace {

void CheckCoordinateRange(std::span<const Vec3f> points) {
    Vec3f lo = Vec3f::Constant(std::numeric_limits<float>::infinity()), hi = -lo;
    for (std::size_t i = 0; i < points.size(); ++i) {
        const Vec3f& p = points[i];
        if (!(p.cwiseAbs().maxCoeff() <= kMaxKdTreeCoordinate)) {  // also NaN
            std::ostringstream os;
            os << "point " << i << ": coordinates (" << p.x() << ", " << p.y() << ", " << p.z() << ") "
               << (p.allFinite() ? "exceed " : "are not finite; the limit is ") << "+-" << kMaxKdTreeCoordinate
               << " (squared distances must fit in single precision): scale the cloud";
            throw Error(ErrorCode::kInvalidArgument, os.str());
        }
        lo = lo.cwiseMin(p);
        hi = hi.cwiseMax(p);
    }
    const float extent = points.empty() ? 0.0f : (hi - lo).maxCoeff();
    if (extent > 0 && extent < kMinKdTreeExtent) {
        std::ostringstream os;
        os << "the cloud spans only " << extent << " (below " << kMinKdTreeExtent
           << ", squared distances underflow single precision): scale the cloud";
        throw Error(ErrorCode::kInvalidArgument, os.str());
    }
}

}  // namespace

KdTree::KdTree(std::span<const Vec3f> points) : impl_(std::make_unique<Impl>()) {
    CheckCoordinateRange(points);
    if (points.size() >= std::numeric_limits<std::uint32_t>::max())
        throw Error(ErrorCode::kResourceExhausted, "too many points for the kd-tree: " + std::to_string(points.size()));
    Impl& t = *impl_;
    t.points.assign(points.begin(), points.end());
    const auto n = static_cast<std::uint32_t>(points.size());
    if (n == 0) return;
    std::vector<Impl::Item> items(n);
    for (std::uint32_t i = 0; i < n; ++i) items[i] = {{points[i].x(), points[i].y(), points[i].z()}, i};
    std::map<std::uint32_t, std::uint32_t> sizes;
    const std::uint32_t total = Impl::NodeCount(n, sizes);
    t.nodes.resize(total);
    std::array<float, 3> lo = {items[0].c[0], items[0].c[1], items[0].c[2]}, hi = lo;
    for (const Impl::Item& it : items)
        for (int d = 0; d < 3; ++d) {
            lo[d] = std::min(lo[d], it.c[d]);
            hi[d] = std::max(hi[d], it.c[d]);
        }
    t.BuildNode(items, 0, 0, n, sizes, lo, hi);
    t.order.resize(n);
    t.xyz.resize(3 * static_cast<std::size_t>(n));
    for (std::uint32_t i = 0; i < n; ++i) {
        t.order[i] = items[i].index;
        for (int a = 0; a < 3; ++a) t.xyz[3 * static_cast<std::size_t>(i) + a] = items[i].c[a];
    }
}

KdTree::~KdTree() = default;

std::size_t KdTree::size() const { return impl_->points.size(); }
std::span<const Vec3f> KdTree::points() const { return impl_->points; }

void KdTree::Knn(const Vec3f& q, int k, std::vector<Neighbor>* out) const {
    SURFEL_CHECK(k > 0, "k = " << k);
    out->resize(static_cast<std::size_t>(k));
    Impl::KnnVisit v{impl_.get(), q, out->data(), static_cast<std::size_t>(k)};
    if (!impl_->nodes.empty()) {
        float off[3] = {0, 0, 0};
        impl_->Search(0, q, 0.0f, off, v);
    }
    out->resize(v.count);
}

void KdTree::Radius(const Vec3f& q, float radius, std::vector<Neighbor>* out) const {
    out->clear();
    Impl::RadiusVisit v{impl_.get(), q, radius * radius, out};
    if (!impl_->nodes.empty()) {
        float off[3] = {0, 0, 0};
        impl_->Search(0, q, 0.0f, off, v);
    }
}

Neighbor KdTree::Nearest(const Vec3f& q) const {
    Neighbor best{UINT32_MAX, std::numeric_limits<float>::infinity()};
    Impl::KnnVisit v{impl_.get(), q, &best, 1};
    if (!impl_->nodes.empty()) {
        float off[3] = {0, 0, 0};
        impl_->Search(0, q, 0.0f, off, v);
    }
    if (v.count == 0) return {UINT32_MAX, std::numeric_limits<float>::infinity()};
    return best;
}

namespace {
// Queries `at(i)` for i in [0, n), row `row(i)` of the table; `self(i)` the query's own index to
// leave out (UINT32_MAX: none).
template <typename At, typename RowOf, typename SelfOf>
KnnTable RunBatch(const KdTree& tree, std::size_t n, int k, bool exclude_self, At at, RowOf row_of, SelfOf self_of,
                  const ProgressFn& progress) {
    SURFEL_CHECK(k > 0, "k = " << k);
    KnnTable table;
    table.k = k;
    table.indices.assign(n * k, UINT32_MAX);
    table.dist2.assign(n * k, std::numeric_limits<float>::infinity());
    ProgressTracker tracker(progress, static_cast<double>(n), "neighbour search");
    const int kq = exclude_self ? k + 1 : k;
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const tbb::blocked_range<std::size_t>& r) {
        std::vector<Neighbor> buf;
        for (std::size_t s = r.begin(); s != r.end(); ++s) {
            tree.Knn(at(s), kq, &buf);
            const std::size_t i = row_of(s);
            if (exclude_self) {
                const std::uint32_t self = self_of(s);
                auto it = std::find_if(buf.begin(), buf.end(), [self](const Neighbor& nb) { return nb.index == self; });
                if (it != buf.end()) buf.erase(it);
                else if (static_cast<int>(buf.size()) > k) buf.pop_back();
            }
            const std::size_t m = std::min<std::size_t>(buf.size(), k);
            for (std::size_t j = 0; j < m; ++j) {
                table.indices[i * k + j] = buf[j].index;
                table.dist2[i * k + j] = buf[j].dist2;
            }
        }
        tracker.Advance(static_cast<double>(r.size()));
    });
    return table;
}
}  // namespace

KnnTable KdTree::KnnAll(int k, const ProgressFn& progress) const {
    // In the tree's order (neighbouring queries visit the same leaves), each into its own row.
    const Impl& t = *impl_;
    return RunBatch(
        *this, size(), k, true, [&](std::size_t s) { return t.points[t.order[s]]; },
        [&](std::size_t s) { return static_cast<std::size_t>(t.order[s]); }, [&](std::size_t s) { return t.order[s]; },
        progress);
}

KnnTable KdTree::KnnBatch(std::span<const Vec3f> queries, int k, const ProgressFn& progress) const {
    return RunBatch(
        *this, queries.size(), k, false, [&](std::size_t s) { return queries[s]; }, [](std::size_t s) { return s; },
        [](std::size_t) { return UINT32_MAX; }, progress);
}

}  // namespace surfel
