#include <gtest/gtest.h>

#include <filesystem>

#include "surfel/base/shapes.h"
#include "surfel/io/ply.h"
#include "surfel/surface/local_analysis.h"

namespace surfel {
namespace {

double AngleDeg(const Vec3f& a, const Vec3d& b) {
    return std::acos(std::clamp(a.cast<double>().normalized().dot(b.normalized()), -1.0, 1.0)) * 180.0 / M_PI;
}

TEST(Normals, TorusWithinTwoDegreesAndAllOutward) {
    ShapeOptions o;
    o.points = 20000;
    const PointCloud c = SampleShape(Shape::kTorus, o);
    KdTree tree(c.positions);
    const NormalResult r = EstimateNormals(tree);
    EXPECT_EQ(r.components, 1u);
    double worst = 0;
    for (std::size_t i = 0; i < c.size(); ++i) {
        const double a = AngleDeg(r.normals[i], ShapeNormal(Shape::kTorus, c.positions[i].cast<double>()));
        worst = std::max(worst, a);
    }
    EXPECT_LT(worst, 2.0);  // every normal outward (no flip) and within 2 degrees
}

TEST(Normals, SphereAllOutwardWithNoise) {
    ShapeOptions o;
    o.points = 10000;
    o.noise = 0.005;
    const PointCloud c = SampleShape(Shape::kSphere, o);
    KdTree tree(c.positions);
    const NormalResult r = EstimateNormals(tree);
    for (std::size_t i = 0; i < c.size(); ++i) ASSERT_GT(r.normals[i].dot(c.positions[i].normalized()), 0.9f) << i;
}

TEST(Normals, TwoSeparateComponentsEachOrientedOutward) {
    ShapeOptions o;
    o.points = 4000;
    PointCloud a = SampleShape(Shape::kSphere, o), b = SampleShape(Shape::kBox, o);
    const Vec3f shift(5, 0, 0);
    for (auto& p : b.positions) p += shift;
    a.positions.insert(a.positions.end(), b.positions.begin(), b.positions.end());
    KdTree tree(a.positions);
    const NormalResult r = EstimateNormals(tree);
    EXPECT_EQ(r.components, 2u);
    for (std::size_t i = 0; i < a.size(); ++i) {
        const Vec3f center = i < 4000 ? Vec3f::Zero() : shift;
        ASSERT_GT(r.normals[i].dot(a.positions[i] - center), 0.0f) << i;
    }
}

TEST(Normals, SurfaceVariationZeroOnPlaneAndPositiveOnSphere) {
    ShapeOptions o;
    o.points = 5000;
    KdTree plane(SampleShape(Shape::kPlane, o).positions);
    const NormalResult rp = EstimateNormals(plane, {.orient = false});
    for (float v : rp.surface_variation) ASSERT_LT(v, 1e-9f);
    o.scale = 0.1;  // a small sphere: strong curvature relative to the neighbourhood
    KdTree sphere(SampleShape(Shape::kSphere, o).positions);
    const NormalResult rs = EstimateNormals(sphere, {.orient = false});
    for (float v : rs.surface_variation) ASSERT_GT(v, 1e-5f);
}

TEST(Density, SpacingOfARegularGrid) {
    std::vector<Vec3f> pts;
    for (int i = 0; i < 50; ++i)
        for (int j = 0; j < 50; ++j) pts.emplace_back(0.01f * i, 0.01f * j, 0.0f);
    KdTree tree(pts);
    const SamplingDensity d = ComputeSamplingDensity(tree, 6);
    // Interior: 6th neighbour at sqrt(2) s, rho = 6 / (2 pi s^2), eta = s sqrt(pi / 3).
    EXPECT_NEAR(d.median_spacing, 0.01 * std::sqrt(M_PI / 3.0), 1e-5);
    EXPECT_NEAR(DefaultScale(d), 2 * 0.01 * std::sqrt(M_PI / 3.0), 2e-5);
}

TEST(Normals, BunnyMatchesGroundTruth) {
    const std::string path = std::string(SURFEL_SHARED_DATA_DIR) + "/bunny_normals.ply";
    if (!std::filesystem::exists(path)) GTEST_SKIP() << path << " not present";
    const PointCloud truth = ReadPly(path);
    KdTree tree(truth.positions);
    const NormalResult r = EstimateNormals(tree);
    std::size_t good = 0;
    for (std::size_t i = 0; i < truth.size(); ++i)
        good += AngleDeg(r.normals[i], truth.normals[i].cast<double>()) < 30.0;
    const double fraction = double(good) / truth.size();
    std::printf("bunny: %.2f%% of normals within 30 degrees of the mesh normals\n", 100 * fraction);
    EXPECT_GE(fraction, 0.99);
}

}  // namespace
}  // namespace surfel
