#include "surfel/spatial/kd_tree.h"

#include <tbb/blocked_range.h>
#include <tbb/global_control.h>
#include <tbb/parallel_for.h>
#include <tbb/task_group.h>

#include <algorithm>
#include <cmath>
#include <flann/algorithms/kdtree_single_index.h>
#include <flann/flann.hpp>
#include <limits>
#include <mutex>
#include <sstream>

#include "surfel/base/error.h"
#include "surfel/spatial/neighbor_radii.h"
#include "surfel/spatial/uniform_grid.h"

#if defined(__SANITIZE_THREAD__) || defined(SURFEL_TSAN_BUILD)
// (SURFEL_TSAN_BUILD: the TSan build, which compiles this module itself without instrumentation.)
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

using FlannTree = flann::KDTreeSingleIndex<flann::L2_Simple<float>>;

// k nearest, kept sorted by insertion into a caller-owned buffer (no allocation per query once
// the buffer has grown). The worst distance is cached: FLANN asks for it at every node.
class KnnCollector : public flann::ResultSet<float> {
public:
    KnnCollector(std::vector<Neighbor>* out, std::size_t k) : out_(out), k_(k) { out_->resize(k); }
    ~KnnCollector() override { out_->resize(count_); }
    bool full() const override { return count_ == k_; }
    // FLANN offers a leaf point only when strictly nearer than this: the next float above the
    // k-th lets a point tied with it through, so that addPoint ranks ties by index whatever
    // order the tree visits them in (the grid's KnnAll gives the same rows).
    float worstDist() const override { return count_ == k_ ? std::nextafter(worst_, std::numeric_limits<float>::infinity()) : worst_; }
    void addPoint(float dist, std::size_t index) override {
        const auto idx = static_cast<std::uint32_t>(index);
        Neighbor* buf = out_->data();
        if (count_ == k_ && !(dist < buf[k_ - 1].dist2 || (dist == buf[k_ - 1].dist2 && idx < buf[k_ - 1].index)))
            return;
        std::size_t i = count_ < k_ ? count_++ : k_ - 1;
        // Shift larger entries up (ties by index, so the result is deterministic).
        while (i > 0 && (buf[i - 1].dist2 > dist || (buf[i - 1].dist2 == dist && buf[i - 1].index > idx))) {
            buf[i] = buf[i - 1];
            --i;
        }
        buf[i] = {idx, dist};
        if (count_ == k_) worst_ = buf[k_ - 1].dist2;
    }

private:
    std::vector<Neighbor>* out_;
    std::size_t k_;
    std::size_t count_ = 0;
    float worst_ = std::numeric_limits<float>::max();
};

// Everything within a radius (FLANN compares squared distances for L2_Simple).
class RadiusCollector : public flann::ResultSet<float> {
public:
    RadiusCollector(std::vector<Neighbor>* out, float radius2) : out_(out), r2_(radius2) { out_->clear(); }
    bool full() const override { return true; }
    float worstDist() const override { return r2_; }
    void addPoint(float dist, std::size_t index) override {
        if (dist <= r2_) out_->push_back({static_cast<std::uint32_t>(index), dist});
    }

private:
    std::vector<Neighbor>* out_;
    float r2_;
};

}  // namespace

struct KdTree::Impl {
    std::vector<Vec3f> points;
    std::unique_ptr<FlannTree> tree;
    std::once_flag built;
    flann::SearchParams params{flann::FLANN_CHECKS_UNLIMITED, 0.0f, false};

    /// The FLANN index, built on first use (null for no points): KnnAll builds it beside the grid's
    /// search, which answers most rows without it (session 12: the build was ~50 ms on one core
    /// before anything else could start, on the 362k merged scans).
    FlannTree* Tree() {
        std::call_once(built, [this] {
            if (points.empty()) return;
            flann::Matrix<float> data(points.data()->data(), points.size(), 3);
            tree = std::make_unique<FlannTree>(data, flann::KDTreeSingleIndexParams(15, true));
            tree->buildIndex();
        });
        return tree.get();
    }
};

// ---- The range single-precision distances can hold ---------------------------------------------

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
    impl_->points.assign(points.begin(), points.end());
    if (impl_->points.size() >= std::numeric_limits<std::uint32_t>::max())
        throw Error(ErrorCode::kResourceExhausted, "too many points for the kd-tree: " + std::to_string(points.size()));
    // The index itself is built on first use (Impl::Tree).
}

KdTree::~KdTree() = default;

std::size_t KdTree::size() const { return impl_->points.size(); }
std::span<const Vec3f> KdTree::points() const { return impl_->points; }

void KdTree::Knn(const Vec3f& q, int k, std::vector<Neighbor>* out) const {
    SURFEL_CHECK(k > 0, "k = " << k);
    KnnCollector c(out, static_cast<std::size_t>(k));
    if (FlannTree* tree = impl_->Tree()) tree->findNeighbors(c, q.data(), impl_->params);
}

void KdTree::Radius(const Vec3f& q, float radius, std::vector<Neighbor>* out) const {
    RadiusCollector c(out, radius * radius);
    if (FlannTree* tree = impl_->Tree()) tree->findNeighbors(c, q.data(), impl_->params);
}

namespace {
// The single nearest point, held in place (Nearest runs once per point in several hot loops).
class NearestCollector : public flann::ResultSet<float> {
public:
    bool full() const override { return best_.index != UINT32_MAX; }
    float worstDist() const override { return best_.dist2; }
    void addPoint(float dist, std::size_t index) override {
        const auto idx = static_cast<std::uint32_t>(index);
        if (dist < best_.dist2 || (dist == best_.dist2 && idx < best_.index)) best_ = {idx, dist};
    }
    Neighbor best() const { return best_; }

private:
    Neighbor best_{UINT32_MAX, std::numeric_limits<float>::infinity()};
};
}  // namespace

Neighbor KdTree::Nearest(const Vec3f& q) const {
    NearestCollector c;
    if (FlannTree* tree = impl_->Tree()) tree->findNeighbors(c, q.data(), impl_->params);
    return c.best();
}

namespace {
// The k nearest points of q into indices[0, k) and dist2[0, k) (when not null), without point
// i itself when `exclude_self` (q is then point i): the k smallest by (distance, index) among
// the others; UINT32_MAX / infinity where there are fewer.
void FillRow(const KdTree& tree, const Vec3f& q, std::size_t i, int k, bool exclude_self, std::vector<Neighbor>& buf,
             std::uint32_t* indices, float* dist2) {
    tree.Knn(q, exclude_self ? k + 1 : k, &buf);
    if (exclude_self) {
        auto self = std::find_if(buf.begin(), buf.end(), [i](const Neighbor& nb) { return nb.index == i; });
        if (self != buf.end()) buf.erase(self);
        else if (static_cast<int>(buf.size()) > k) buf.pop_back();
    }
    const std::size_t m = std::min<std::size_t>(buf.size(), k);
    for (std::size_t j = 0; j < static_cast<std::size_t>(k); ++j) {
        indices[j] = j < m ? buf[j].index : UINT32_MAX;
        if (dist2) dist2[j] = j < m ? buf[j].dist2 : std::numeric_limits<float>::infinity();
    }
}

// Row i of `table` (FillRow).
void FillRow(const KdTree& tree, const Vec3f& q, std::size_t i, bool exclude_self, std::vector<Neighbor>& buf,
             KnnTable& table) {
    const std::size_t at = i * static_cast<std::size_t>(table.k);
    FillRow(tree, q, i, table.k, exclude_self, buf, table.indices.data() + at, table.dist2.data() + at);
}

// A table of n rows of k, padded (UINT32_MAX / infinity) for the rows no search fills.
void PrepareTable(KnnTable& table, std::size_t n, int k) {
    table.k = k;
    table.indices.assign(n * k, UINT32_MAX);
    table.dist2.assign(n * k, std::numeric_limits<float>::infinity());
}

// Every row of `table` (PrepareTable's) from the tree.
void RunBatch(const KdTree& tree, std::size_t n, bool exclude_self, const Vec3f* queries, const ProgressFn& progress,
              KnnTable& table) {
    ProgressTracker tracker(progress, static_cast<double>(n), "neighbour search");
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const tbb::blocked_range<std::size_t>& r) {
        std::vector<Neighbor> buf;
        for (std::size_t i = r.begin(); i != r.end(); ++i) FillRow(tree, queries[i], i, exclude_self, buf, table);
        tracker.Advance(static_cast<double>(r.size()));
    });
}

KnnTable RunBatch(const KdTree& tree, std::size_t n, int k, bool exclude_self, const Vec3f* queries,
                  const ProgressFn& progress) {
    SURFEL_CHECK(k > 0, "k = " << k);
    KnnTable table;
    PrepareTable(table, n, k);
    RunBatch(tree, n, exclude_self, queries, progress, table);
    return table;
}

// KnnAll's rows the grid's 3 x 3 x 3 blocks leave are searched in blocks of up to 9 x 9 x 9 cells,
// and when at most kWholeGridRows are left after those, in the whole grid (a pass over every point
// a row; far outliers) before the tree: on the merged scans (k = 16) 10,319 of 362k rows reach
// past 3 x 3 x 3, and 1 past 9 x 9 x 9, which no longer costs the tree's build (~75 ms CPU).
constexpr int kMaxGridRing = 4;
constexpr std::size_t kWholeGridRows = 32;
}  // namespace

KnnTable KdTree::KnnAll(int k, const ProgressFn& progress) const {
    SURFEL_CHECK(k > 0, "k = " << k);
    const std::size_t n = size();
    // One thread writes the table's padding (its first touch of ~n * k * 8 bytes of fresh pages)
    // while the caller builds the grid. (Session 14: the FLANN index is no longer built here
    // beside the grid; the wider blocks answer the grid's leftover rows without it.)
    KnnTable table;
    std::vector<std::uint8_t> answered;
    tbb::task_group fill;
    fill.run([&] {
        PrepareTable(table, n, k);
        answered.assign(n, 0);
    });
    const auto grid = NeighborGrid(impl_->points, k);
    fill.wait();
    if (!grid) {
        RunBatch(*this, n, true, impl_->points.data(), progress, table);
        return table;
    }
    // Most rows from the grid's blocks (the same table: same ranking, same float distances), the
    // rest (near a sparse region's edge) from wider blocks of the grid, and the few left after
    // those (far outliers) from the tree, as RunBatch answers them.
    ProgressTracker tracker(progress, static_cast<double>(n), "neighbour search");
    grid->KnnInBlock(k, table.indices.data(), table.dist2.data(), answered.data(),
                     [&](std::size_t points) { tracker.Advance(0.8 * static_cast<double>(points)); });
    std::vector<std::uint32_t> rest;
    for (std::size_t i = 0; i < n; ++i)
        if (!answered[i]) rest.push_back(static_cast<std::uint32_t>(i));
    const double per_row = rest.empty() ? 0.0 : 0.2 * static_cast<double>(n) / static_cast<double>(rest.size());
    const auto advance = [&](std::size_t rows) { tracker.Advance(per_row * static_cast<double>(rows)); };
    grid->KnnInWideBlock(impl_->points, rest, k, 2, kMaxGridRing, table.indices.data(), table.dist2.data(),
                         answered.data(), advance);
    std::erase_if(rest, [&](std::uint32_t i) { return answered[i] != 0; });
    if (!rest.empty() && rest.size() <= kWholeGridRows) {
        grid->KnnInWideBlock(impl_->points, rest, k, 1 << 20, 1 << 20, table.indices.data(), table.dist2.data(),
                             answered.data(), {});
        std::erase_if(rest, [&](std::uint32_t i) { return answered[i] != 0; });
    }
    if (rest.empty()) return table;
    impl_->Tree();  // built once, before the threads ask for it
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, rest.size(), 256), [&](const tbb::blocked_range<std::size_t>& r) {
        std::vector<Neighbor> buf;
        for (std::size_t t = r.begin(); t != r.end(); ++t) FillRow(*this, impl_->points[rest[t]], rest[t], true, buf, table);
    });
    return table;
}

void KdTree::KnnRow(std::size_t i, int k, std::uint32_t* indices, float* dist2, std::vector<Neighbor>& buf) const {
    SURFEL_CHECK(k > 0 && i < size(), "k = " << k << ", i = " << i);
    FillRow(*this, impl_->points[i], i, k, true, buf, indices, dist2);
}

KnnTable KdTree::KnnBatch(std::span<const Vec3f> queries, int k, const ProgressFn& progress) const {
    return RunBatch(*this, queries.size(), k, false, queries.data(), progress);
}

}  // namespace surfel
