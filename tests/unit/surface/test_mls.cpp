#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <limits>
#include <string>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/base/shapes.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/mls.h"

namespace surfel {
namespace {

TEST(Mls, NoisySphereProjectsToItsRadius) {
    ShapeOptions o;
    o.points = 20000;
    o.noise = 0.01;  // 1 % of r
    o.normals = true;
    const PointCloud c = SampleShape(Shape::kSphere, o);
    KdTree tree(c.positions);
    MlsOptions m;
    m.h = 0.1f;  // about 6 spacings: averages enough samples to suppress the noise
    MlsSurface mls(c, tree, m);
    const auto b = mls.ProjectAll(c.positions);
    EXPECT_EQ(b.failed, 0u);
    double sum = 0, worst = 0;
    for (std::size_t i = 0; i < c.size(); ++i) {
        const double r = b.positions[i].cast<double>().norm();
        sum += r;
        worst = std::max(worst, std::abs(r - 1.0));
        ASSERT_GT(b.normals[i].dot(c.positions[i].normalized()), 0.99f);
    }
    EXPECT_NEAR(sum / c.size(), 1.0, 0.002);  // mean radius within 0.2 % of r
    EXPECT_LT(worst, 0.01);                    // and every point closer than the noise level
}

// MedianSpacing from a density computed already equals the one from the tree (the same spacing
// at the same strided points): exactly, for a cloud below the sample limit and one above it.
TEST(Mls, MedianSpacingFromADensityEqualsTheTreesOne) {
    for (std::size_t n : {5000u, 35000u}) {
        ShapeOptions o;
        o.points = n;
        o.noise = 0.002;
        const PointCloud c = SampleShape(Shape::kTorus, o);
        const KdTree tree(c.positions);
        const SamplingDensity density = ComputeSamplingDensity(tree, 6);
        EXPECT_EQ(MedianSpacing(density), MedianSpacing(tree)) << n;
        EXPECT_EQ(MedianSpacing(density, 1000), MedianSpacing(tree, 6, 1000)) << n;
        EXPECT_GT(MedianSpacing(density), 0.0f);
    }
}

// The noise rule (ChooseMlsScale): the noise estimated from the quadratic fits' residuals, and a
// scale that leaves under 0.15 % RMS radial error on a unit sphere with 1 % noise (the spacing
// rule, still the default, leaves 0.30 %). Measured: sigma 0.0095, h = 4 h0 = 0.211, 0.088 %.
TEST(Mls, NoiseRuleChoosesAScaleFromTheResiduals) {
    ShapeOptions o;
    o.points = 20000;
    o.noise = 0.01;
    const PointCloud c = SampleShape(Shape::kSphere, o);
    KdTree tree(c.positions);
    const MlsSurface spacing_rule(c, tree);
    EXPECT_FLOAT_EQ(spacing_rule.h(), 2.0f * MedianSpacing(tree));  // the default is unchanged
    EXPECT_FALSE(spacing_rule.scale_choice());
    MlsOptions m;
    m.scale_rule = MlsScaleRule::kNoise;
    const MlsSurface mls(c, tree, m);
    ASSERT_TRUE(mls.scale_choice());
    const MlsScaleChoice& choice = *mls.scale_choice();
    EXPECT_EQ(mls.h(), choice.h);
    EXPECT_EQ(choice.h0, spacing_rule.h());
    EXPECT_NEAR(choice.noise, 0.01, 0.001);
    EXPECT_GE(choice.scale_factor, 2.0);
    EXPECT_EQ(choice.samples, kMlsNoiseSamples);
    auto rms = [&](const MlsSurface& s) {
        const auto b = s.ProjectAll(c.positions);
        double sum = 0;
        for (const Vec3f& p : b.positions) sum += std::pow(p.cast<double>().norm() - 1.0, 2);
        return std::sqrt(sum / static_cast<double>(c.size()));
    };
    const double noisy = rms(mls), plain = rms(spacing_rule);
    std::printf("noise rule: sigma %.5f, h %.4f (%.2f h0): RMS %.5f; spacing rule %.5f\n", choice.noise, choice.h,
                choice.scale_factor, noisy, plain);
    EXPECT_LE(noisy, 0.0015);
    EXPECT_GT(plain, 0.0025);
    // A given h wins over the rule.
    m.h = 0.05f;
    EXPECT_EQ(MlsSurface(c, tree, m).h(), 0.05f);
    EXPECT_FALSE(MlsSurface(c, tree, m).scale_choice());
}

// Clean samples: nothing to average away, the rule keeps h0, and reports ~no noise.
TEST(Mls, NoiseRuleKeepsTheSpacingScaleOnCleanData) {
    ShapeOptions o;
    o.points = 20000;
    const PointCloud c = SampleShape(Shape::kSphere, o);
    KdTree tree(c.positions);
    for (int degree = kMinMlsDegree; degree <= kMaxMlsDegree; ++degree) {
        const MlsScaleChoice choice = ChooseMlsScale(c, tree, MlsOptions{.degree = degree});
        EXPECT_EQ(choice.h, choice.h0) << degree;
        EXPECT_FLOAT_EQ(choice.h0, 2.0f * MedianSpacing(tree));
        EXPECT_LT(choice.noise, 1e-4) << degree;
    }
}

TEST(Mls, PlaneIsReproducedExactly) {
    ShapeOptions o;
    o.points = 4000;
    const PointCloud c = SampleShape(Shape::kPlane, o);
    KdTree tree(c.positions);
    for (int degree : {0, 1, 2}) {
        MlsOptions m;
        m.degree = degree;
        MlsSurface mls(c, tree, m);
        for (const Vec3f& x : {Vec3f(0.1f, 0.2f, 0.05f), Vec3f(-0.3f, 0.4f, -0.02f), Vec3f(0, 0, 0)}) {
            auto p = mls.Project(x);
            ASSERT_TRUE(p);
            EXPECT_NEAR(p->position.z(), 0.0f, 1e-6f);
            EXPECT_NEAR(p->position.x(), x.x(), 1e-5f);
            EXPECT_NEAR(std::abs(p->normal.z()), 1.0f, 1e-6f);
        }
    }
}

TEST(Mls, QuadraticBeatsPlanarOnACurvedSurface) {
    ShapeOptions o;
    o.points = 5000;
    const PointCloud c = SampleShape(Shape::kSphere, o);
    KdTree tree(c.positions);
    auto error = [&](int degree) {
        MlsOptions m;
        m.degree = degree;
        m.h = 0.15f;
        MlsSurface mls(c, tree, m);
        const auto b = mls.ProjectAll(c.positions);
        double e = 0;
        for (const auto& p : b.positions) e = std::max(e, std::abs(p.cast<double>().norm() - 1.0));
        return e;
    };
    const double e1 = error(1), e2 = error(2);
    EXPECT_LT(e2, 1e-3);
    EXPECT_LT(e2, 0.5 * e1);
}

TEST(Mls, AdaptiveScaleFollowsDensityAndTooFewNeighboursFail) {
    ShapeOptions o;
    o.points = 3000;
    const PointCloud c = SampleShape(Shape::kSphere, o);
    KdTree tree(c.positions);
    MlsOptions m;
    m.adaptive = true;
    MlsSurface mls(c, tree, m);
    auto p = mls.Project(Vec3f(0.0f, 0.0f, 1.02f));
    ASSERT_TRUE(p);
    EXPECT_NEAR(p->position.norm(), 1.0f, 2e-3f);
    EXPECT_FALSE(mls.Project(Vec3f(10, 10, 10)));  // nothing within reach
}

// Validate: each bad field names itself and its range, and the MlsSurface constructor checks first.
TEST(MlsOptions, BadFieldsNameThemselves) {
    const float inf = std::numeric_limits<float>::infinity(), nan = std::numeric_limits<float>::quiet_NaN();
    const std::vector<std::pair<MlsOptions, std::string>> cases = {
        {MlsOptions{.h = -1.0f}, "h: must be finite and at least 0, got -1"},
        {MlsOptions{.h = nan}, "h: must be finite and at least 0, got nan"},
        {MlsOptions{.degree = -1}, "degree: must lie in 0..2, got -1"},
        {MlsOptions{.degree = 3}, "degree: must lie in 0..2, got 3"},
        {MlsOptions{.cutoff = 0.5f}, "cutoff: must lie in 1..10, got 0.5"},
        {MlsOptions{.cutoff = inf}, "cutoff: must lie in 1..10, got inf"},
        {MlsOptions{.max_iterations = 0}, "max_iterations: must lie in 1..1000, got 0"},
        {MlsOptions{.max_iterations = kMaxMlsIterations + 1}, "max_iterations: must lie in 1..1000, got 1001"},
        {MlsOptions{.tolerance = -0.25f}, "tolerance: must lie in 0..1, got -0.25"},
        {MlsOptions{.tolerance = 2.0f}, "tolerance: must lie in 0..1, got 2"},
        {MlsOptions{.min_neighbors = 0}, "min_neighbors: must lie in 1..100000, got 0"},
        {MlsOptions{.scale_rule = static_cast<MlsScaleRule>(5)}, "scale_rule: unknown rule 5"},
    };
    ShapeOptions o;
    o.points = 500;
    const PointCloud c = SampleShape(Shape::kSphere, o);
    KdTree tree(c.positions);
    for (const auto& [options, message] : cases) {
        for (int call = 0; call < 2; ++call) {
            try {
                if (call == 0) options.Validate();
                else MlsSurface(c, tree, options);
                ADD_FAILURE() << message << ": accepted";
            } catch (const Error& e) {
                EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument) << message;
                EXPECT_EQ(e.what(), message);
            }
        }
    }
}

TEST(MlsOptions, DefaultsAndLimitsAreValid) {
    EXPECT_NO_THROW(MlsOptions{}.Validate());
    for (int degree = kMinMlsDegree; degree <= kMaxMlsDegree; ++degree)
        EXPECT_NO_THROW((MlsOptions{.h = 0, .degree = degree, .cutoff = static_cast<float>(kMinMlsCutoff),
                                    .max_iterations = kMinMlsIterations, .tolerance = 0, .min_neighbors = kMinMlsNeighbors})
                            .Validate());
    EXPECT_NO_THROW((MlsOptions{.cutoff = static_cast<float>(kMaxMlsCutoff), .max_iterations = kMaxMlsIterations,
                                .tolerance = static_cast<float>(kMaxMlsTolerance), .min_neighbors = kMaxMlsNeighbors})
                        .Validate());
}

// ProjectAll visits its points in a spatial order and gathers neighbours from a per-thread
// superset of the last gather's ball; a lone Project walks the grid. Every point must get the
// same bits both ways (the same neighbours in the same order), whatever came before it.
TEST(Mls, ProjectAllGivesEachPointsOwnProjectionToTheBit) {
    ShapeOptions o;
    o.points = 6000;
    o.noise = 0.005;
    const PointCloud c = SampleShape(Shape::kTorus, o);
    KdTree tree(c.positions);
    const MlsSurface mls(c, tree);
    // Queries off the samples too, in a scrambled order, with repeats.
    std::vector<Vec3f> queries;
    for (std::size_t i = 0; i < c.size(); i += 3) queries.push_back(c.positions[(i * 7919) % c.size()] * 1.01f);
    queries.push_back(queries.front());
    const auto b = mls.ProjectAll(queries);
    ASSERT_EQ(b.positions.size(), queries.size());
    std::size_t projected = 0;
    for (std::size_t i = queries.size(); i-- > 0;) {  // backwards: a different superset history
        const auto p = mls.Project(queries[i]);
        ASSERT_EQ(p.has_value(), b.normals[i] != Vec3f::Zero()) << i;
        if (!p) continue;
        ++projected;
        ASSERT_EQ(p->position, b.positions[i]) << i;
        ASSERT_EQ(p->normal, b.normals[i]) << i;
    }
    EXPECT_GT(projected, queries.size() * 9 / 10);
}

// ProjectAll over the cloud's own points visits them in the grid's cell order and gathers from
// a per-thread block of 3 x 3 x 3 cells: the same bits as a lone Project (the grid walk), at the
// default support and at small ones (few neighbours, many points near their cell's faces).
TEST(Mls, ProjectAllOverTheCloudsOwnPointsGivesEachPointsOwnProjectionToTheBit) {
    ShapeOptions so;
    so.points = 6000;
    so.noise = 0.005;
    const PointCloud c = SampleShape(Shape::kTorus, so);
    KdTree tree(c.positions);
    for (const auto& [h_scale, cutoff] : {std::pair{1.0f, 3.0f}, std::pair{1.0f, 1.5f}, std::pair{0.5f, 2.0f}}) {
        MlsOptions o;
        o.h = h_scale * 2.0f * MedianSpacing(tree);
        o.cutoff = cutoff;
        const MlsSurface mls(c, tree, o);
        const auto b = mls.ProjectAll(c.positions);
        ASSERT_EQ(b.positions.size(), c.size());
        std::size_t projected = 0;
        for (std::size_t i = 0; i < c.size(); ++i) {
            const auto p = mls.Project(c.positions[i]);
            ASSERT_EQ(p.has_value(), b.normals[i] != Vec3f::Zero()) << i << " cutoff " << cutoff;
            if (!p) {
                ASSERT_EQ(b.positions[i], c.positions[i]) << i;
                continue;
            }
            ++projected;
            ASSERT_EQ(p->position, b.positions[i]) << i << " cutoff " << cutoff;
            ASSERT_EQ(p->normal, b.normals[i]) << i << " cutoff " << cutoff;
        }
        EXPECT_GT(projected, c.size() * 9 / 10) << "cutoff " << cutoff;
    }
}

}  // namespace
}  // namespace surfel
