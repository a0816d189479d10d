// Iterative simplification by point-pair contraction (course notes, Pauly 2.2): quadric error
// metric over the k-nearest-neighbour graph (Garland & Heckbert's pair contraction), the cheapest
// pair contracted first.
//
// Layout (docs/simplification.md, "Iterative"): the graph lives in one pool of adjacency entries
// (neighbour, cost of the pair), a node's entries contiguous; every node keeps its cheapest pair
// among those whose lower end (by input index) it is, and an indexed 4-ary heap of the nodes
// orders those. A contraction re-evaluates the survivor's
// pairs once each (the entry at the pair's lower end holds its cost) and repairs the best pair of
// the nodes it touched; nothing stale ever enters the heap. The order of contractions is the one of
// a priority queue of all pairs by (cost, lower index, higher index): the same result as the lazy
// queue of the first version, several times faster. The points are kept in Morton order, every
// order and tie still by input index, and a contraction prefetches the lines it will touch
// (session 11: the loop waits on memory, not on arithmetic).

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_sort.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <memory>
#include <utility>

#include <sys/mman.h>

#include "surfel/base/error.h"
#include "surfel/simplify/simplify_internal.h"
#include "surfel/spatial/kd_tree.h"

namespace surfel::detail {
namespace {

/// std::allocator whose value-less construct leaves trivially constructible elements as they are:
/// the large arrays below are first written in parallel loops, which then also take their page
/// faults (session 12: zero-filling them, and the pool's copy into its reserve, ran on one core).
/// Arrays of 2 MiB and more are placed on 2 MiB boundaries and offered to the kernel for huge
/// pages (session 13: with 4 KiB pages nearly every scattered access of the contraction loop, over
/// ~200 MB, also missed the TLB; transparent huge pages are often granted only on request).
template <class T>
struct NoInit : std::allocator<T> {
    using value_type = T;
    template <class U>
    struct rebind {
        using other = NoInit<U>;
    };
    NoInit() = default;
    template <class U>
    NoInit(const NoInit<U>&) noexcept {}
    static constexpr std::size_t kHuge = std::size_t{2} << 20;
    T* allocate(std::size_t count) {
        const std::size_t bytes = count * sizeof(T);
        if (bytes < kHuge) return std::allocator<T>::allocate(count);
        const std::size_t rounded = (bytes + kHuge - 1) / kHuge * kHuge;
        void* p = std::aligned_alloc(kHuge, rounded);
        if (!p) throw std::bad_alloc();
#ifdef MADV_HUGEPAGE
        madvise(p, rounded, MADV_HUGEPAGE);  // advice only: without it the pages are 4 KiB
#endif
        return static_cast<T*>(p);
    }
    void deallocate(T* p, std::size_t count) noexcept {
        if (count * sizeof(T) < kHuge) std::allocator<T>::deallocate(p, count);
        else std::free(p);
    }
    template <class U>
    void construct(U* p) noexcept {
        ::new (static_cast<void*>(p)) U;
    }
    template <class U, class... Args>
    void construct(U* p, Args&&... args) {
        ::new (static_cast<void*>(p)) U(std::forward<Args>(args)...);
    }
};
template <class T>
bool operator==(const NoInit<T>&, const NoInit<T>&) noexcept { return true; }

/// The large arrays of the contraction loop.
template <class T>
using BigVector = std::vector<T, NoInit<T>>;

/// Sum of squared distances to a set of planes n.x = d: x^T A x - 2 b^T x + c, with A symmetric
/// (a00 a01 a02 a11 a12 a22). Quadric{} is the zero quadric (no member initialisers: a node's
/// array is left uninitialised until the parallel loop that fills it).
struct Quadric {
    double a[6];
    double b[3];
    double c;
    double planes;

    void AddPlane(const Eigen::Vector3d& n, const Eigen::Vector3d& p) {
        const double d = n.dot(p);
        a[0] += n.x() * n.x();
        a[1] += n.x() * n.y();
        a[2] += n.x() * n.z();
        a[3] += n.y() * n.y();
        a[4] += n.y() * n.z();
        a[5] += n.z() * n.z();
        for (int i = 0; i < 3; ++i) b[i] += d * n[i];
        c += d * d;
        planes += 1.0;
    }
    Quadric& operator+=(const Quadric& o) {
        for (int i = 0; i < 6; ++i) a[i] += o.a[i];
        for (int i = 0; i < 3; ++i) b[i] += o.b[i];
        c += o.c;
        planes += o.planes;
        return *this;
    }
    Eigen::Matrix3d A() const {
        Eigen::Matrix3d m;
        m << a[0], a[1], a[2], a[1], a[3], a[4], a[2], a[4], a[5];
        return m;
    }
    Eigen::Vector3d B() const { return {b[0], b[1], b[2]}; }
};

/// The sum of two quadrics, at its best point: err = Q(x) at x, the minimiser (a truncated
/// pseudo-inverse around the pair's midpoint: directions the planes do not constrain, such as
/// the tangent directions of a flat region, stay at the midpoint), or the best point of the segment
/// where nearly parallel planes let the minimiser run off (scan lines, thin strips: Garland &
/// Heckbert's fallback).
struct PairFit {
    Eigen::Vector3d x;
    double err;
    double planes;
};

PairFit FitPair(const Quadric& qu, const Quadric& qv, const Eigen::Vector3d& pu, const Eigen::Vector3d& pv) {
    Quadric q = qu;
    q += qv;
    const Eigen::Matrix3d a = q.A();
    const Eigen::Vector3d b = q.B();
    const Eigen::Vector3d mid = 0.5 * (pu + pv), e = pv - pu;
    Eigen::Vector3d x = MinimizeQuadric(a, b, mid);
    if ((x - mid).squaredNorm() > e.squaredNorm()) {
        const Eigen::Vector3d ae = SymmetricTimes(q.a, e);
        const double a2 = Dot3(e, ae), b1 = 2.0 * (Dot3(pu, ae) - Dot3(b, e));
        const double t = a2 > 0 ? std::clamp(-b1 / (2.0 * a2), 0.0, 1.0) : 0.5;
        x = pu + t * e;
    }
    const double err = std::max(0.0, Dot3(x, SymmetricTimes(q.a, x)) - 2.0 * Dot3(b, x) + q.c);
    return {x, err, q.planes};
}

// Weight of the tie-breaking term: on flat regions every quadric cost is 0, and contracting the
// shortest pair first keeps the sampling even there; small enough not to compete with the
// quadric wherever the surface bends. Chosen by measurement (bench_core, surface error Δavg on
// bunny_scans_merged and person_scan at 1 % and 10 %): 1e-4 -> 1e-3 lowered Δavg at 1 % from
// 2.12e-3 to 1.60e-3 (bunny) and at 10 % from 1.20e-3 to 0.70e-3 (person). 1e-2 and 1e-1 were
// no better there and lost the crease adaptivity (test IterativeIsCurvatureAdaptiveByItsQuadrics).
// Re-measured with the current error metric (session 4; bunny 1 %, 10 %, person 1 %, 10 %):
// 3e-4: 2.127e-3, 1.988e-4, 2.175e-3, 8.18e-4; 1e-3: 2.125e-3, 1.994e-4, 2.139e-3, 8.49e-4;
// 3e-3: 2.157e-3, 1.975e-4, 2.160e-3, 1.116e-3; 1e-2: 2.184e-3, 1.985e-4, 2.156e-3, 1.153e-3;
// 1e-1: 2.331e-3, 2.069e-4, 2.101e-3, 1.135e-3. 1e-3 stays (no setting is best everywhere).
constexpr double kLengthWeight = 1e-3;

// Room a node's list has beyond its initial degree in the pool (the rest moves when it grows).
constexpr std::uint32_t kSlack = 2;

constexpr double kNever = std::numeric_limits<double>::infinity();  // a pair that must not contract
constexpr std::uint32_t kNone = UINT32_MAX;

/// One adjacency entry: the neighbour (in the spatial numbering), its input index and the cost of
/// contracting the pair; 16 bytes.
struct Entry {
    double cost;
    std::uint32_t id, input;
};

/// A node's list in the pool ([start, start + degree), room for capacity) and its mark (the last
/// contraction that visited it): one cache line holds all a contraction needs to find the list.
struct NodeRow {
    std::uint32_t start, degree, capacity, mark;
};

/// All a contraction reads and writes of a node but its key: its list's place, its position and
/// its quadric, on two cache lines of their own (session 12: separate arrays of quadrics (88 bytes),
/// positions (24) and rows put a node on three to five lines).
struct alignas(64) Node {
    NodeRow row;
    Eigen::Vector3d p;
    Quadric q;
};
static_assert(sizeof(Node) == 128);

/// The order of pairs: (cost, lower input index, higher input index), as a queue of all pairs
/// would pop them. The indices are the input's, whatever order the points are kept in.
struct PairKey {
    double cost = kNever;
    std::uint32_t lo = kNone, hi = kNone;
    bool operator<(const PairKey& o) const {
        if (cost != o.cost) return cost < o.cost;
        if (lo != o.lo) return lo < o.lo;
        return hi < o.hi;
    }
};

/// A node's best pair (its key in the heap), the position of that pair's other end (`mate`) and
/// the node's place in the heap, on one line (session 18: three arrays put them on three; a
/// contraction reads or writes all three for each of its ~12 neighbours).
struct alignas(32) NodeKey {
    PairKey best;
    std::uint32_t mate, pos;
};
static_assert(sizeof(NodeKey) == 32);

/// A 4-ary min-heap of nodes by their best pair's key, with each node's position (NodeKey::pos),
/// so a key can move either way. A slot holds the cost and the lower index (16 bytes: a node's four
/// children share one cache line); the rare ties on both read the higher index from the keys.
class NodeHeap {
public:
    explicit NodeHeap(std::span<NodeKey> key) : key_(key) {}
    void Build() {
        const std::size_t n = key_.size();
        // Room for the slots with (heap_ + 1) on a 64-byte boundary: children 4i+1..4i+4 share a line.
        storage_.assign(n + 8, Slot{});
        const auto addr = reinterpret_cast<std::uintptr_t>(storage_.data() + 1);
        heap_ = storage_.data() + ((64 - addr % 64) % 64) / sizeof(Slot);
        size_ = static_cast<std::uint32_t>(n);
        for (std::uint32_t i = 0; i < size_; ++i) {
            heap_[i] = SlotOf(i);
            key_[i].pos = i;
        }
        // Floyd's bottom-up construction (a sorted array would put the two ends of each pair, which
        // share a key, next to each other, and every comparison between them reads their keys).
        for (std::uint32_t i = size_ / 4 + 1; i-- > 0;) {
            const Slot s = heap_[i];  // Down overwrites heap_[i]
            Down(i, s);
        }
    }
    std::uint32_t top() const { return heap_[0].node; }
    /// The least of the top's children: the top after it, unless a key changes before.
    std::uint32_t RunnerUp() const {
        if (size_ < 2) return kNone;
        const std::uint32_t end = std::min<std::uint32_t>(5, size_);
        std::uint32_t m = 1;
        for (std::uint32_t j = 2; j < end; ++j)
            if (Less(heap_[j], heap_[m])) m = j;
        return heap_[m].node;
    }
    /// Asks for node u's slot ahead of an Update (its key, with its position, asked for before).
    void PrefetchSlot(std::uint32_t u) const {
        if (key_[u].pos != kNone) __builtin_prefetch(heap_ + key_[u].pos);
    }
    /// Re-sorts node u after its key changed.
    void Update(std::uint32_t u) {
        const std::uint32_t i = key_[u].pos;
        if (i == kNone) return;
        const Slot s = SlotOf(u);
        if (i > 0 && Less(s, heap_[(i - 1) / 4])) Up(i, s);
        else Down(i, s);
    }
    void Remove(std::uint32_t u) {
        const std::uint32_t i = key_[u].pos;
        if (i == kNone) return;
        const Slot last = heap_[--size_];
        key_[u].pos = kNone;
        if (last.node == u) return;
        heap_[i] = last;
        key_[last.node].pos = i;
        Update(last.node);
    }

private:
    struct alignas(16) Slot {
        double cost;
        std::uint32_t lo, node;
    };
    Slot SlotOf(std::uint32_t u) const { return {key_[u].best.cost, key_[u].best.lo, u}; }
    bool Less(const Slot& a, const Slot& b) const {
        if (a.cost != b.cost) return a.cost < b.cost;
        if (a.lo != b.lo) return a.lo < b.lo;
        const std::uint32_t ha = key_[a.node].best.hi, hb = key_[b.node].best.hi;
        if (ha != hb) return ha < hb;
        return a.node < b.node;  // (each pair is held at one end: two slots never share a key)
    }
    void Up(std::uint32_t i, const Slot& s) {
        while (i > 0) {
            const std::uint32_t p = (i - 1) / 4;
            if (!Less(s, heap_[p])) break;
            heap_[i] = heap_[p];
            key_[heap_[i].node].pos = i;
            i = p;
        }
        heap_[i] = s;
        key_[s.node].pos = i;
    }
    void Down(std::uint32_t i, const Slot& s) {
        for (;;) {
            const std::uint32_t c = 4 * i + 1;
            if (c >= size_) break;
            // The grandchildren (four lines in a row) while the children are compared.
            if (4 * c + 1 < size_) {
                const char* g = reinterpret_cast<const char*>(heap_ + 4 * c + 1);
                for (int line = 0; line < 4; ++line) __builtin_prefetch(g + 64 * line);
            }
            const std::uint32_t end = std::min(c + 4, size_);
            std::uint32_t m = c;
            for (std::uint32_t j = c + 1; j < end; ++j)
                if (Less(heap_[j], heap_[m])) m = j;
            if (!Less(heap_[m], s)) break;
            heap_[i] = heap_[m];
            key_[heap_[i].node].pos = i;
            i = m;
        }
        heap_[i] = s;
        key_[s.node].pos = i;
    }
    std::span<NodeKey> key_;
    BigVector<Slot> storage_;
    Slot* heap_ = nullptr;
    std::uint32_t size_ = 0;
};

/// A spatial order of the points (Morton order of a 1024^3 grid over the bounding box, ties by
/// index): neighbours in the graph lie near each other in memory. Returns the input index of
/// each position in that order.
std::vector<std::uint32_t> SpatialOrder(std::span<const Vec3f> points) {
    const std::size_t n = points.size();
    Eigen::Vector3f lo = Eigen::Vector3f::Constant(std::numeric_limits<float>::max()), hi = -lo;
    for (const Vec3f& p : points) {
        lo = lo.cwiseMin(p);
        hi = hi.cwiseMax(p);
    }
    const float extent = (hi - lo).maxCoeff();
    const float scale = extent > 0 ? 1023.0f / extent : 0.0f;
    auto spread = [](std::uint64_t x) {  // 10 bits to every third of 30
        x &= 0x3ff;
        x = (x | (x << 16)) & 0x30000ff;
        x = (x | (x << 8)) & 0x300f00f;
        x = (x | (x << 4)) & 0x30c30c3;
        x = (x | (x << 2)) & 0x9249249;
        return x;
    };
    std::vector<std::uint64_t> code(n);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 8192), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i) {
            const Eigen::Vector3f c = ((points[i] - lo) * scale).cwiseMax(0.0f).cwiseMin(1023.0f);
            const std::uint64_t m = spread(static_cast<std::uint64_t>(c.x())) |
                                    (spread(static_cast<std::uint64_t>(c.y())) << 1) |
                                    (spread(static_cast<std::uint64_t>(c.z())) << 2);
            code[i] = (m << 32) | i;
        }
    });
    tbb::parallel_sort(code.begin(), code.end());  // keys are unique: the order is deterministic
    std::vector<std::uint32_t> input_of(n);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 16384), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i) input_of[i] = static_cast<std::uint32_t>(code[i] & 0xffffffffu);
    });
    return input_of;
}

}  // namespace

Clustering IterativeSimplification(std::span<const Vec3f> points, std::span<const Vec3f> normals,
                                   KnnTable knn, bool cluster_normals, const SimplifyOptions& options,
                                   std::vector<Vec3f>& positions, ProgressTracker& progress) {
    const std::size_t n = points.size();
    const int k = std::max(1, std::min<int>(options.neighbors, static_cast<int>(n) - 1));
    if (knn.k < k) {
        const KdTree tree(points);
        knn = tree.KnnAll(k);
    }
    // knn: rows nearest first, its first k columns are the k-NN graph

    // The points are kept in a spatial order (position i holds input point input_of[i]) for the
    // locality of the contraction loop; every order and tie between pairs still goes by input
    // index, and each sum is taken in the same order as over the input numbering, so the result
    // is the one of the input order, to the bit.
    const std::vector<std::uint32_t> input_of = SpatialOrder(points);
    BigVector<std::uint32_t> at(n);  // input index -> position
    tbb::parallel_for(tbb::blocked_range<std::uint32_t>(0, static_cast<std::uint32_t>(n), 16384),
                      [&](const tbb::blocked_range<std::uint32_t>& r) {
                          for (std::uint32_t i = r.begin(); i != r.end(); ++i) at[input_of[i]] = i;
                      });

    // Symmetric neighbour graph, each row sorted by input index and without repeats. Built in
    // parallel: a node's row holds its own k-NN row's entries first, written in place, then the
    // entries of the nodes that have it in theirs, placed by atomic increments (the order within a
    // row depends on the threads, its sorted contents do not). Session 15's second iterative helper:
    // with every entry placed by an atomic increment the merged scans took 6.9 M of them, now 4.4 M.
    std::vector<std::uint32_t> first(n + 1, 0);
    BigVector<Node> node(n);  // filled below, in parallel
    BigVector<std::uint32_t> graph_storage;
    {
        std::vector<std::atomic<std::uint32_t>> reverse(n);  // counts, then each row's next free slot
        static_assert(kMaxNeighbors <= 255);
        SURFEL_CHECK(k <= 255, "iterative: k = " << k << " beyond " << kMaxNeighbors);
        std::vector<std::uint8_t> own(n);  // valid entries among a row's first k
        tbb::parallel_for(tbb::blocked_range<std::uint32_t>(0, static_cast<std::uint32_t>(n), 4096),
                          [&](const tbb::blocked_range<std::uint32_t>& r) {
                              for (std::uint32_t i = r.begin(); i != r.end(); ++i) {
                                  const auto row = knn.Row(input_of[i]);
                                  std::uint32_t valid = 0;
                                  for (int c = 0; c < k; ++c) {
                                      const std::uint32_t j = row[c];
                                      if (j == kNone) continue;
                                      ++valid;
                                      reverse[at[j]].fetch_add(1, std::memory_order_relaxed);
                                  }
                                  own[i] = static_cast<std::uint8_t>(valid);
                              }
                          });
        for (std::size_t i = 0; i < n; ++i) {
            const std::uint32_t start = first[i] + own[i];
            first[i + 1] = start + reverse[i].load(std::memory_order_relaxed);
            reverse[i].store(start, std::memory_order_relaxed);
        }
        decltype(graph_storage)(first[n]).swap(graph_storage);  // every slot is written below
        tbb::parallel_for(tbb::blocked_range<std::uint32_t>(0, static_cast<std::uint32_t>(n), 4096),
                          [&](const tbb::blocked_range<std::uint32_t>& r) {
                              for (std::uint32_t i = r.begin(); i != r.end(); ++i) {
                                  const auto row = knn.Row(input_of[i]);
                                  std::uint32_t slot = first[i];
                                  for (int c = 0; c < k; ++c) {
                                      const std::uint32_t j = row[c];
                                      if (j == kNone) continue;
                                      graph_storage[slot++] = j;
                                      graph_storage[reverse[at[j]].fetch_add(1, std::memory_order_relaxed)] = input_of[i];
                                  }
                              }
                          });
    }
    // The table is not read again: it goes before the node records and the pool are first touched
    // below (session 14: the process's peak memory on the merged scans 226 -> 167 MB with the
    // pool's smaller room).
    knn = KnnTable{};
    auto& graph = graph_storage;  // input indices
    // Each node's row (its list's place and room come with the pool), position and quadric, in one
    // pass (session 15: the quadrics' own pass read each neighbour's position from its node record
    // through `at`; the input's float point is the same value).
    // Quadrics: one tangent plane per edge, spanned by e_i = p - p_i and b_i = e_i x n (the sign
    // of n does not matter: a quadric holds n n^T, d n and d^2).
    // room[i + 1]: the pool's room for node i's list (see the pool below), summed after this pass.
    std::vector<std::uint32_t> room(n + 1, 0);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 4096), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i) {
            auto b = graph.begin() + first[i], e = graph.begin() + first[i + 1];
            std::sort(b, e);
            const auto degree = static_cast<std::uint32_t>(std::unique(b, e) - b);
            room[i + 1] = std::min(first[i + 1] - first[i], degree + kSlack);
            const Eigen::Vector3d p = points[input_of[i]].cast<double>();
            const Eigen::Vector3d ni = normals[input_of[i]].cast<double>();
            Quadric q{};
            for (auto it = b; it != b + degree; ++it) {
                const Eigen::Vector3d d = p - points[*it].cast<double>();
                Eigen::Vector3d plane = d.cross(d.cross(ni));
                const double len = plane.norm();
                plane = len > 1e-300 ? Eigen::Vector3d(plane / len) : ni;
                if (plane.dot(ni) < 0) plane = -plane;
                q.AddPlane(plane, p);
            }
            if (degree == 0) q.AddPlane(ni, p);
            node[i].row = {first[i], degree, 0, 0};
            node[i].p = p;
            node[i].q = q;
        }
    });
    progress.Advance(0.1);

    // The cost of a pair: the quadric error at its best point plus the length term; pairs whose RMS
    // distance to their planes would exceed the error bound never contract (until one end changes).
    const double bound2 = options.error > 0 ? options.error * options.error : kNever;
    // Always from the lower input index to the higher (the fit is symmetric only up to rounding).
    // Callers pass the input indices iu, iv of u and v: the lists hold them, and input_of[] is
    // one more scattered read per pair in the contraction loop.
    auto fit = [&](std::uint32_t u, std::uint32_t v, std::uint32_t iu, std::uint32_t iv) {
        if (iu > iv) std::swap(u, v);
        return FitPair(node[u].q, node[v].q, node[u].p, node[v].p);
    };
    auto cost_of = [&](std::uint32_t u, std::uint32_t v, std::uint32_t iu, std::uint32_t iv) {
        const PairFit f = fit(u, v, iu, iv);
        if (f.err / std::max(1.0, f.planes) > bound2) return kNever;
        return f.err + kLengthWeight * f.planes * (node[u].p - node[v].p).squaredNorm();
    };

    // The pool: a node's entries at [start, start + degree), room for `capacity`; a node whose list
    // outgrows its room moves to the end of the pool.
    // Every entry is written by the loop below (the room a list leaves behind is never read).
    // Room for kSlack more entries than a list holds (its row's repeats are not kept: 44 % of the
    // rows' entries on the merged scans); a list that outgrows its room takes over the removed
    // node's room when that is large enough, else moves to the end (session 14: 70 -> 53 MB).
    // (The sizes come from the pass above: summing them here from node[i].row.degree read one
    // 128-byte record per node, serially.)
    for (std::size_t i = 0; i < n; ++i) room[i + 1] += room[i];
    BigVector<Entry> pool;
    pool.reserve(static_cast<std::size_t>(first[n]) * 2);
    pool.resize(static_cast<std::size_t>(room[n]));
    // Every pair's cost, evaluated once from its lower end (by input index).
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i) {
            node[i].row.start = room[i];
            node[i].row.capacity = room[i + 1] - room[i];
            for (std::uint32_t c = 0; c < node[i].row.degree; ++c) {
                const std::uint32_t j = graph[first[i] + c];
                Entry& en = pool[room[i] + c];
                en = {kNever, at[j], j};
                if (j > input_of[i])
                    en.cost = cost_of(static_cast<std::uint32_t>(i), at[j], input_of[i], j);
            }
        }
    });
    decltype(graph_storage)().swap(graph);
    // Only the lower end's entry holds the cost: a node's best pair is among its pairs to higher
    // indices, and nothing else reads a cost (the higher end's entry keeps kNever).
    progress.Advance(0.1);

    // Each node's best pair among those whose lower end (by input index) it is, and the heap over
    // them: every pair is in the heap once, at its lower end, so the top is still the least pair
    // by (cost, lower index, higher index), and a contraction repairs the best pair of only those
    // neighbours that are the lower end of a pair it changed (session 13: with each pair at both
    // ends, twice as many heap updates).
    // keys[u]: u's best pair, the position of its higher end (`mate`, read beside the key at the
    // start of a contraction instead of after it from `at`: one miss fewer in the chain to the
    // pair's nodes) and u's place in the heap, on one line.
    BigVector<NodeKey> keys(n);
    auto rescan = [&](std::uint32_t u, std::uint32_t self) {  // self = input_of[u]
        PairKey b;
        std::uint32_t m = kNone;
        for (std::uint32_t e = node[u].row.start; e < node[u].row.start + node[u].row.degree; ++e) {
            if (pool[e].input < self) continue;
            const PairKey key{pool[e].cost, self, pool[e].input};
            if (key < b) b = key, m = pool[e].id;
        }
        keys[u].best = b;
        keys[u].mate = m;
    };
    tbb::parallel_for(tbb::blocked_range<std::uint32_t>(0, static_cast<std::uint32_t>(n), 4096),
                      [&](const tbb::blocked_range<std::uint32_t>& r) {
                          for (std::uint32_t i = r.begin(); i != r.end(); ++i) rescan(i, input_of[i]);
                      });
    NodeHeap heap(keys);
    heap.Build();
    auto entry_of = [&](std::uint32_t w, std::uint32_t id) -> Entry* {
        for (std::uint32_t e = node[w].row.start; e < node[w].row.start + node[w].row.degree; ++e)
            if (pool[e].id == id) return &pool[e];
        return nullptr;
    };
    // Sets the cost of pair (u, w) at w's end where w is its lower end, and repairs w's best pair;
    // `gone` (an input index) is a node that may just have left w's list (w's best may have been
    // the pair with it). iw, iu: the input indices of w and u. Where u is the pair's lower end,
    // u's own list holds the cost and its rescan after the contraction takes the pair into account.
    auto set_cost_at = [&](std::uint32_t w, std::uint32_t iw, std::uint32_t u, std::uint32_t iu, double cost,
                           std::uint32_t gone) {
        const bool lost_best = gone != kNone && keys[w].best.hi == gone;
        if (iw < iu) {
            Entry* e = entry_of(w, u);
            SURFEL_CHECK(e != nullptr, "pair " << iu << "-" << iw << " missing at " << iw);
            e->cost = cost;
            const PairKey key{cost, iw, iu};
            if (keys[w].best.hi == iu || lost_best) rescan(w, iw);
            else if (key < keys[w].best) keys[w].best = key, keys[w].mate = u;
            else return;
        } else if (lost_best) {
            rescan(w, iw);
        } else {
            return;
        }
        heap.Update(w);
    };

    BigVector<char> alive(n, 1);
    BigVector<std::uint32_t> parent(n);
    std::vector<Entry> merged;  // cost unused
    for (std::uint32_t i = 0; i < n; ++i) parent[i] = i;
    std::uint32_t epoch = 0;
    std::size_t count = n;
    const std::size_t target = options.target;
    const double total = target ? static_cast<double>(n - std::min(n, target)) : static_cast<double>(n);
    std::size_t since = 0;
    while (count > target && count > 1) {
        const std::uint32_t top = heap.top(), top_mate = keys[top].mate;  // both loads at once
        if (keys[top].best.cost == kNever) {
            if (target == 0) break;  // error-bounded: no admissible contraction left
            // Components ran out of pairs before the target: connect the survivors by their k
            // nearest survivors (taken in input order).
            std::vector<Vec3f> live;
            std::vector<std::uint32_t> ids;
            for (std::uint32_t o = 0; o < n; ++o)
                if (alive[at[o]]) {
                    live.push_back(node[at[o]].p.cast<float>());
                    ids.push_back(at[o]);
                }
            const KdTree live_tree(live);
            const KnnTable live_knn = live_tree.KnnAll(std::min<int>(k, static_cast<int>(live.size()) - 1));
            auto append = [&](std::uint32_t u, std::uint32_t v) {
                if (node[u].row.degree == node[u].row.capacity) {
                    const std::uint32_t moved = static_cast<std::uint32_t>(pool.size());
                    const std::uint32_t cap = std::max<std::uint32_t>(4, 2 * node[u].row.capacity);
                    pool.resize(moved + cap);
                    std::copy_n(pool.begin() + node[u].row.start, node[u].row.degree, pool.begin() + moved);
                    node[u].row.start = moved;
                    node[u].row.capacity = cap;
                }
                pool[node[u].row.start + node[u].row.degree++] = {kNever, v, input_of[v]};
            };
            for (std::uint32_t a = 0; a < live.size(); ++a)
                for (const std::uint32_t b : live_knn.Row(a)) {
                    if (b == kNone) continue;
                    const std::uint32_t u = ids[a], v = ids[b];
                    if (!entry_of(u, v)) {
                        append(u, v);
                        append(v, u);
                    }
                }
            for (std::uint32_t a = 0; a < live.size(); ++a) {
                const std::uint32_t u = ids[a];
                for (std::uint32_t e = node[u].row.start; e < node[u].row.start + node[u].row.degree; ++e) {
                    if (pool[e].input > input_of[u])  // held at the lower end only
                        pool[e].cost = cost_of(u, pool[e].id, input_of[u], pool[e].input);
                }
            }
            for (const std::uint32_t u : ids) {
                rescan(u, input_of[u]);
                heap.Update(u);
            }
            if (keys[heap.top()].best.cost == kNever) break;  // nothing left to join (coincident points)
            continue;
        }
        // Contract the best pair: v (the higher input index) into u.
        const std::uint32_t u = top, v = top_mate;  // the pair's lower end holds it
        const std::uint32_t u_input = keys[top].best.lo, v_input = keys[top].best.hi;
        // The loop waits on memory (each pair touches rows, quadrics and keys scattered over the
        // pool): ask for all of a contraction's lines at once, in two waves (a list's place, then
        // the list), while the pair's fit computes.
        auto prefetch_row = [&](std::uint32_t w) {
            const Entry* row = pool.data() + node[w].row.start;
            for (std::uint32_t e = 0; e < node[w].row.degree; e += 4) __builtin_prefetch(row + e);
        };
        prefetch_row(u);
        prefetch_row(v);
        // Look-ahead (session 15): the next contraction's pair is, nearly always, the heap's second
        // (the least of the top's children: a contraction seldom makes a pair cheaper than that or
        // touches it; on the merged scans it was the next top at 358,610 of 358,648 contractions,
        // and touched by the contraction before at 22). Its chain (key and mate, the two records,
        // their lists, the neighbours' records and keys) is asked for one link at a time, spread
        // over this contraction so that each link has come in when the next needs it; the first
        // wave of the next contraction then finds its lines in the cache. Prefetches only: the
        // contractions are the same whatever the guess.
        const std::uint32_t next = heap.RunnerUp();
        if (next != kNone) {
            __builtin_prefetch(&keys[next]);
            __builtin_prefetch(&node[next]);
            __builtin_prefetch(reinterpret_cast<const char*>(&node[next]) + 64);
        }
        // The first line of the records (list place, mark) and the keys (heap place) of x's and y's
        // neighbours, which the second wave reads; with `second_lines`, then the records' second
        // lines (the quadrics' rest, read only by the cost loop). Session 18: the lines are asked
        // for in the order they are needed: the memory system holds only so many requests, and a
        // line asked for early but needed late holds up the ones needed first (the second wave
        // waited on the first lines behind the second ones: the loop 637 -> 494 ms).
        auto prefetch_neighbours = [&](std::uint32_t x, std::uint32_t y, bool second_lines) {
            for (const std::uint32_t z : {x, y})
                for (std::uint32_t e = node[z].row.start; e < node[z].row.start + node[z].row.degree; ++e) {
                    const std::uint32_t w = pool[e].id;
                    __builtin_prefetch(&node[w]);
                    __builtin_prefetch(&keys[w]);
                }
            if (!second_lines) return;
            for (const std::uint32_t z : {x, y})
                for (std::uint32_t e = node[z].row.start; e < node[z].row.start + node[z].row.degree; ++e)
                    __builtin_prefetch(reinterpret_cast<const char*>(&node[pool[e].id]) + 64);
        };
        const PairFit f = fit(u, v, u_input, v_input);
        prefetch_neighbours(u, v, false);
        const std::uint32_t next_mate = next != kNone ? keys[next].mate : kNone;
        if (next_mate < n) {
            __builtin_prefetch(&node[next_mate]);
            __builtin_prefetch(reinterpret_cast<const char*>(&node[next_mate]) + 64);
        }
        // While the first wave's lines come in: the pair's point and quadric, v out of the heap.
        node[u].p = f.x;
        node[u].q += node[v].q;
        alive[v] = 0;
        parent[v] = u;
        heap.Remove(v);
        // The second wave: the neighbours' lists (the merge below reads them), then their records'
        // second lines and heap slots (the cost loop after it).
        for (const std::uint32_t x : {u, v})
            for (std::uint32_t e = node[x].row.start; e < node[x].row.start + node[x].row.degree; ++e)
                prefetch_row(pool[e].id);
        for (const std::uint32_t x : {u, v})
            for (std::uint32_t e = node[x].row.start; e < node[x].row.start + node[x].row.degree; ++e) {
                __builtin_prefetch(reinterpret_cast<const char*>(&node[pool[e].id]) + 64);
                heap.PrefetchSlot(pool[e].id);
            }

        // u's new neighbours: its own and v's, without u and v. v's neighbours now point to u.
        ++epoch;
        merged.clear();
        node[u].row.mark = node[v].row.mark = epoch;
        for (std::uint32_t e = node[u].row.start; e < node[u].row.start + node[u].row.degree; ++e)
            if (node[pool[e].id].row.mark != epoch) {
                node[pool[e].id].row.mark = epoch;
                merged.push_back(pool[e]);
            }
        for (std::uint32_t e = node[v].row.start; e < node[v].row.start + node[v].row.degree; ++e) {
            const std::uint32_t w = pool[e].id;
            if (w == u) continue;
            Entry* at_w = entry_of(w, v);
            if (node[w].row.mark == epoch) {
                *at_w = pool[node[w].row.start + --node[w].row.degree];  // w knew both: drop v
            } else {
                at_w->id = u;
                at_w->input = u_input;
                node[w].row.mark = epoch;
                merged.push_back(pool[e]);
            }
        }
        node[v].row.degree = 0;
        if (merged.size() > node[u].row.capacity && merged.size() <= node[v].row.capacity) {  // v's room
            node[u].row.start = node[v].row.start;
            node[u].row.capacity = node[v].row.capacity;
        } else if (merged.size() > node[u].row.capacity) {
            const std::uint32_t cap = static_cast<std::uint32_t>(merged.size() + merged.size() / 2);
            node[u].row.start = static_cast<std::uint32_t>(pool.size());
            node[u].row.capacity = cap;
            pool.resize(pool.size() + cap);
        }
        node[u].row.degree = static_cast<std::uint32_t>(merged.size());
        if (next_mate < n && next != v && next_mate != v) {  // the next pair's lists
            prefetch_row(next);
            prefetch_row(next_mate);
        }
        for (std::size_t j = 0; j < merged.size(); ++j) {
            const std::uint32_t w = merged[j].id;
            const double cost = cost_of(u, w, u_input, merged[j].input);
            pool[node[u].row.start + j] = {cost, w, merged[j].input};
            set_cost_at(w, merged[j].input, u, u_input, cost, v_input);
        }
        if (next_mate < n && next != v && next_mate != v) prefetch_neighbours(next, next_mate, true);  // the next pair's
        rescan(u, u_input);
        heap.Update(u);
        --count;
        if (++since == 8192) {
            progress.Advance(0.8 * 8192.0 / std::max(1.0, total));
            since = 0;
        }
    }

    // Clusters: follow each point's contraction chain to its surviving representative.
    Clustering out;
    out.label.resize(n);
    for (std::uint32_t i = 0; i < n; ++i) {
        std::uint32_t r = i;
        while (parent[r] != r) r = parent[r];
        std::uint32_t j = i;
        while (parent[j] != r && parent[j] != j) {
            const std::uint32_t next = parent[j];
            parent[j] = r;
            j = next;
        }
        out.label[input_of[i]] = r;
    }
    out.count = Compact(out.label);
    positions.assign(out.count, Vec3f::Zero());
    std::vector<std::uint32_t> rep(out.count, kNone);  // input index of each cluster's survivor
    for (std::uint32_t o = 0; o < n; ++o)
        if (alive[at[o]]) {
            positions[out.label[o]] = node[at[o]].p.cast<float>();
            rep[out.label[o]] = o;
        }
    if (cluster_normals) {
        // Unoriented input normals: each cluster's normal is the sum of its members' normals
        // turned to agree with its surviving point's; BuildFromClusters orients them over the
        // representatives.
        std::vector<Eigen::Vector3d> sum(out.count, Eigen::Vector3d::Zero());
        for (std::uint32_t i = 0; i < n; ++i) {
            const std::uint32_t c = out.label[i];
            const Eigen::Vector3d ni = normals[i].cast<double>();
            sum[c] += normals[rep[c]].dot(normals[i]) < 0 ? Eigen::Vector3d(-ni) : ni;
        }
        out.normals.assign(out.count, Vec3f::Zero());
        for (std::size_t c = 0; c < out.count; ++c) {
            const double len = sum[c].norm();
            if (len > 1e-6) out.normals[c] = (sum[c] / len).cast<float>();
        }
    }
    return out;
}

}  // namespace surfel::detail
