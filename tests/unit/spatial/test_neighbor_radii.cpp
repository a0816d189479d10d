#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <random>

#include "surfel/base/shapes.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/spatial/neighbor_radii.h"
#include "surfel/spatial/uniform_grid.h"

namespace surfel {
namespace {

// The k-th smallest distance from p_i to the other points, by sorting all of them.
std::vector<float> BruteKth(std::span<const Vec3f> pts, int k) {
    std::vector<float> out(pts.size());
    std::vector<float> d;
    for (std::size_t i = 0; i < pts.size(); ++i) {
        d.clear();
        for (std::size_t j = 0; j < pts.size(); ++j)
            if (j != i) d.push_back((pts[j] - pts[i]).squaredNorm());
        std::nth_element(d.begin(), d.begin() + (k - 1), d.end());
        out[i] = std::sqrt(d[k - 1]);
    }
    return out;
}

void ExpectSame(const std::vector<float>& got, const std::vector<float>& want, const char* what) {
    ASSERT_EQ(got.size(), want.size()) << what;
    for (std::size_t i = 0; i < got.size(); ++i)
        ASSERT_NEAR(got[i], want[i], 1e-6f * (1.0f + want[i])) << what << ", point " << i;
}

TEST(KthNeighborDistances, SurfaceVolumeAndUnevenCloudsMatchBruteForce) {
    ShapeOptions o;
    o.points = 2500;
    o.noise = 0.01;
    const PointCloud torus = SampleShape(Shape::kTorus, o);
    // A filled cube (a volume: the surface guess of the cell is far off and gets refined) and a
    // dense cluster beside a sparse one (many points search beyond their block).
    std::vector<Vec3f> cube, uneven;
    std::mt19937 rng(5);
    std::uniform_real_distribution<float> u(0.0f, 1.0f);
    for (int i = 0; i < 2000; ++i) cube.emplace_back(u(rng), u(rng), u(rng));
    for (int i = 0; i < 1500; ++i) uneven.emplace_back(0.01f * u(rng), 0.01f * u(rng), 0.01f * u(rng));
    for (int i = 0; i < 300; ++i) uneven.emplace_back(u(rng), u(rng), 0.0f);
    for (const int k : {1, 6, 16}) {
        ExpectSame(KthNeighborDistances(torus.positions, k), BruteKth(torus.positions, k), "torus");
        ExpectSame(KthNeighborDistances(cube, k), BruteKth(cube, k), "cube");
        ExpectSame(KthNeighborDistances(uneven, k), BruteKth(uneven, k), "uneven");
    }
}

TEST(KthNeighborDistances, LatticeTiesDuplicatesAndSmallClouds) {
    // A lattice: many neighbours at exactly the same distance, on cell boundaries.
    std::vector<Vec3f> lattice;
    for (int x = 0; x < 12; ++x)
        for (int y = 0; y < 12; ++y)
            for (int z = 0; z < 3; ++z) lattice.emplace_back(0.1f * x, 0.1f * y, 0.1f * z);
    for (const int k : {1, 4, 6, 26}) ExpectSame(KthNeighborDistances(lattice, k), BruteKth(lattice, k), "lattice");
    // A duplicate counts as a neighbour at distance 0.
    std::vector<Vec3f> dup = lattice;
    dup.push_back(lattice[40]);
    const auto r = KthNeighborDistances(dup, 1);
    EXPECT_EQ(r[40], 0.0f);
    EXPECT_EQ(r.back(), 0.0f);
    // k is clamped to n - 1; fewer than 2 points or all coincident give 0.
    const std::vector<Vec3f> three = {{0, 0, 0}, {1, 0, 0}, {0, 2, 0}};
    ExpectSame(KthNeighborDistances(three, 10), {2.0f, std::sqrt(5.0f), std::sqrt(5.0f)}, "three");
    EXPECT_EQ(KthNeighborDistances(std::vector<Vec3f>{{1, 2, 3}}, 6), std::vector<float>{0.0f});
    EXPECT_EQ(KthNeighborDistances(std::vector<Vec3f>(5, Vec3f(1, 1, 1)), 3), std::vector<float>(5, 0.0f));
}

TEST(KthNeighborDistances, SparseCloudsAndLargeKUseTheKdTree) {
    ShapeOptions o;
    o.points = 1500;
    std::vector<Vec3f> pts = SampleShape(Shape::kSphere, o).positions;
    pts.emplace_back(1e4f, 1e4f, 1e4f);  // the box is too large for a dense grid
    const KdTree tree(pts);
    const KnnTable knn = tree.KnnAll(6);
    std::vector<float> want(pts.size());
    for (std::size_t i = 0; i < pts.size(); ++i) want[i] = std::sqrt(knn.Dist2(i)[5]);
    ExpectSame(KthNeighborDistances(pts, 6), want, "sparse");
    ExpectSame(KthNeighborDistances(pts, 6, &tree), want, "sparse, given tree");
    pts.pop_back();
    ExpectSame(KthNeighborDistances(pts, 70), BruteKth(pts, 70), "k = 70");
}

TEST(UniformGrid, KthNeighborInBlockIsExactOrDeclines) {
    ShapeOptions o;
    o.points = 3000;
    o.noise = 0.02;
    const PointCloud torus = SampleShape(Shape::kTorus, o);
    const UniformGrid grid(torus.positions, 0.15f);  // about 1.5 x the 6th distance
    ASSERT_TRUE(grid.dense());
    const auto want = BruteKth(torus.positions, 6);
    const auto got = grid.KthNeighborDist2InBlock(6);
    std::size_t answered = 0;
    for (std::size_t i = 0; i < got.size(); ++i) {
        if (got[i] < 0) continue;
        ++answered;
        ASSERT_NEAR(std::sqrt(got[i]), want[i], 1e-6f) << "point " << i;
    }
    EXPECT_GT(answered, got.size() / 2);
    std::vector<Vec3f> far = torus.positions;
    far.emplace_back(1e4f, 0.0f, 0.0f);
    EXPECT_TRUE(UniformGrid(far, 0.08f).KthNeighborDist2InBlock(6).empty());  // sparse layout
}

// NearestDistances from any KnnAll(K) table: KthNeighborDistances(points, 1) bit for bit, also on
// the rows KthNeighborDistances searches outside the grid's block, whose squared distances it sums
// in another order than the table (x^2 + (y^2 + z^2) against (x^2 + y^2) + z^2).
TEST(NearestDistances, FromATableEqualKthNeighborDistancesBitForBit) {
    ShapeOptions o;
    o.points = 4000;
    o.noise = 0.01;
    std::vector<std::pair<const char*, std::vector<Vec3f>>> clouds;
    clouds.emplace_back("torus", SampleShape(Shape::kTorus, o).positions);
    std::mt19937 rng(9);
    std::uniform_real_distribution<float> u(0.0f, 1.0f);
    std::vector<Vec3f> cube, uneven;
    for (int i = 0; i < 3000; ++i) cube.emplace_back(u(rng), u(rng), u(rng));
    for (int i = 0; i < 3000; ++i) uneven.emplace_back(0.01f * u(rng), 0.01f * u(rng), 0.01f * u(rng));
    for (int i = 0; i < 2000; ++i) uneven.emplace_back(u(rng), u(rng), 0.3f * u(rng));
    clouds.emplace_back("cube", cube);
    clouds.emplace_back("uneven", uneven);
    std::vector<Vec3f> lattice;
    for (int x = 0; x < 12; ++x)
        for (int y = 0; y < 12; ++y)
            for (int z = 0; z < 3; ++z) lattice.emplace_back(0.1f * x, 0.1f * y, 0.1f * z);
    for (int i = 0; i < 40; ++i) lattice.push_back(lattice[7 * i]);  // duplicates: distance 0
    clouds.emplace_back("lattice", lattice);
    clouds.emplace_back("three", std::vector<Vec3f>{{0, 0, 0}, {1, 0, 0}, {0, 2, 0}});
    clouds.emplace_back("coincident", std::vector<Vec3f>(5, Vec3f(1, 1, 1)));
    std::vector<Vec3f> far = SampleShape(Shape::kSphere, o).positions;
    far.emplace_back(1e4f, 1e4f, 1e4f);  // no dense grid: KnnAll(1)'s column
    clouds.emplace_back("far", far);
    std::size_t outward_differs = 0;  // rows where the table's own first column is off by a bit
    for (const auto& [name, pts] : clouds) {
        SCOPED_TRACE(name);
        const KdTree tree(pts);
        const std::vector<float> want = KthNeighborDistances(pts, 1);
        for (const int k : {1, 10, 16}) {
            const KnnTable knn = tree.KnnAll(std::min<int>(k, static_cast<int>(pts.size()) - 1));
            const std::vector<float> got = NearestDistances(pts, knn);
            ASSERT_EQ(got.size(), want.size());
            for (std::size_t i = 0; i < pts.size(); ++i) {
                ASSERT_EQ(std::memcmp(&got[i], &want[i], sizeof(float)), 0) << "k " << k << ", point " << i << ": " << got[i] << " " << want[i];
                if (k == 16 && std::sqrt(knn.Dist2(i)[0]) != want[i]) ++outward_differs;
            }
        }
    }
    EXPECT_GT(outward_differs, 0u);  // the case the grid's reach decides is exercised
    EXPECT_EQ(NearestDistances(std::vector<Vec3f>{{1, 2, 3}}, KnnTable{}), std::vector<float>{0.0f});
}

}  // namespace
}  // namespace surfel
