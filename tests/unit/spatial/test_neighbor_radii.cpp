#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
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

}  // namespace
}  // namespace surfel
