#include <gtest/gtest.h>
#include <tbb/global_control.h>

#include <algorithm>
#include <limits>
#include <random>

#include "surfel/base/shapes.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/spatial/uniform_grid.h"

namespace surfel {
namespace {

std::vector<Neighbor> BruteKnn(std::span<const Vec3f> pts, const Vec3f& q, int k) {
    std::vector<Neighbor> all;
    for (std::size_t i = 0; i < pts.size(); ++i) all.push_back({std::uint32_t(i), (pts[i] - q).squaredNorm()});
    std::sort(all.begin(), all.end(), [](auto& a, auto& b) { return a.dist2 < b.dist2 || (a.dist2 == b.dist2 && a.index < b.index); });
    all.resize(std::min<std::size_t>(k, all.size()));
    return all;
}

class KdTreeTest : public ::testing::Test {
protected:
    void SetUp() override {
        ShapeOptions o;
        o.points = 3000;
        o.noise = 0.02;
        cloud_ = SampleShape(Shape::kTorus, o);
        std::mt19937 rng(3);
        std::uniform_real_distribution<float> u(-1.6f, 1.6f);
        for (int i = 0; i < 200; ++i) queries_.emplace_back(u(rng), u(rng), u(rng) * 0.3f);
    }
    PointCloud cloud_;
    std::vector<Vec3f> queries_;
};

TEST_F(KdTreeTest, KnnMatchesBruteForce) {
    KdTree tree(cloud_.positions);
    std::vector<Neighbor> got;
    for (const auto& q : queries_) {
        tree.Knn(q, 16, &got);
        const auto want = BruteKnn(cloud_.positions, q, 16);
        ASSERT_EQ(got.size(), want.size());
        // FLANN sums the squared differences in another order: equal to 4 ulps.
        for (std::size_t j = 0; j < want.size(); ++j) EXPECT_FLOAT_EQ(got[j].dist2, want[j].dist2);
        std::vector<std::uint32_t> a, b;
        for (std::size_t j = 0; j + 1 < want.size(); ++j) {  // the last may tie with the next
            a.push_back(got[j].index);
            b.push_back(want[j].index);
        }
        std::sort(a.begin(), a.end());
        std::sort(b.begin(), b.end());
        EXPECT_EQ(a, b);
    }
}

TEST_F(KdTreeTest, RadiusMatchesBruteForce) {
    KdTree tree(cloud_.positions);
    std::vector<Neighbor> got;
    for (const auto& q : queries_) {
        tree.Radius(q, 0.15f, &got);
        std::vector<std::uint32_t> a, b;
        for (auto& n : got) a.push_back(n.index);
        for (std::size_t i = 0; i < cloud_.size(); ++i)
            if ((cloud_.positions[i] - q).squaredNorm() <= 0.15f * 0.15f) b.push_back(std::uint32_t(i));
        std::sort(a.begin(), a.end());
        EXPECT_EQ(a, b);
    }
}

TEST_F(KdTreeTest, KnnAllExcludesSelfAndIsDeterministic) {
    KdTree tree(cloud_.positions);
    const KnnTable t1 = tree.KnnAll(8), t2 = tree.KnnAll(8);
    EXPECT_EQ(t1.indices, t2.indices);
    for (std::size_t i = 0; i < t1.size(); ++i) {
        for (auto j : t1.Row(i)) EXPECT_NE(j, i);
        const auto want = BruteKnn(cloud_.positions, cloud_.positions[i], 9);
        EXPECT_FLOAT_EQ(t1.Dist2(i)[7], want[8].dist2);
    }
}

// KnnAll answers most rows from a uniform grid: each row must be the tree's own answer to the
// bit (the k smallest (distance, index) pairs among the other points; ties at the k-th ranked
// by index), on clouds full of ties (a lattice, duplicates), with sparse outliers (rows the grid
// leaves to the tree) and on a noisy torus.
KnnTable TreeRows(const KdTree& tree, int k) {
    const auto pts = tree.points();
    const KnnTable all = tree.KnnBatch(pts, k + 1);  // the tree's search, self included
    KnnTable t;
    t.k = k;
    for (std::size_t i = 0; i < pts.size(); ++i) {
        int taken = 0;
        for (int j = 0; j < k + 1 && taken < k; ++j) {
            if (all.Row(i)[j] == i) continue;
            t.indices.push_back(all.Row(i)[j]);
            t.dist2.push_back(all.Dist2(i)[j]);
            ++taken;
        }
        for (; taken < k; ++taken) t.indices.push_back(UINT32_MAX), t.dist2.push_back(std::numeric_limits<float>::infinity());
    }
    return t;
}

void ExpectKnnAllIsTheTreesAnswer(const std::vector<Vec3f>& pts, int k) {
    const KdTree tree(pts);
    const KnnTable got = tree.KnnAll(k), want = TreeRows(tree, k);
    ASSERT_EQ(got.indices.size(), want.indices.size());
    for (std::size_t i = 0; i < got.size(); ++i) {
        for (int j = 0; j < k; ++j) {
            ASSERT_EQ(got.Row(i)[j], want.Row(i)[j]) << "row " << i << " rank " << j;
            ASSERT_EQ(got.Dist2(i)[j], want.Dist2(i)[j]) << "row " << i << " rank " << j;
        }
        // Ranked by (distance, index); ties at the last rank resolved by index, not by the
        // order a search happened to visit them.
        for (int j = 1; j < k; ++j)
            EXPECT_TRUE(got.Dist2(i)[j - 1] < got.Dist2(i)[j] ||
                        (got.Dist2(i)[j - 1] == got.Dist2(i)[j] && got.Row(i)[j - 1] < got.Row(i)[j]))
                << "row " << i;
        if (i % 37 != 0) continue;
        // Brute force on every 37th row, with FLANN's float sum ((dx^2 + dy^2) + dz^2; Eigen's
        // squaredNorm differs in the last bits): as many others nearer than the k-th as the row
        // holds, and no tie of the k-th with a smaller index left out.
        const float kth = got.Dist2(i)[k - 1];
        int nearer = 0, tied_before = 0;
        std::uint32_t last_kept = got.Row(i)[k - 1];
        for (std::size_t j = 0; j < pts.size(); ++j) {
            if (j == i) continue;
            const float dx = pts[i].x() - pts[j].x(), dy = pts[i].y() - pts[j].y(), dz = pts[i].z() - pts[j].z();
            const float d2 = dx * dx + dy * dy + dz * dz;
            nearer += d2 < kth;
            tied_before += d2 == kth && j <= last_kept;
        }
        int tied_in_row = 0, nearer_in_row = 0;
        for (int j = 0; j < k; ++j) (got.Dist2(i)[j] == kth ? tied_in_row : nearer_in_row) += 1;
        EXPECT_EQ(nearer, nearer_in_row) << "row " << i;
        EXPECT_EQ(tied_before, tied_in_row) << "row " << i << ": ties at the k-th not the smallest indices";
    }
}

TEST(KdTree, KnnAllRowsAreTheTreesOnATorus) {
    ShapeOptions o;
    o.points = 20000;
    o.noise = 0.01;
    const PointCloud c = SampleShape(Shape::kTorus, o);
    ExpectKnnAllIsTheTreesAnswer(c.positions, 16);
    ExpectKnnAllIsTheTreesAnswer(c.positions, 6);
}

TEST(KdTree, KnnAllRowsAreTheTreesOnALatticeFullOfTies) {
    std::vector<Vec3f> pts;
    for (int x = 0; x < 60; ++x)
        for (int y = 0; y < 50; ++y) pts.emplace_back(0.01f * x, 0.01f * y, 0.0f);
    ExpectKnnAllIsTheTreesAnswer(pts, 8);   // 4 at one spacing, 4 at the diagonal
    ExpectKnnAllIsTheTreesAnswer(pts, 6);   // the 5th and 6th of 4 tied diagonals
    ExpectKnnAllIsTheTreesAnswer(pts, 16);
}

TEST(KdTree, KnnAllRowsAreTheTreesWithDuplicatesAndOutliers) {
    ShapeOptions o;
    o.points = 5000;
    PointCloud c = SampleShape(Shape::kSphere, o);
    std::vector<Vec3f> pts;
    for (const Vec3f& p : c.positions) pts.insert(pts.end(), {p, p, p});  // each point three times
    for (int i = 0; i < 30; ++i) pts.emplace_back(5.0f + 0.7f * i, 3.0f, -2.0f);  // sparse: the tree's rows
    ExpectKnnAllIsTheTreesAnswer(pts, 2);   // a point's own duplicates
    ExpectKnnAllIsTheTreesAnswer(pts, 10);
}

// More outliers than KnnAll searches in the whole grid: the rows past the 9 x 9 x 9 blocks come
// from the tree, the same bits.
TEST(KdTree, KnnAllRowsAreTheTreesWithManyFarOutliers) {
    ShapeOptions o;
    o.points = 8000;
    std::vector<Vec3f> pts = SampleShape(Shape::kSphere, o).positions;
    for (int i = 0; i < 80; ++i) pts.emplace_back(4.0f + 0.9f * i, 0.3f * (i % 7), -2.0f - 0.5f * (i % 3));
    ExpectKnnAllIsTheTreesAnswer(pts, 8);
}

// The wider blocks answer the rows the 3 x 3 x 3 blocks leave, exactly (the tree's rows), and
// the whole grid (ring 1 << 20) every row with k others.
TEST(UniformGrid, KnnInWideBlockRowsAreTheTrees) {
    ShapeOptions o;
    o.points = 6000;
    o.noise = 0.02;
    std::vector<Vec3f> pts = SampleShape(Shape::kTorus, o).positions;
    for (int i = 0; i < 12; ++i) pts.emplace_back(2.0f + 0.3f * i, 0.1f * i, 0.0f);  // sparse
    const int k = 12;
    const KdTree tree(pts);
    const KnnTable want = TreeRows(tree, k);
    const UniformGrid grid(pts, 0.05f);  // small cells: many rows reach past 3 x 3 x 3
    ASSERT_TRUE(grid.dense());
    const std::size_t n = pts.size();
    for (const int max_ring : {3, 1 << 20}) {
        std::vector<std::uint32_t> indices(n * k, UINT32_MAX);
        std::vector<float> dist2(n * k, -1.0f);
        std::vector<std::uint8_t> answered(n, 0);
        grid.KnnInBlock(k, indices.data(), dist2.data(), answered.data(), {});
        std::vector<std::uint32_t> rest;
        for (std::size_t i = 0; i < n; ++i)
            if (!answered[i]) rest.push_back(static_cast<std::uint32_t>(i));
        ASSERT_GT(rest.size(), 100u);
        std::size_t calls = 0;
        grid.KnnInWideBlock(pts, rest, k, 2, max_ring, indices.data(), dist2.data(), answered.data(),
                            [&](std::size_t rows) { calls += rows; });
        EXPECT_EQ(calls, rest.size());
        std::size_t left = 0;
        for (std::size_t i = 0; i < n; ++i) {
            if (!answered[i]) {
                ++left;
                continue;
            }
            for (int j = 0; j < k; ++j) {
                ASSERT_EQ(indices[i * k + j], want.Row(i)[j]) << "row " << i << " rank " << j << " ring " << max_ring;
                ASSERT_EQ(dist2[i * k + j], want.Dist2(i)[j]) << "row " << i << " rank " << j << " ring " << max_ring;
            }
        }
        if (max_ring == 3) EXPECT_GT(left, 0u);  // the sparse points reach past 7 x 7 x 7
        else EXPECT_EQ(left, 0u);
        EXPECT_LT(left, rest.size());
    }
}

// The same neighbours whatever the thread count (KnnAll's queries run in parallel).
TEST(KdTree, SameNeighboursWhateverTheThreadCount) {
    ShapeOptions o;
    o.points = 100000;
    o.noise = 0.01;
    const PointCloud c = SampleShape(Shape::kTorus, o);
    KnnTable serial;
    std::vector<Neighbor> radius_serial, radius_parallel;
    {
        const tbb::global_control one(tbb::global_control::max_allowed_parallelism, 1);
        const KdTree tree(c.positions);
        serial = tree.KnnAll(8);
        tree.Radius(c.positions[0], 0.05f, &radius_serial);
    }
    const KdTree tree(c.positions);
    const KnnTable parallel = tree.KnnAll(8);
    tree.Radius(c.positions[0], 0.05f, &radius_parallel);
    EXPECT_EQ(serial.indices, parallel.indices);
    EXPECT_EQ(serial.dist2, parallel.dist2);
    ASSERT_EQ(radius_serial.size(), radius_parallel.size());
    for (std::size_t i = 0; i < radius_serial.size(); ++i) EXPECT_EQ(radius_serial[i].index, radius_parallel[i].index);
}

TEST(KdTree, FewerPointsThanK) {
    std::vector<Vec3f> pts = {{0, 0, 0}, {1, 0, 0}};
    KdTree tree(pts);
    std::vector<Neighbor> got;
    tree.Knn({0.9f, 0, 0}, 5, &got);
    ASSERT_EQ(got.size(), 2u);
    EXPECT_EQ(got[0].index, 1u);
    KdTree empty(std::span<const Vec3f>{});
    EXPECT_EQ(empty.Nearest({0, 0, 0}).index, UINT32_MAX);
}

std::vector<std::uint32_t> GridWithin(const UniformGrid& grid, const Vec3f& q, float r) {
    std::vector<std::uint32_t> a;
    grid.ForEachWithin(q, r, [&](std::uint32_t i, const Vec3f&, float) { a.push_back(i); });
    std::sort(a.begin(), a.end());
    return a;
}

std::vector<std::uint32_t> BruteWithin(std::span<const Vec3f> pts, const Vec3f& q, float r) {
    std::vector<std::uint32_t> b;
    for (std::size_t i = 0; i < pts.size(); ++i)
        if ((pts[i] - q).squaredNorm() <= r * r) b.push_back(std::uint32_t(i));
    return b;
}

TEST_F(KdTreeTest, UniformGridMatchesBruteForceInBothLayouts) {
    // A compact torus gets the dense layout; the same torus beside a far outlier the sparse one.
    std::vector<Vec3f> sparse_pts = cloud_.positions;
    sparse_pts.emplace_back(1000.0f, 1000.0f, 1000.0f);
    const UniformGrid dense(cloud_.positions, 0.3f), sparse(sparse_pts, 0.3f);
    ASSERT_TRUE(dense.dense());
    ASSERT_FALSE(sparse.dense());
    for (const float r : {0.3f, 0.17f, 0.05f})
        for (const auto& q : queries_) {
            EXPECT_EQ(GridWithin(dense, q, r), BruteWithin(cloud_.positions, q, r)) << "dense, r " << r;
            EXPECT_EQ(GridWithin(sparse, q, r), BruteWithin(sparse_pts, q, r)) << "sparse, r " << r;
        }
    // Far outside the box, and non-finite: nothing, no overflow.
    EXPECT_TRUE(GridWithin(dense, {1e30f, 0, 0}, 0.3f).empty());
    EXPECT_TRUE(GridWithin(dense, {-1e30f, -1e30f, 0}, 0.3f).empty());
    EXPECT_TRUE(GridWithin(dense, {std::numeric_limits<float>::quiet_NaN(), 0, 0}, 0.3f).empty());
}

TEST(UniformGrid, PointsAtExactlyTheRadiusAreFound) {
    // A lattice with spacing 0.25: from a lattice point, neighbours lie at exactly 0.25 and 0.5,
    // on cell boundaries.
    std::vector<Vec3f> pts;
    for (int x = 0; x < 9; ++x)
        for (int y = 0; y < 9; ++y)
            for (int z = 0; z < 9; ++z) pts.emplace_back(0.25f * x, 0.25f * y, 0.25f * z);
    const UniformGrid grid(pts, 0.5f);
    EXPECT_TRUE(grid.dense());
    for (const Vec3f& q : {Vec3f(1, 1, 1), Vec3f(0, 0, 0), Vec3f(2, 2, 2), Vec3f(0.5f, 1.75f, 0.25f)})
        for (const float r : {0.25f, 0.5f}) EXPECT_EQ(GridWithin(grid, q, r), BruteWithin(pts, q, r)) << q.transpose() << " r " << r;
}

}  // namespace
}  // namespace surfel
