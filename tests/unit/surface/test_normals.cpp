#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>
#include <string>
#include <vector>

#include "surfel/base/error.h"
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

TEST(Normals, OnePointAtATimeIsBitForBitTheBatch) {
    // EstimateNormalAt (the particle engine's lazy normals) against EstimateNormals unoriented,
    // plain and weighted, on a torus with noise (uneven neighbourhoods) and a tiny cloud.
    ShapeOptions o;
    o.points = 4000;
    o.noise = 0.002;
    for (const std::size_t points : {std::size_t{4000}, std::size_t{9}}) {
        o.points = points;
        const KdTree tree(SampleShape(Shape::kTorus, o).positions);
        for (const bool weighted : {false, true}) {
            NormalOptions no;
            no.orient = false;
            no.weighted = weighted;
            const NormalResult batch = EstimateNormals(tree, no);
            NormalScratch scratch;
            for (std::size_t i = 0; i < tree.size(); ++i) {
                float variation = -1.0f;
                const Vec3f one = EstimateNormalAt(tree, i, no, scratch, &variation);
                ASSERT_EQ(one, batch.normals[i]) << i << (weighted ? " weighted" : " plain");
                ASSERT_EQ(variation, batch.surface_variation[i]) << i;
            }
        }
    }
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

// Every estimated normal of `cloud` points outward of `shape` (placed at `center`, size `scale`).
std::size_t CountInward(const PointCloud& cloud, const std::vector<Vec3f>& normals, Shape shape,
                        const Vec3f& center = Vec3f::Zero(), double scale = 1.0, std::size_t first = 0,
                        std::size_t last = std::numeric_limits<std::size_t>::max()) {
    std::size_t inward = 0;
    for (std::size_t i = first; i < std::min(last, cloud.size()); ++i)
        inward += normals[i].cast<double>().dot(ShapeNormal(shape, (cloud.positions[i] - center).cast<double>(), scale)) <= 0;
    return inward;
}

TEST(Orientation, BoxAllOutward) {
    ShapeOptions o;
    o.points = 12000;
    const PointCloud c = SampleShape(Shape::kBox, o);
    KdTree tree(c.positions);
    const NormalResult r = EstimateNormals(tree);
    EXPECT_EQ(r.components, 1u);
    EXPECT_EQ(CountInward(c, r.normals, Shape::kBox), 0u);
}

TEST(Orientation, CylinderAndTorusAllOutward) {
    for (Shape shape : {Shape::kCylinder, Shape::kTorus}) {
        SCOPED_TRACE(ShapeName(shape));
        ShapeOptions o;
        o.points = 15000;
        const PointCloud c = SampleShape(shape, o);
        KdTree tree(c.positions);
        EXPECT_EQ(CountInward(c, EstimateNormals(tree).normals, shape), 0u);
    }
}

// Five disjoint spheres of different sizes, stacked and side by side (one directly below
// another): five components, each voted outward on its own.
TEST(Orientation, SeveralDisjointSpheresEachOutward) {
    const std::vector<std::pair<Vec3f, double>> spheres = {
        {{0, 0, 0}, 1.0}, {{0, 0, 3}, 0.5}, {{4, 0, 0}, 1.5}, {{0, -4, -1}, 0.3}, {{-3, 2, 1}, 0.8}};
    PointCloud all;
    std::vector<std::size_t> first;
    for (std::size_t s = 0; s < spheres.size(); ++s) {
        ShapeOptions o;
        o.points = 3000;
        o.scale = spheres[s].second;
        o.seed = 10 + s;
        const PointCloud c = SampleShape(Shape::kSphere, o);
        first.push_back(all.size());
        for (const Vec3f& p : c.positions) all.positions.push_back(p + spheres[s].first);
    }
    first.push_back(all.size());
    KdTree tree(all.positions);
    const NormalResult r = EstimateNormals(tree);
    EXPECT_EQ(r.components, spheres.size());
    for (std::size_t s = 0; s < spheres.size(); ++s)
        EXPECT_EQ(CountInward(all, r.normals, Shape::kSphere, spheres[s].first, spheres[s].second, first[s], first[s + 1]),
                  0u)
            << "sphere " << s;
}

// The seed does not trust the normal at the extremal point: exact sphere normals with random
// signs, and the normal at the highest point replaced by one nearly in the tangent plane (what
// the tip of an ear or a noise spike gets), tilted either way. Every other normal ends outward.
TEST(Orientation, AWrongNormalAtTheTopDoesNotDecideTheSign) {
    ShapeOptions o;
    o.points = 8000;
    o.normals = true;
    const PointCloud c = SampleShape(Shape::kSphere, o);
    KdTree tree(c.positions);
    const std::size_t top = static_cast<std::size_t>(
        std::max_element(c.positions.begin(), c.positions.end(), [](const Vec3f& a, const Vec3f& b) { return a.z() < b.z(); }) -
        c.positions.begin());
    for (const Vec3f& wrong : {Vec3f(1, 0, 0.02f), Vec3f(-1, 0, 0.02f), Vec3f(0, 1, -0.02f), Vec3f(0, -1, -0.02f)}) {
        SCOPED_TRACE(::testing::Message() << wrong.transpose());
        std::vector<Vec3f> normals = c.normals;
        std::uint64_t state = 7;
        for (Vec3f& n : normals) {
            state = state * 6364136223846793005ull + 1442695040888963407ull;
            if (state >> 63) n = -n;
        }
        normals[top] = wrong.normalized();
        std::size_t flipped = 0;
        EXPECT_EQ(OrientNormals(tree, normals, {}, &flipped), 1u);
        std::size_t inward = 0;
        for (std::size_t i = 0; i < c.size(); ++i)
            if (i != top) inward += normals[i].dot(c.normals[i]) <= 0;
        EXPECT_EQ(inward, 0u);
        EXPECT_GT(flipped, c.size() / 4);  // about half the random signs were turned
    }
}

// A flat sheet bounds no volume: its votes along d and -d cancel, and CGAL's rule orients it
// (the normal at the highest point, here every point, points up).
TEST(Orientation, FlatSheetPointsUp) {
    ShapeOptions o;
    o.points = 5000;
    const PointCloud c = SampleShape(Shape::kPlane, o);
    KdTree tree(c.positions);
    const NormalResult r = EstimateNormals(tree);
    for (std::size_t i = 0; i < c.size(); ++i) ASSERT_GT(r.normals[i].z(), 0.99f) << i;
}

// Kruskal's trees over the edges sorted in parallel are Prim's wherever the least forest is
// unique, or where its ties cannot change a sign: the same normals and counts from both methods, on
// clouds with one and several components, with random input signs and with either edge cost;
// where ties can change the signs, Prim's runs instead.
TEST(Orientation, KruskalGivesPrimsTrees) {
    struct Case {
        std::string name;
        PointCloud cloud;
        float weight = NormalOptions{}.orient_crossing_weight;
    };
    std::vector<Case> cases;
    for (Shape shape : {Shape::kSphere, Shape::kTorus, Shape::kBox}) {
        ShapeOptions o;
        o.points = 6000;
        o.noise = 0.004;
        cases.push_back({ShapeName(shape), SampleShape(shape, o)});
    }
    cases.push_back({"sphere, Hoppe's cost", cases[0].cloud, 0.0f});
    {
        PointCloud two = cases[0].cloud;  // two components
        for (const Vec3f& p : cases[1].cloud.positions) two.positions.push_back(p + Vec3f(5, 0, 0));
        cases.push_back({"two components", two});
    }
    for (Case& c : cases) {
        SCOPED_TRACE(c.name);
        KdTree tree(c.cloud.positions);
        std::vector<Vec3f> normals = EstimateNormals(tree, {.orient = false}).normals;
        std::uint64_t state = 11;
        for (Vec3f& n : normals) {
            state = state * 6364136223846793005ull + 1442695040888963407ull;
            if (state >> 63) n = -n;
        }
        const NormalOptions opt{.orient_crossing_weight = c.weight};
        std::vector<Vec3f> by_prim = normals, by_auto = normals;
        std::size_t flipped_prim = 0, flipped_auto = 0;
        bool kruskal = false;
        const std::size_t comps_prim =
            detail::OrientNormals(tree, by_prim, opt, detail::SpanningTrees::kPrim, &flipped_prim, &kruskal);
        EXPECT_FALSE(kruskal);
        const std::size_t comps_auto =
            detail::OrientNormals(tree, by_auto, opt, detail::SpanningTrees::kAuto, &flipped_auto, &kruskal);
        EXPECT_TRUE(kruskal);  // noisy estimates: no tie decides a tree
        EXPECT_EQ(comps_auto, comps_prim);
        EXPECT_EQ(flipped_auto, flipped_prim);
        EXPECT_GT(flipped_auto, 0u);
        for (std::size_t i = 0; i < normals.size(); ++i)
            ASSERT_TRUE(by_auto[i].x() == by_prim[i].x() && by_auto[i].y() == by_prim[i].y() &&
                        by_auto[i].z() == by_prim[i].z())
                << i;
    }
    // A regular grid in the plane z = 0 with every normal (0, 0, 1) or its negation: every edge
    // costs exactly 0, so the least spanning trees are many and Prim's tie-break picks one; but
    // every edge that could swap in agrees with the signs (the normals are parallel), so every
    // least tree gives the same normals and Kruskal's stands.
    PointCloud grid;
    for (int y = 0; y < 40; ++y)
        for (int x = 0; x < 40; ++x) grid.positions.emplace_back(0.1f * x, 0.1f * y, 0.0f);
    {
        KdTree tree(grid.positions);
        std::vector<Vec3f> normals(grid.size());
        for (std::size_t i = 0; i < normals.size(); ++i) normals[i] = Vec3f(0, 0, (i * 7919) % 3 == 0 ? -1.0f : 1.0f);
        std::vector<Vec3f> by_prim = normals, by_auto = normals;
        bool kruskal = false;
        detail::OrientNormals(tree, by_prim, {}, detail::SpanningTrees::kPrim);
        detail::OrientNormals(tree, by_auto, {}, detail::SpanningTrees::kAuto, nullptr, &kruskal);
        EXPECT_TRUE(kruskal);
        EXPECT_EQ(by_auto, by_prim);
        for (const Vec3f& n : by_auto) EXPECT_EQ(n.z(), 1.0f);
    }
    // Ties that decide: four points, each the others' neighbour (a complete graph), with the
    // tetrahedron's normals (1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1) / sqrt 3, whose dot
    // products are all exactly -1/3 (Hoppe's cost alone: six edges of one cost). Each triangle
    // has three negative edges, so which edge a tree leaves out changes the signs: Prim's runs.
    {
        const float s = 1.0f / std::sqrt(3.0f);
        PointCloud four;
        four.positions = {{0, 0, 0}, {1, 0, 0}, {0, 1.1f, 0}, {0.2f, 0.3f, 0.9f}};
        std::vector<Vec3f> normals = {{s, s, s}, {s, -s, -s}, {-s, s, -s}, {-s, -s, s}};
        KdTree tree(four.positions);
        const NormalOptions opt{.orient_k = 3, .orient_crossing_weight = 0.0f};
        std::vector<Vec3f> by_prim = normals, by_auto = normals;
        bool kruskal = true;
        detail::OrientNormals(tree, by_prim, opt, detail::SpanningTrees::kPrim);
        detail::OrientNormals(tree, by_auto, opt, detail::SpanningTrees::kAuto, nullptr, &kruskal);
        EXPECT_FALSE(kruskal);
        EXPECT_EQ(by_auto, by_prim);
    }
}

// OrientNormals over a table the caller already has (KnnAll(K), K >= orient_k): the normals,
// flips and components of OrientNormals' own search, bit for bit, whatever K.
TEST(Orientation, GivenTableEqualsOwnSearch) {
    ShapeOptions o;
    o.points = 6000;
    o.noise = 0.004;
    const PointCloud torus = SampleShape(Shape::kTorus, o);
    PointCloud two = torus;  // two components
    for (const Vec3f& p : SampleShape(Shape::kSphere, o).positions) two.positions.push_back(p + Vec3f(6, 0, 0));
    PointCloud grid;  // ties: a lattice, every distance repeated
    for (int y = 0; y < 30; ++y)
        for (int x = 0; x < 30; ++x) grid.positions.emplace_back(0.1f * x, 0.1f * y, 0.0f);
    for (const PointCloud* cloud : std::vector<const PointCloud*>{&torus, &two, &grid}) {
        const KdTree tree(cloud->positions);
        std::vector<Vec3f> normals = EstimateNormals(tree, {.orient = false}).normals;
        std::uint64_t state = 3;
        for (Vec3f& n : normals) {
            state = state * 6364136223846793005ull + 1442695040888963407ull;
            if (state >> 63) n = -n;
        }
        for (const int orient_k : {4, 10}) {
            const NormalOptions opt{.orient_k = orient_k};
            std::vector<Vec3f> want = normals;
            std::size_t want_flipped = 0;
            const std::size_t want_comps = OrientNormals(tree, want, opt, &want_flipped);
            for (const int k : {orient_k, 16, 24}) {
                SCOPED_TRACE(std::to_string(cloud->size()) + " points, orient_k " + std::to_string(orient_k) + ", k " + std::to_string(k));
                const KnnTable knn = tree.KnnAll(k);
                std::vector<Vec3f> got = normals;
                std::size_t flipped = 0;
                EXPECT_EQ(OrientNormals(cloud->positions, knn, got, opt, &flipped), want_comps);
                EXPECT_EQ(flipped, want_flipped);
                EXPECT_EQ(std::memcmp(got.data(), want.data(), got.size() * sizeof(Vec3f)), 0);
            }
        }
    }
    // One point needs no table.
    const std::vector<Vec3f> point = {{0, 0, 0}};
    std::vector<Vec3f> one = {-Vec3f::UnitZ()}, one_tree = one;
    EXPECT_EQ(OrientNormals(point, KnnTable{}, one), OrientNormals(KdTree(point), one_tree));
    EXPECT_EQ(one, one_tree);
}

// A slab thinner than the orientation graph's neighbourhoods: the box squashed to 4 % of its
// height (its faces keep their normals). Edges across the slab join antiparallel normals, the
// cheapest edges under Hoppe's cost alone; the crossing term keeps the tree on the faces.
TEST(Orientation, ThinSlabOutwardWithTheCrossingTerm) {
    ShapeOptions o;
    o.points = 30000;
    const PointCloud box = SampleShape(Shape::kBox, o);
    PointCloud slab = box;
    for (Vec3f& p : slab.positions) p.z() *= 0.04f;
    KdTree tree(slab.positions);
    auto inward = [&](float weight) {
        const NormalResult r = EstimateNormals(tree, {.orient_crossing_weight = weight});
        std::size_t count = 0;
        for (std::size_t i = 0; i < slab.size(); ++i)
            count += r.normals[i].cast<double>().dot(ShapeNormal(Shape::kBox, box.positions[i].cast<double>())) <= 0;
        return count;
    };
    const std::size_t plain = inward(0.0f), crossing = inward(NormalOptions{}.orient_crossing_weight);
    std::printf("thin slab: %zu of %zu normals inward with Hoppe's cost, %zu with the crossing term\n", plain,
                slab.size(), crossing);
    EXPECT_LE(crossing, slab.size() / 1000);
}

// Orientation against the scanned models' meshes: every `<name>_mesh.ply` in the shared data
// with its point cloud `<name>.ply` (the mesh's vertices, in the same order). The reference is
// the mesh's area-weighted vertex normal (the sum of the cross products of the faces around the
// vertex); the mesh's own winding is checked to be outward by its signed volume
// (1/6 sum v0 . (v1 x v2) > 0). Vertices whose face normals cancel (the zero-thickness fins of
// the dragon and buddha decimations) have no reference and are not counted.
struct OrientationAgreement {
    std::size_t compared = 0, outward = 0, components = 0;
    double signed_volume = 0;
    double fraction() const { return compared ? double(outward) / double(compared) : 0.0; }
};

OrientationAgreement AgreementWithMesh(const PointCloud& cloud, const PointCloud& mesh) {
    std::vector<Vec3d> reference(mesh.size(), Vec3d::Zero());
    OrientationAgreement a;
    for (const auto& t : mesh.triangles) {
        const Vec3d p0 = mesh.positions[t[0]].cast<double>(), p1 = mesh.positions[t[1]].cast<double>(),
                    p2 = mesh.positions[t[2]].cast<double>();
        const Vec3d c = (p1 - p0).cross(p2 - p0);  // twice the area times the face normal
        for (auto v : t) reference[v] += c;
        a.signed_volume += p0.dot(p1.cross(p2)) / 6.0;
    }
    KdTree tree(cloud.positions);
    const NormalResult r = EstimateNormals(tree);
    a.components = r.components;
    for (std::size_t i = 0; i < cloud.size(); ++i) {
        const double len = reference[i].norm();
        if (!(len > 0)) continue;
        ++a.compared;
        a.outward += r.normals[i].cast<double>().dot(reference[i]) > 0;
    }
    return a;
}

TEST(Normals, OutwardOnEveryScannedModelWithAMesh) {
    const std::filesystem::path dir = SURFEL_SHARED_DATA_DIR;
    if (!std::filesystem::is_directory(dir)) GTEST_SKIP() << dir << " not present";
    std::vector<std::string> models;
    const std::string suffix = "_mesh.ply";
    for (const auto& entry : std::filesystem::directory_iterator(dir)) {
        const std::string name = entry.path().filename().string();
        if (name.size() > suffix.size() && name.ends_with(suffix))
            models.push_back(name.substr(0, name.size() - suffix.size()));
    }
    std::sort(models.begin(), models.end());
    if (models.empty()) GTEST_SKIP() << "no *_mesh.ply in " << dir;
    for (const std::string& model : models) {
        SCOPED_TRACE(model);
        const PointCloud mesh = ReadPly((dir / (model + suffix)).string());
        const PointCloud cloud = ReadPly((dir / (model + ".ply")).string());
        ASSERT_EQ(cloud.positions, mesh.positions) << "the cloud is the mesh's vertices, in order";
        const OrientationAgreement a = AgreementWithMesh(cloud, mesh);
        std::printf("%-10s %7zu points, %3zu components: %6.2f%% of normals outward (mesh volume %.3g)\n",
                    model.c_str(), a.compared, a.components, 100.0 * a.fraction(), a.signed_volume);
        EXPECT_GT(a.signed_volume, 0.0) << "the reference mesh must be wound outward";
        EXPECT_GT(a.compared, cloud.size() * 9 / 10);
        EXPECT_GE(a.fraction(), 0.99);
    }
}


// Validate: each bad field names itself and its range, and EstimateNormals checks first.
TEST(NormalOptions, BadFieldsNameThemselves) {
    const float inf = std::numeric_limits<float>::infinity(), nan = std::numeric_limits<float>::quiet_NaN();
    const std::vector<std::pair<NormalOptions, std::string>> cases = {
        {NormalOptions{.k = 1}, "k: must lie in 3..1000, got 1"},
        {NormalOptions{.k = kMaxNormalNeighbors + 1}, "k: must lie in 3..1000, got 1001"},
        {NormalOptions{.h = -0.5f}, "h: must be finite and at least 0, got -0.5"},
        {NormalOptions{.h = inf}, "h: must be finite and at least 0, got inf"},
        {NormalOptions{.orient_k = 0}, "orient_k: must lie in 1..1000, got 0"},
        {NormalOptions{.orient_k = 5000}, "orient_k: must lie in 1..1000, got 5000"},
        {NormalOptions{.orient_crossing_weight = -1.0f}, "orient_crossing_weight: must lie in 0..100, got -1"},
        {NormalOptions{.orient_crossing_weight = nan}, "orient_crossing_weight: must lie in 0..100, got nan"},
    };
    ShapeOptions o;
    o.points = 500;
    KdTree tree(SampleShape(Shape::kSphere, o).positions);
    for (const auto& [options, message] : cases) {
        for (int call = 0; call < 2; ++call) {
            try {
                if (call == 0) options.Validate();
                else EstimateNormals(tree, options);
                ADD_FAILURE() << message << ": accepted";
            } catch (const Error& e) {
                EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument) << message;
                EXPECT_EQ(e.what(), message);
            }
        }
    }
}

TEST(NormalOptions, DefaultsAndLimitsAreValid) {
    EXPECT_NO_THROW(NormalOptions{}.Validate());
    EXPECT_NO_THROW((NormalOptions{.k = kMinNormalNeighbors, .h = 0, .orient_k = kMinOrientNeighbors,
                                   .orient_crossing_weight = 0})
                        .Validate());
    EXPECT_NO_THROW((NormalOptions{.k = kMaxNormalNeighbors, .orient_k = kMaxOrientNeighbors,
                                   .orient_crossing_weight = static_cast<float>(kMaxOrientCrossingWeight)})
                        .Validate());
}

}  // namespace
}  // namespace surfel
