#include <gtest/gtest.h>

#include <tbb/global_control.h>
#include <tbb/task_arena.h>

#include <atomic>
#include <cstring>
#include <filesystem>
#include <functional>
#include <limits>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/base/shapes.h"
#include "surfel/io/image.h"
#include "surfel/render/renderer.h"

namespace surfel {
namespace {

PointCloud Sphere() {
    ShapeOptions o;
    o.points = 30000;
    o.normals = true;
    return SampleShape(Shape::kSphere, o);
}

// Sphere() and, behind it, a square wall in the plane z = -2.5 facing it (`scale` wide, with
// `points` samples): what shadow rays from the wall meet.
PointCloud SphereBeforeWall(int points, float scale) {
    PointCloud scene = Sphere();
    ShapeOptions o;
    o.points = points;
    o.normals = true;
    o.scale = scale;
    PointCloud wall = SampleShape(Shape::kPlane, o);
    for (auto& p : wall.positions) p.z() = -2.5f;
    scene.positions.insert(scene.positions.end(), wall.positions.begin(), wall.positions.end());
    scene.normals.insert(scene.normals.end(), wall.normals.begin(), wall.normals.end());
    return scene;
}

// Analytic ray-sphere (unit sphere at the origin): the first t, or nullopt.
std::optional<double> HitSphere(const Vec3d& o, const Vec3d& d) {
    const double b = o.dot(d), c = o.squaredNorm() - 1.0, disc = b * b - c;
    if (disc < 0) return std::nullopt;
    return -b - std::sqrt(disc);
}

// A render of the unit sphere (the camera on the z axis, looking at the origin) against the
// analytic sphere, over the pixels more than one pixel from the silhouette: mask errors, the worst
// depth and the worst normal angle (degrees). `each(x, y, hit)` sees every such pixel.
struct SphereCheck {
    int checked = 0, mask_errors = 0;
    double worst_depth = 0, worst_angle = 0;
};
SphereCheck CheckAgainstUnitSphere(const Image& img, const Camera& camera,
                                   const std::function<void(int, int, bool)>& each = {}) {
    const double distance = camera.eye.norm();
    const double pixel_angle = camera.fovy_deg / camera.height * M_PI / 180;  // one pixel, in radians at the eye
    SphereCheck c;
    for (int y = 0; y < camera.height; ++y)
        for (int x = 0; x < camera.width; ++x) {
            const Vec3d d = camera.Direction(x + 0.5, y + 0.5);
            const auto t = HitSphere(camera.eye, d);
            // Distance of the ray from the silhouette, in pixels (rays within one pixel are exempt).
            const double closest = (camera.eye - camera.eye.dot(d) * d).norm();
            const double silhouette_px =
                std::abs(std::asin(std::min(1.0, closest / distance)) - std::asin(1.0 / distance)) / pixel_angle;
            if (silhouette_px <= 1.0) continue;
            ++c.checked;
            const bool hit = img.At(x, y, 3) > 0.5f;
            if (hit != t.has_value()) ++c.mask_errors;
            if (hit && t) {
                c.worst_depth = std::max(c.worst_depth, std::abs(img.At(x, y, 4) - *t));
                const Vec3d n(img.At(x, y, 5), img.At(x, y, 6), img.At(x, y, 7));
                const Vec3d truth = (camera.eye + *t * d).normalized();
                c.worst_angle = std::max(c.worst_angle, std::acos(std::min(1.0, n.dot(truth))) * 180 / M_PI);
            }
            if (each) each(x, y, hit);
        }
    return c;
}

TEST(Render, SphereHeadOnMatchesAnalyticMaskDepthAndNormals) {
    const PointCloud cloud = Sphere();
    RenderOptions opt;
    opt.camera.eye = {0, 0, 4};
    opt.camera.width = opt.camera.height = 64;
    opt.camera.fovy_deg = 40;
    opt.shadows = false;
    const RenderResult r = Render(cloud, opt);
    const Image& img = r.image;
    const auto [checked, mask_errors, worst_depth, worst_angle] =
        CheckAgainstUnitSphere(img, opt.camera, [&](int x, int y, bool hit) {
            if (!hit) {
                EXPECT_TRUE(std::isinf(img.At(x, y, 4)));
                EXPECT_EQ(img.At(x, y, 3), 0.0f);
            }
        });
    EXPECT_GT(checked, 3000);
    EXPECT_EQ(mask_errors, 0);
    EXPECT_LT(worst_depth, 1e-3);   // within 1e-3 r of the analytic intersection
    EXPECT_LT(worst_angle, 1.0);    // normals within 1 degree
    EXPECT_GT(r.stats.hits, 0u);
    EXPECT_GT(r.stats.surface.cache_hits, 0u);
}

TEST(Render, TiltedPlaneDepth) {
    ShapeOptions o;
    o.points = 20000;
    PointCloud plane = SampleShape(Shape::kPlane, o);
    const Eigen::AngleAxisf tilt(0.5f, Vec3f::UnitX());
    for (auto& p : plane.positions) p = tilt * p;
    const Vec3d n = (tilt * Vec3f::UnitZ()).cast<double>();
    RenderOptions opt;
    opt.camera.eye = {0.1, 0.2, 3};
    opt.camera.width = opt.camera.height = 32;
    opt.camera.fovy_deg = 20;
    opt.shadows = false;
    const RenderResult r = Render(plane, opt);
    int hits = 0;
    for (int y = 4; y < 28; ++y)
        for (int x = 4; x < 28; ++x) {
            const Vec3d d = opt.camera.Direction(x + 0.5, y + 0.5);
            const double t = -opt.camera.eye.dot(n) / d.dot(n);
            ASSERT_GT(r.image.At(x, y, 3), 0.5f) << x << "," << y;
            EXPECT_NEAR(r.image.At(x, y, 4), t, 1e-4);
            ++hits;
        }
    EXPECT_EQ(hits, 24 * 24);
}

TEST(Render, PointBehindTheSphereIsInShadow) {
    const PointCloud scene = SphereBeforeWall(40000, 3);
    RenderOptions opt;
    opt.camera.eye = {0, 0, 6};
    opt.camera.width = opt.camera.height = 48;
    opt.camera.fovy_deg = 50;
    opt.lights = {{Light::Kind::kDirectional, {0, 0, -1}, {1, 1, 1}, 1.0}};  // light from the camera
    opt.ambient = 0.1;
    opt.specular = 0;
    const RenderResult r = Render(scene, opt);
    // The light travels along -z, so wall points (x, y, -2.5) with x^2 + y^2 < 1 lie in the
    // sphere's shadow and all others are lit.
    auto pixel_of = [&](const Vec3d& p) {  // the pixel whose ray passes closest to p
        int best_x = 0, best_y = 0;
        double best = -2;
        const Vec3d want = (p - opt.camera.eye).normalized();
        for (int y = 0; y < 48; ++y)
            for (int x = 0; x < 48; ++x) {
                const double c = opt.camera.Direction(x + 0.5, y + 0.5).dot(want);
                if (c > best) best = c, best_x = x, best_y = y;
            }
        return std::pair{best_x, best_y};
    };
    const Vec3d lit(0.0, 2.2, -2.5);
    const auto [lx, ly] = pixel_of(lit);
    EXPECT_NEAR(r.image.At(lx, ly, 4), (lit - opt.camera.eye).norm(), 0.05);  // it is the wall
    EXPECT_GT(r.image.At(lx, ly, 0), 0.5f);                                    // lit: ambient + Lambert
    // From the camera the shadowed wall is hidden by the sphere; look from above instead.
    opt.camera.eye = {0, 5, 4};
    opt.camera.target = {0, 0, -2.5};
    const RenderResult r2 = Render(scene, opt);
    const auto [hx, hy] = pixel_of({0.0, -0.6, -2.5});
    ASSERT_GT(r2.image.At(hx, hy, 3), 0.5f);
    const double t_wall = (Vec3d(0, -0.6, -2.5) - opt.camera.eye).norm();
    EXPECT_NEAR(r2.image.At(hx, hy, 4), t_wall, 0.1);    // the wall, not the sphere
    EXPECT_NEAR(r2.image.At(hx, hy, 0), 0.1 * 0.8, 1e-4);  // ambient only: in shadow
    EXPECT_GT(r2.stats.shadow_rays, 0u);
}

TEST(Render, ExrRoundTripHasTheChannelsWritten) {
    const PointCloud cloud = Sphere();
    RenderOptions opt;
    opt.camera.width = 24;
    opt.camera.height = 16;
    opt.samples_per_pixel = 4;
    const RenderResult r = Render(cloud, opt);
    const auto path = std::filesystem::temp_directory_path() / ("surfel_render_" + std::to_string(::getpid()) + ".exr");
    WriteImage(r.image, path.string());
    const Image back = ReadImage(path.string());
    std::filesystem::remove(path);
    EXPECT_EQ(back.width, 24);
    EXPECT_EQ(back.height, 16);
    for (const char* c : {"R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z"}) {
        const int i = back.ChannelIndex(c), j = r.image.ChannelIndex(c);
        ASSERT_GE(i, 0) << c;
        for (int y = 0; y < 16; ++y)
            for (int x = 0; x < 24; ++x) {
                const float a = back.At(x, y, i), b = r.image.At(x, y, j);
                if (std::isinf(b)) EXPECT_TRUE(std::isinf(a));
                else EXPECT_EQ(a, b) << c << " " << x << "," << y;
            }
    }
    const std::string png = EncodeImage(r.image, ImageFormat::kPng);
    EXPECT_EQ(png.substr(1, 3), "PNG");
}

TEST(Render, SameImageWhateverTheTileSize) {
    const PointCloud cloud = Sphere();
    RenderOptions opt;
    opt.camera.width = 40;
    opt.camera.height = 30;
    opt.tile = 16;
    const RenderResult a = Render(cloud, opt);
    opt.tile = 7;
    const RenderResult b = Render(cloud, opt);
    EXPECT_EQ(a.image.pixels.size(), b.image.pixels.size());
    for (std::size_t i = 0; i < a.image.pixels.size(); ++i)
        if (!std::isinf(a.image.pixels[i])) ASSERT_EQ(a.image.pixels[i], b.image.pixels[i]) << i;
}

TEST(Render, SameImageWhateverTheThreadCount) {
    // The per-ball cache fills in whatever order the threads reach the balls; every ray must
    // read the same cached values, with shadows and several samples a pixel.
    ShapeOptions o;
    o.points = 8000;
    o.noise = 0.003;
    const PointCloud cloud = SampleShape(Shape::kTorus, o);
    RenderOptions opt;
    opt.camera = Camera::Framing(cloud.Bounds(), 48, 40, Vec3d(0.3, -1.0, 0.8));
    opt.samples_per_pixel = 2;
    opt.tile = 8;
    RenderResult one, many;
    {
        tbb::global_control limit(tbb::global_control::max_allowed_parallelism, 1);
        one = Render(cloud, opt);
    }
    {
        tbb::global_control limit(tbb::global_control::max_allowed_parallelism, 4);
        many = Render(cloud, opt);
    }
    ASSERT_GT(one.stats.hits, 0u);
    EXPECT_EQ(one.stats.hits, many.stats.hits);
    ASSERT_EQ(one.image.pixels.size(), many.image.pixels.size());
    for (std::size_t i = 0; i < one.image.pixels.size(); ++i)
        if (!std::isinf(one.image.pixels[i])) ASSERT_EQ(one.image.pixels[i], many.image.pixels[i]) << i;
}

TEST(Render, RepeatedRendersAreByteIdenticalWithOneTwoAndEightThreads) {
    // The scene where the ray that filled a ball's centre-fit cache once saw other values than
    // the rays that read it (a compiler fold of the float round trip): with several threads, which
    // ray fills a ball is a race, and N.Z of pixel (64, 59) changed by 1 ulp in most renders.
    ShapeOptions o;
    o.points = 20000;
    o.normals = true;
    const PointCloud torus = SampleShape(Shape::kTorus, o);
    RenderOptions opt;
    opt.camera = Camera::Framing(torus.Bounds(), 150, 110, Vec3d(0.3, 1.0, 0.8));
    opt.samples_per_pixel = 2;
    opt.shadows = true;
    opt.lights.push_back({Light::Kind::kDirectional, {-0.3, -1.0, -0.5}, {1, 0.9, 0.8}, 1.0});
    opt.lights.push_back({Light::Kind::kPoint, {0.5, 2.0, 1.5}, {0.5, 0.6, 1.0}, 0.8});
    opt.background = {0.1, 0.2, 0.3};
    // Allow more threads than cores (the race shows most under oversubscription).
    tbb::global_control allow(tbb::global_control::max_allowed_parallelism, 8);
    auto render = [&](int threads) {
        tbb::task_arena arena(threads);
        RenderResult r;
        arena.execute([&] { r = Render(torus, opt); });
        return r;
    };
    const RenderResult reference = render(1);
    ASSERT_GT(reference.stats.hits, 0u);
    const std::vector<float>& want = reference.image.pixels;
    for (int threads : {1, 2, 8})
        for (int run = 0; run < (threads == 1 ? 1 : 3); ++run) {
            const RenderResult r = render(threads);
            const std::vector<float>& got = r.image.pixels;
            ASSERT_EQ(got.size(), want.size());
            std::size_t differ = 0, first = 0;
            for (std::size_t i = 0; i < got.size(); ++i)
                if (std::memcmp(&got[i], &want[i], sizeof(float)) != 0 && differ++ == 0) first = i;
            const std::size_t channels = r.image.channels.size(), pixel = first / channels;
            EXPECT_EQ(differ, 0u) << threads << " threads, run " << run << ": first at pixel ("
                                  << pixel % r.image.width << ", " << pixel / r.image.width
                                  << ") channel " << r.image.channels[first % channels] << ": "
                                  << got[first] << " against " << want[first];
            EXPECT_EQ(r.stats.hits, reference.stats.hits);
            // The work counters too: two threads that computed a ball's centre fit at the same
            // time count one evaluation and one cache hit (they counted two evaluations once).
            EXPECT_EQ(r.stats.shadow_rays, reference.stats.shadow_rays);
            EXPECT_EQ(r.stats.surface.evaluations, reference.stats.surface.evaluations) << threads << " threads";
            EXPECT_EQ(r.stats.surface.cache_hits, reference.stats.surface.cache_hits) << threads << " threads";
            EXPECT_EQ(r.stats.surface.iterations, reference.stats.surface.iterations);
            EXPECT_EQ(r.stats.surface.converged, reference.stats.surface.converged);
        }
}

// ---- Validate(): each bad field -> its exact message ------------------------------------------

struct BadRenderCase {
    const char* name;
    std::function<void(RenderOptions&)> spoil;
    const char* message;
};

Light Directional(const Vec3d& v) { return {Light::Kind::kDirectional, v, {1, 1, 1}, 1.0}; }

TEST(RenderOptions, EachBadFieldIsNamedInTheMessage) {
    const double nan = std::numeric_limits<double>::quiet_NaN(), inf = std::numeric_limits<double>::infinity();
    const std::vector<BadRenderCase> cases = {
        {"width 0", [](RenderOptions& o) { o.camera.width = 0; }, "width: must lie in 1..16384, got 0"},
        {"width big", [](RenderOptions& o) { o.camera.width = kMaxImageSide + 1; },
         "width: must lie in 1..16384, got 16385"},
        {"height", [](RenderOptions& o) { o.camera.height = -3; }, "height: must lie in 1..16384, got -3"},
        {"fovy low", [](RenderOptions& o) { o.camera.fovy_deg = 0.5; }, "camera.fovy_deg: must lie in 1..179, got 0.5"},
        {"fovy high", [](RenderOptions& o) { o.camera.fovy_deg = 180; }, "camera.fovy_deg: must lie in 1..179, got 180"},
        {"fovy nan", [&](RenderOptions& o) { o.camera.fovy_deg = nan; }, "camera.fovy_deg: must lie in 1..179, got nan"},
        {"eye", [&](RenderOptions& o) { o.camera.eye.y() = nan; }, "camera.eye: must be finite"},
        {"target", [&](RenderOptions& o) { o.camera.target.x() = -inf; }, "camera.target: must be finite"},
        {"up finite", [&](RenderOptions& o) { o.camera.up.z() = inf; }, "camera.up: must be finite"},
        {"eye = target", [](RenderOptions& o) { o.camera.target = o.camera.eye; }, "camera: eye and target must differ"},
        {"up zero", [](RenderOptions& o) { o.camera.up = Vec3d::Zero(); },
         "camera.up: must be non-zero and not parallel to the view direction"},
        {"up parallel", [](RenderOptions& o) { o.camera.up = 2.0 * (o.camera.eye - o.camera.target); },
         "camera.up: must be non-zero and not parallel to the view direction"},
        {"spp 0", [](RenderOptions& o) { o.samples_per_pixel = 0; }, "samples_per_pixel: must lie in 1..1024, got 0"},
        {"spp big", [](RenderOptions& o) { o.samples_per_pixel = 1025; },
         "samples_per_pixel: must lie in 1..1024, got 1025"},
        {"lights count", [](RenderOptions& o) { o.lights.assign(kMaxLights + 1, Light{}); }, "lights: at most 64 lights"},
        {"light zero direction", [](RenderOptions& o) { o.lights = {Light{}, Directional(Vec3d::Zero())}; },
         "lights[1].vector: a directional light needs a non-zero direction"},
        {"light vector", [&](RenderOptions& o) { o.lights = {Directional({0, nan, 1})}; },
         "lights[0].vector: must be finite"},
        {"light colour", [&](RenderOptions& o) { o.lights = {Light{}}; o.lights[0].color.x() = inf; },
         "lights[0].color: must be finite"},
        {"light intensity low", [](RenderOptions& o) { o.lights = {Light{}}; o.lights[0].intensity = -1; },
         "lights[0].intensity: must lie in 0..1e+06, got -1"},
        {"light intensity high", [](RenderOptions& o) { o.lights = {Light{}}; o.lights[0].intensity = 2e6; },
         "lights[0].intensity: must lie in 0..1e+06, got 2e+06"},
        {"background", [&](RenderOptions& o) { o.background.z() = nan; }, "background: must be finite"},
        {"albedo", [&](RenderOptions& o) { o.albedo.x() = inf; }, "albedo: must be finite"},
        {"ambient", [](RenderOptions& o) { o.ambient = -0.1; }, "ambient: must be finite and at least 0, got -0.1"},
        {"specular", [&](RenderOptions& o) { o.specular = nan; }, "specular: must be finite and at least 0, got nan"},
        {"shininess", [](RenderOptions& o) { o.shininess = -2; }, "shininess: must be finite and at least 0, got -2"},
        {"h", [](RenderOptions& o) { o.surface.h = -1; }, "h: must be finite and at least 0, got -1"},
        {"precision", [](RenderOptions& o) { o.surface.precision = std::numeric_limits<float>::infinity(); },
         "precision: must be finite and at least 0, got inf"},
        {"relative_precision 0", [](RenderOptions& o) { o.surface.relative_precision = 0; },
         "relative_precision: must be > 0, got 0"},
        {"relative_precision 2", [](RenderOptions& o) { o.surface.relative_precision = 2; },
         "relative_precision: must lie in 0..1, got 2"},
        {"degree", [](RenderOptions& o) { o.surface.degree = 3; }, "degree: must lie in 0..2, got 3"},
        {"max_iterations 0", [](RenderOptions& o) { o.surface.max_iterations = 0; },
         "max_iterations: must lie in 1..1000, got 0"},
        {"max_iterations big", [](RenderOptions& o) { o.surface.max_iterations = kMaxSurfaceIterations + 1; },
         "max_iterations: must lie in 1..1000, got 1001"},
        {"tile", [](RenderOptions& o) { o.tile = 0; }, "tile: must lie in 1..16384, got 0"},
    };
    for (const BadRenderCase& c : cases) {
        RenderOptions opt;
        c.spoil(opt);
        try {
            opt.Validate();
            ADD_FAILURE() << c.name << ": accepted";
        } catch (const Error& e) {
            EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument) << c.name;
            EXPECT_STREQ(e.what(), c.message) << c.name;
        }
    }
}

TEST(RenderOptions, DefaultsAndLimitsAreValid) {
    EXPECT_NO_THROW(RenderOptions{}.Validate());
    RenderOptions opt;  // every limit itself is allowed
    opt.camera.width = opt.camera.height = kMaxImageSide;
    opt.camera.fovy_deg = kMaxFovyDeg;
    opt.samples_per_pixel = kMaxSamplesPerPixel;
    opt.lights.assign(kMaxLights, Light{});
    opt.lights[0] = {Light::Kind::kPoint, Vec3d::Zero(), {1, 1, 1}, kMaxLightIntensity};  // a point light may sit at 0
    opt.lights[1].intensity = 0;
    opt.surface.max_iterations = kMaxSurfaceIterations;
    EXPECT_NO_THROW(opt.Validate());
    opt.camera.fovy_deg = kMinFovyDeg;
    EXPECT_NO_THROW(opt.Validate());
}

TEST(Render, ValidatesTheOptionsFirst) {
    // An empty cloud would fail in the surface; the options are checked before it is built.
    RenderOptions opt;
    opt.camera.width = 0;
    try {
        Render(PointCloud{}, opt);
        ADD_FAILURE() << "accepted";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
        EXPECT_STREQ(e.what(), "width: must lie in 1..16384, got 0");
    }
}

// ---- Exceptions inside Embree's callbacks and the hit-filter seam ----------------------------

// Render(), expecting the Error that the hit filter throws from inside the callbacks.
void ExpectFilterErrorReachesTheCaller(const PointCloud& cloud, RenderOptions opt) {
    std::atomic<int> calls{0};
    opt.hit_filter = [&](const AaHit&) -> bool {
        ++calls;
        throw Error(ErrorCode::kResourceExhausted, "other surface: out of budget");
    };
    try {
        Render(cloud, opt);
        ADD_FAILURE() << "the render did not throw";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kResourceExhausted);
        EXPECT_STREQ(e.what(), "other surface: out of budget");
    }
    EXPECT_GT(calls.load(), 0);
}

TEST(Render, ErrorInsideTheIntersectCallbackReachesTheCaller) {
    RenderOptions opt;
    opt.camera.width = opt.camera.height = 16;
    opt.shadows = false;
    ExpectFilterErrorReachesTheCaller(Sphere(), opt);
}

TEST(Render, ErrorInsideTheOccludedCallbackReachesTheCaller) {
    // The camera sits between the sphere and the wall behind it and sees only the wall; only the
    // shadow rays from the wall meet the sphere, in the occluded callback.
    const PointCloud scene = SphereBeforeWall(20000, 2);
    RenderOptions opt;
    opt.camera.eye = {0, 0, -1.2};
    opt.camera.target = {0, 0, -2.5};
    opt.camera.width = opt.camera.height = 12;
    opt.camera.fovy_deg = 30;
    opt.lights = {Directional({0, 0, -1})};  // shadow rays from the wall go +z into the sphere
    // The primary rays' hits on the wall pass; a hit anywhere else throws.
    std::atomic<int> shadow_calls{0};
    opt.hit_filter = [&](const AaHit& hit) -> bool {
        if (std::abs(hit.position.z() + 2.5) < 0.1) return true;
        ++shadow_calls;
        throw Error(ErrorCode::kResourceExhausted, "other surface: out of budget");
    };
    try {
        Render(scene, opt);
        ADD_FAILURE() << "the render did not throw";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kResourceExhausted);
        EXPECT_STREQ(e.what(), "other surface: out of budget");
    }
    EXPECT_GT(shadow_calls.load(), 0);
    // Without shadows no ray meets the sphere: the same filter lets the render through.
    opt.shadows = false;
    shadow_calls = 0;
    const RenderResult r = Render(scene, opt);
    EXPECT_EQ(shadow_calls.load(), 0);
    EXPECT_EQ(r.stats.hits, 144u);
}

TEST(Render, HitFilterRejectsTheNearSheet) {
    // The seam a CSG render plugs into: reject every hit on the camera's half (z > 0) of the unit
    // sphere, and the rays go on to the far side, at the analytic far root.
    const PointCloud cloud = Sphere();
    RenderOptions opt;
    opt.camera.eye = {0, 0, 4};
    opt.camera.width = opt.camera.height = 48;
    opt.shadows = false;
    opt.hit_filter = [](const AaHit& hit) { return hit.position.z() <= 0; };
    const RenderResult r = Render(cloud, opt);
    const double pixel_angle = 40.0 / 48 * M_PI / 180;
    int checked = 0, misses = 0;
    double worst_depth = 0;
    for (int y = 0; y < 48; ++y)
        for (int x = 0; x < 48; ++x) {
            const Vec3d d = opt.camera.Direction(x + 0.5, y + 0.5);
            const double b = opt.camera.eye.dot(d), disc = b * b - (opt.camera.eye.squaredNorm() - 1.0);
            const double closest = (opt.camera.eye - b * d).norm();
            const double silhouette_px = std::abs(std::asin(std::min(1.0, closest / 4.0)) - std::asin(0.25)) / pixel_angle;
            if (silhouette_px <= 1.0) continue;
            if (disc < 0) {
                EXPECT_EQ(r.image.At(x, y, 3), 0.0f) << x << "," << y;
                continue;
            }
            const double t_far = -b + std::sqrt(disc);
            if ((opt.camera.eye + t_far * d).z() > -0.1) continue;  // near the filter's edge
            ++checked;
            if (r.image.At(x, y, 3) < 0.5f) {
                ++misses;
                continue;
            }
            worst_depth = std::max(worst_depth, std::abs(r.image.At(x, y, 4) - t_far));
            EXPECT_LT(r.image.At(x, y, 7), 0.0f) << x << "," << y;  // the far side's normal faces -z
        }
    EXPECT_GT(checked, 700);
    EXPECT_EQ(misses, 0);
    EXPECT_LT(worst_depth, 1e-3);
}

// ---- RenderQuality ---------------------------------------------------------------------------

TEST(RenderQuality, FullIsTheDefaultsAndPreviewIsThePapersSurfaceWithItsThreeChanges) {
    const RenderOptions defaults;
    RenderOptions full;
    full.surface.normal_sigma = 0.25f;  // a setting kFull puts back
    full.shadow_second_stage = false;
    full.surface.h = 0.5f;              // and one it does not choose
    ApplyRenderQuality(RenderQuality::kFull, &full);
    EXPECT_EQ(full.surface.normal_sigma, defaults.surface.normal_sigma);
    EXPECT_EQ(full.surface.bandwidth, defaults.surface.bandwidth);
    EXPECT_EQ(full.surface.relative_precision, kPaperRelativePrecision);
    EXPECT_TRUE(full.shadow_second_stage);
    EXPECT_EQ(full.surface.h, 0.5f);
    RenderOptions preview;
    ApplyRenderQuality(RenderQuality::kPreview, &preview);
    EXPECT_EQ(preview.surface.normal_sigma, 0.0f);
    EXPECT_EQ(preview.surface.bandwidth, AaBandwidth::kFixed);
    EXPECT_EQ(preview.surface.relative_precision, kPreviewRelativePrecision);
    EXPECT_FALSE(preview.shadow_second_stage);
    EXPECT_EQ(preview.surface.degree, defaults.surface.degree);
    EXPECT_EQ(preview.surface.cutoff, defaults.surface.cutoff);
    EXPECT_NO_THROW(preview.Validate());
    try {
        ApplyRenderQuality(static_cast<RenderQuality>(9), &preview);
        ADD_FAILURE() << "accepted";
    } catch (const Error& e) {
        EXPECT_STREQ(e.what(), "quality: unknown quality 9");
    }
}

TEST(RenderQuality, PreviewHitsTheSampledSphereWithinItsPrecisionAndItsNormalsWithinTwoDegrees) {
    // The unit sphere of SphereHeadOnMatchesAnalyticMaskDepthAndNormals at preview quality (with
    // a light and shadows): the same mask off the silhouette, every hit within 0.03 h (the
    // acceptance's scale; it bounds the last fit's offset, not this distance, but on a sphere the
    // iteration stops well within it) + 1e-3 (the full render's bound against the analytic
    // sphere) of it, its normals within 2 degrees. (A sphere is a quadric: the degree-2 fits converge at once at
    // either precision, so the iteration counts do not differ here; the bunny's do.)
    const PointCloud cloud = Sphere();
    RenderOptions opt;
    opt.camera.eye = {0, 0, 4};
    opt.camera.width = opt.camera.height = 64;
    opt.camera.fovy_deg = 40;
    opt.lights = {{Light::Kind::kDirectional, {-0.4, -0.5, -1}, {1, 1, 1}, 1.0}};
    ApplyRenderQuality(RenderQuality::kPreview, &opt);
    const RenderResult r = Render(cloud, opt);
    const double h = r.stats.h;
    EXPECT_FLOAT_EQ(r.stats.precision, kPreviewRelativePrecision * h);
    const auto [checked, mask_errors, worst_depth, worst_angle] = CheckAgainstUnitSphere(r.image, opt.camera);
    EXPECT_GT(checked, 3000);
    EXPECT_EQ(mask_errors, 0);
    EXPECT_LT(worst_depth, kPreviewRelativePrecision * h + 1e-3);
    EXPECT_LT(worst_angle, 2.0);
    EXPECT_GT(r.stats.shadow_rays, 0u);
}

TEST(RenderQuality, PreviewsFirstStageShadowRaysStillFindTheSphereBeforeTheWall) {
    // The wall behind the sphere of PointBehindTheSphereIsInShadow, seen from above, with shadow
    // rays in the first stage alone: the point in the sphere's shadow stays dark, a lit one lit.
    const PointCloud scene = SphereBeforeWall(40000, 3);
    RenderOptions opt;
    opt.camera.eye = {0, 5, 4};
    opt.camera.target = {0, 0, -2.5};
    opt.camera.width = opt.camera.height = 48;
    opt.camera.fovy_deg = 50;
    opt.lights = {{Light::Kind::kDirectional, {0, 0, -1}, {1, 1, 1}, 1.0}};
    opt.specular = 0;
    ApplyRenderQuality(RenderQuality::kPreview, &opt);
    ASSERT_FALSE(opt.shadow_second_stage);
    const RenderResult r = Render(scene, opt);
    auto pixel_of = [&](const Vec3d& p) {
        int best_x = 0, best_y = 0;
        double best = -2;
        const Vec3d want = (p - opt.camera.eye).normalized();
        for (int y = 0; y < 48; ++y)
            for (int x = 0; x < 48; ++x) {
                const double c = opt.camera.Direction(x + 0.5, y + 0.5).dot(want);
                if (c > best) best = c, best_x = x, best_y = y;
            }
        return std::pair{best_x, best_y};
    };
    const auto [hx, hy] = pixel_of({0.0, -0.6, -2.5});
    ASSERT_GT(r.image.At(hx, hy, 3), 0.5f);
    EXPECT_NEAR(r.image.At(hx, hy, 4), (Vec3d(0, -0.6, -2.5) - opt.camera.eye).norm(), 0.1);
    EXPECT_NEAR(r.image.At(hx, hy, 0), 0.1 * 0.8, 1e-4);  // ambient only: in shadow
    const Vec3d lit(1.6, 0.0, -2.5);  // outside the shadow (x^2 + y^2 > 1), in view past the sphere
    const auto [lx, ly] = pixel_of(lit);
    EXPECT_NEAR(r.image.At(lx, ly, 4), (lit - opt.camera.eye).norm(), 0.1);  // the wall
    EXPECT_GT(r.image.At(lx, ly, 0), 0.5f);                                  // lit: ambient + Lambert
    // The shadow's area in the image matches the two-stage render's to a few outline pixels.
    opt.shadow_second_stage = true;
    const RenderResult both = Render(scene, opt);
    int dark_first = 0, dark_both = 0, differ = 0;
    for (int y = 0; y < 48; ++y)
        for (int x = 0; x < 48; ++x) {
            const bool a = r.image.At(x, y, 3) > 0.5f && r.image.At(x, y, 0) < 0.1f;
            const bool b = both.image.At(x, y, 3) > 0.5f && both.image.At(x, y, 0) < 0.1f;
            dark_first += a, dark_both += b, differ += a != b;
        }
    EXPECT_GT(dark_both, 50);
    EXPECT_LE(differ, dark_both / 20 + 2) << dark_first << " against " << dark_both;
}

}  // namespace
}  // namespace surfel
