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
