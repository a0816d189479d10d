#include <gtest/gtest.h>

#include "surfel/base/shapes.h"

namespace surfel {
namespace {

TEST(Shapes, SamplesLieOnTheSurfaceWithExactNormals) {
    for (Shape s : AllShapes()) {
        ShapeOptions o;
        o.points = 5000;
        o.normals = true;
        o.scale = 2.0;
        const PointCloud c = SampleShape(s, o);
        ASSERT_EQ(c.size(), 5000u) << ShapeName(s);
        for (std::size_t i = 0; i < c.size(); ++i) {
            const Vec3d p = c.positions[i].cast<double>();
            ASSERT_LT(ShapeDistance(s, p, 2.0), 1e-5) << ShapeName(s) << " point " << i;
            ASSERT_NEAR(c.normals[i].norm(), 1.0f, 1e-5f);
            if (s != Shape::kBox && s != Shape::kCylinder) {  // edges are ambiguous there
                ASSERT_GT(c.normals[i].cast<double>().dot(ShapeNormal(s, p, 2.0)), 0.9999) << ShapeName(s);
            }
        }
    }
}

TEST(Shapes, UniformByArea) {
    // Sphere: each octant holds 1/8 of the points; torus: outer half (x^2+y^2 > R^2) holds
    // (R + 2r/pi) / (2R) of the area.
    ShapeOptions o;
    o.points = 80000;
    const PointCloud sphere = SampleShape(Shape::kSphere, o);
    std::size_t pos = 0;
    for (const auto& p : sphere.positions) pos += (p.x() > 0 && p.y() > 0 && p.z() > 0);
    EXPECT_NEAR(pos / 80000.0, 0.125, 0.005);
    const PointCloud torus = SampleShape(Shape::kTorus, o);
    std::size_t outer = 0;
    for (const auto& p : torus.positions) outer += (p.x() * p.x() + p.y() * p.y() > 1.0f);
    EXPECT_NEAR(outer / 80000.0, (1.0 + 2 * kTorusMinorRatio / M_PI) / 2.0, 0.006);
}

TEST(Shapes, NoiseHasTheRequestedDeviationAndSeedsRepeat) {
    ShapeOptions o;
    o.points = 20000;
    o.noise = 0.01;
    o.seed = 7;
    const PointCloud a = SampleShape(Shape::kSphere, o), b = SampleShape(Shape::kSphere, o);
    EXPECT_EQ(a.positions, b.positions);
    double s2 = 0;
    for (const auto& p : a.positions) s2 += std::pow(p.cast<double>().norm() - 1.0, 2);
    EXPECT_NEAR(std::sqrt(s2 / a.size()), 0.01, 0.0005);
    o.seed = 8;
    EXPECT_NE(SampleShape(Shape::kSphere, o).positions, a.positions);
}

}  // namespace
}  // namespace surfel
