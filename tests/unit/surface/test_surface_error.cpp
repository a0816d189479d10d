#include <gtest/gtest.h>

#include <limits>
#include <string>
#include <vector>

#include "surfel/base/error.h"
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

// The notes' Delta_avg is an area integral (Q uniform by area). A sphere sampled nine times more
// densely at the poles than at the equator, against the same sphere moved by t along z: the
// distance is about t |cos theta|, whose mean over the sphere's area is t / 2. The plain mean over
// the samples leans to the poles, where the distance is largest: t E[|c| (1 + 8c^2)] / E[1 + 8c^2]
// = t * 2.5 / (11 / 3) = 0.682 t.
TEST(SurfaceError, AverageIsOverAreaWhateverTheSamplingDensity) {
    ShapeOptions o;
    o.points = 60000;
    const PointCloud dense = SampleShape(Shape::kSphere, o);
    PointCloud a;
    std::uint64_t state = 12345;
    for (const Vec3f& p : dense.positions) {
        state = state * 6364136223846793005ull + 1442695040888963407ull;
        const double u = static_cast<double>(state >> 11) / 9007199254740992.0;
        if (u * 9.0 < 1.0 + 8.0 * p.z() * p.z()) a.positions.push_back(p);
    }
    const double t = 0.02;
    o.points = 8000;
    o.seed = 7;
    PointCloud b = SampleShape(Shape::kSphere, o);
    for (Vec3f& p : b.positions) p.z() += static_cast<float>(t);
    const SurfaceError e = MeasureSurfaceError(a, b);
    EXPECT_NEAR(e.avg, 0.5 * t, 0.03 * t);
    EXPECT_NEAR(e.avg_per_sample, 2.5 / (11.0 / 3.0) * t, 0.03 * t);
    EXPECT_NEAR(e.max, t, 0.1 * t);
}

// Validate: each bad field names itself and its range, and MeasureSurfaceError checks first.
TEST(SurfaceErrorOptions, BadFieldsNameThemselves) {
    const float inf = std::numeric_limits<float>::infinity();
    const std::vector<std::pair<SurfaceErrorOptions, std::string>> cases = {
        {SurfaceErrorOptions{.h_source = -0.01f}, "h_source: must be finite and at least 0, got -0.01"},
        {SurfaceErrorOptions{.h_target = inf}, "h_target: must be finite and at least 0, got inf"},
        {SurfaceErrorOptions{.degree = 3}, "degree: must lie in 0..2, got 3"},
        {SurfaceErrorOptions{.degree = -2}, "degree: must lie in 0..2, got -2"},
    };
    ShapeOptions o;
    o.points = 500;
    const PointCloud a = SampleShape(Shape::kSphere, o);
    for (const auto& [options, message] : cases) {
        for (int call = 0; call < 2; ++call) {
            try {
                if (call == 0) options.Validate();
                else MeasureSurfaceError(a, a, options);
                ADD_FAILURE() << message << ": accepted";
            } catch (const Error& e) {
                EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument) << message;
                EXPECT_EQ(e.what(), message);
            }
        }
    }
    EXPECT_NO_THROW(SurfaceErrorOptions{}.Validate());
    EXPECT_NO_THROW((SurfaceErrorOptions{.h_source = 0, .h_target = 0, .degree = kMinMlsDegree}).Validate());
}

}  // namespace
}  // namespace surfel
