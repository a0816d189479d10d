#include <gtest/gtest.h>

#include "surfel/base/shapes.h"
#include "surfel/surface/surface_error.h"

namespace surfel {
namespace {

TEST(SurfaceError, SphereAgainstItselfIsNearZero) {
    ShapeOptions o;
    o.points = 8000;
    const PointCloud a = SampleShape(Shape::kSphere, o);
    o.seed = 99;  // a different sampling of the same surface
    const PointCloud b = SampleShape(Shape::kSphere, o);
    const SurfaceError e = MeasureSurfaceError(a, b);
    EXPECT_LT(e.max, 2e-3);
    EXPECT_LT(e.avg, 3e-4);
    EXPECT_EQ(e.samples, a.size());
}

TEST(SurfaceError, OffsetSphereMeasuresTheOffset) {
    ShapeOptions o;
    o.points = 8000;
    const PointCloud a = SampleShape(Shape::kSphere, o);
    o.scale = 1.02;
    o.seed = 5;
    const PointCloud b = SampleShape(Shape::kSphere, o);
    const SurfaceError e = MeasureSurfaceError(a, b, {.max_samples = 2000});
    EXPECT_NEAR(e.avg, 0.02, 1e-3);
    EXPECT_NEAR(e.max, 0.02, 3e-3);
    EXPECT_EQ(e.samples, 2000u);
    EXPECT_NEAR(e.avg_relative(), 0.02 / e.diagonal, 1e-4);
}

}  // namespace
}  // namespace surfel
