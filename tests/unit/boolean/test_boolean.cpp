// Boolean operations against exact CSG of analytic solids (issue 14, item 9): sphere with a box
// whose face cuts it in a circle, and two spheres (the curve is an exact circle), for the four
// operations of Table 3.1; bad input; disjoint and empty results.

#include <gtest/gtest.h>
#include <tbb/global_control.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <functional>
#include <memory>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/base/shapes.h"
#include "surfel/boolean/boolean.h"
#include "../even_solids.h"
#include "surfel/io/cloud_io.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/surface/local_analysis.h"

namespace surfel {
namespace {

constexpr double kPi = 3.14159265358979323846;

// An analytic solid: a shape of shapes.h placed by world = s R x + t.
struct Solid {
    Shape shape;
    double scale = 1.0;  // the shape's own size parameter
    Similarity place;

    Vec3d ToLocal(const Vec3d& x) const {
        return place.rotation.transpose() * (x - place.translation) / place.scale;
    }
    // Signed distance (negative inside); exact for spheres and boxes.
    double Sd(const Vec3d& x) const {
        const Vec3d p = ToLocal(x);
        double d = ShapeDistance(shape, p, scale);
        bool inside = false;
        switch (shape) {
            case Shape::kSphere:
                inside = p.norm() < scale;
                break;
            case Shape::kBox:
                inside = p.cwiseAbs().maxCoeff() < scale;
                break;
            case Shape::kCylinder:
                inside = std::hypot(p.x(), p.y()) < scale && std::abs(p.z()) < scale;
                break;
            case Shape::kTorus: {
                const double r = kTorusMinorRatio * scale, rho = std::hypot(p.x(), p.y()) - scale;
                inside = rho * rho + p.z() * p.z() < r * r;
                break;
            }
            default:
                ADD_FAILURE() << "no inside test for this shape";
        }
        return place.scale * (inside ? -d : d);
    }
    Vec3d Normal(const Vec3d& x) const {
        return place.rotation * ShapeNormal(shape, ToLocal(x), scale);
    }
};

// The exact intersection curve: a circle (centre, unit axis, radius).
struct Circle {
    Vec3d c, axis;
    double r;
    double Distance(const Vec3d& x) const {
        const Vec3d d = x - c;
        const double h = d.dot(axis);
        const double rho = (d - h * axis).norm();
        return std::hypot(h, rho - r);
    }
    Vec3d At(double phi) const {
        const Vec3d u = axis.unitOrthogonal(), v = axis.cross(u);
        return c + r * (std::cos(phi) * u + std::sin(phi) * v);
    }
};

// The exact curve as the tests use it: a distance and points along it (4000 on a circle).
struct Curve {
    std::function<double(const Vec3d&)> distance;
    std::vector<Vec3d> points;

    Curve(const Circle& c)
        : distance([c](const Vec3d& x) { return c.Distance(x); }) {  // NOLINT: implicit
        for (int i = 0; i < 4000; ++i) points.push_back(c.At(2 * kPi * i / 4000));
    }
    // A polyline through dense points (closer than 1e-4 apart): the distance to the nearest one.
    explicit Curve(std::vector<Vec3d> pts) : points(std::move(pts)) {
        std::vector<Vec3f> f;
        for (const Vec3d& p : points) f.push_back(p.cast<float>());
        auto tree = std::make_shared<KdTree>(f);
        distance = [tree](const Vec3d& x) {
            return std::sqrt(double{tree->Nearest(x.cast<float>()).dist2});
        };
    }
    double Distance(const Vec3d& x) const { return distance(x); }
};

bool InsideWanted(BooleanOp op, bool of_a) {
    switch (op) {
        case BooleanOp::kUnion:
            return false;
        case BooleanOp::kIntersection:
            return true;
        case BooleanOp::kDifference:
            return !of_a;
        case BooleanOp::kReverseDifference:
            return of_a;
    }
    return false;
}
bool Flipped(BooleanOp op, bool of_a) {
    return (op == BooleanOp::kDifference && !of_a) || (op == BooleanOp::kReverseDifference && of_a);
}

PointCloud Sample(Shape shape, std::size_t n, double scale, std::uint64_t seed,
                  bool normals = true) {
    ShapeOptions o;
    o.points = n;
    o.scale = scale;
    o.normals = normals;
    o.seed = seed;
    return SampleShape(shape, o);
}

// Evenly sampled inputs, so that "no holes within 2 spacings" measures the boolean, not the
// gaps of a random sampling (uniformly random samples leave empty disks of 2.5 spacings).
using test::EvenBox;
using test::EvenSphere;

// The cylinder of radius `scale`, z in [-scale, scale]: rings about `spacing` apart on the side
// and concentric rings on the caps, exact outward normals.
PointCloud EvenCylinder(double scale, double spacing) {
    PointCloud c;
    const int around = static_cast<int>(std::lround(2 * kPi * scale / spacing));
    const int rings = static_cast<int>(std::lround(2 * scale / spacing));
    for (int k = 0; k < rings; ++k)
        for (int i = 0; i < around; ++i) {
            const double phi = 2 * kPi * (i + 0.5 * (k % 2)) / around,
                         z = scale * (2.0 * (k + 0.5) / rings - 1.0);
            c.positions.push_back(
                Vec3d(scale * std::cos(phi), scale * std::sin(phi), z).cast<float>());
            c.normals.push_back(Vec3d(std::cos(phi), std::sin(phi), 0).cast<float>());
        }
    const int radial = static_cast<int>(std::lround(scale / spacing));
    for (int sign = -1; sign <= 1; sign += 2)
        for (int k = 0; k < radial; ++k) {
            const double r = scale * (k + 0.5) / radial;
            const int m = std::max(1, static_cast<int>(std::lround(2 * kPi * r / spacing)));
            for (int i = 0; i < m; ++i) {
                const double phi = 2 * kPi * (i + 0.5 * (k % 2)) / m;
                c.positions.push_back(
                    Vec3d(r * std::cos(phi), r * std::sin(phi), sign * scale).cast<float>());
                c.normals.push_back(Vec3f(0, 0, static_cast<float>(sign)));
            }
        }
    return c;
}

// The torus of major radius 1 and minor radius kTorusMinorRatio: rings of the tube about
// `spacing` apart, each with points about `spacing` apart, exact outward normals.
PointCloud EvenTorus(double spacing) {
    PointCloud c;
    const double R = 1.0, r = kTorusMinorRatio;
    const int rings = static_cast<int>(std::lround(2 * kPi * r / spacing));
    for (int k = 0; k < rings; ++k) {
        const double v = 2 * kPi * (k + 0.5) / rings;
        const int m = static_cast<int>(std::lround(2 * kPi * (R + r * std::cos(v)) / spacing));
        for (int i = 0; i < m; ++i) {
            const double u = 2 * kPi * (i + 0.5 * (k % 2)) / m;
            const Vec3d n(std::cos(v) * std::cos(u), std::cos(v) * std::sin(u), std::sin(v));
            c.positions.push_back(
                (Vec3d(R * std::cos(u), R * std::sin(u), 0) + r * n).cast<float>());
            c.normals.push_back(n.cast<float>());
        }
    }
    return c;
}

// Sampled points of the exact boundary of the result: both surfaces where Table 3.1 keeps them,
// plus the curve.
std::vector<Vec3d> ExactBoundary(const Solid& sa, const Solid& sb, const Curve& curve,
                                 BooleanOp op) {
    std::vector<Vec3d> out;
    const PointCloud ta = Sample(sa.shape, 60000, sa.scale, 99),
                     tb = Sample(sb.shape, 60000, sb.scale, 98);
    for (const Vec3f& p : ta.positions) {
        const Vec3d x =
            sa.place.scale * (sa.place.rotation * p.cast<double>()) + sa.place.translation;
        if ((sb.Sd(x) < 0) == InsideWanted(op, true)) out.push_back(x);
    }
    for (const Vec3f& p : tb.positions) {
        const Vec3d x =
            sb.place.scale * (sb.place.rotation * p.cast<double>()) + sb.place.translation;
        if ((sa.Sd(x) < 0) == InsideWanted(op, false)) out.push_back(x);
    }
    out.insert(out.end(), curve.points.begin(), curve.points.end());
    return out;
}

struct Measures {
    double max_boundary = 0;  // non-curve samples: distance to the exact boundary
    double max_curve = 0;     // curve samples: distance to the exact curve
    std::size_t wrong_side = 0;
    std::size_t wrong_normal = 0;
    double worst_hole =
        0;  // max over the exact boundary of (distance to the output) / local spacing
    double worst_at_curve = 0;  // where: its distance to the curve, in local spacings
    double diag = 0;
};

Measures Measure(const BooleanResult& r, const Solid& sa, const Solid& sb, const Curve& curve,
                 BooleanOp op) {
    Measures m;
    const PointCloud& c = r.cloud;
    const ExtraAttribute* src = c.FindExtra(kSourceAttribute);
    const ExtraAttribute *cx = c.FindExtra(kCreaseNormalX), *cy = c.FindExtra(kCreaseNormalY),
                         *cz = c.FindExtra(kCreaseNormalZ);
    EXPECT_TRUE(src && cx && cy && cz);
    if (!(src && cx && cy && cz)) return m;
    BoundingBox box = c.Bounds();
    m.diag = box.Diagonal();
    const double tol = 1e-3 * m.diag;
    for (std::size_t i = 0; i < c.size(); ++i) {
        const Vec3d p = c.positions[i].cast<double>(), n = c.normals[i].cast<double>();
        const int s = static_cast<int>(src->values[i]);
        if (s == 2) {
            m.max_curve = std::max(m.max_curve, curve.Distance(p));
            const Vec3d n2(cx->values[i], cy->values[i], cz->values[i]);
            const Vec3d ea = sa.Normal(p) * (Flipped(op, true) ? -1.0 : 1.0);
            const Vec3d eb = sb.Normal(p) * (Flipped(op, false) ? -1.0 : 1.0);
            m.wrong_normal += n.dot(ea) < 0.9 || n2.dot(eb) < 0.9;
            continue;
        }
        const bool of_a = s == 0;
        const Solid& own = of_a ? sa : sb;
        const Solid& other = of_a ? sb : sa;
        const double sd_other = other.Sd(p);
        // On the wrong side: beyond the tolerance on the side of the other solid Table 3.1 drops.
        if (InsideWanted(op, of_a) ? sd_other > tol : sd_other < -tol) ++m.wrong_side;
        const bool kept_region = (sd_other < 0) == InsideWanted(op, of_a);
        const double d = std::min(kept_region ? std::abs(own.Sd(p)) : 1e30, curve.Distance(p));
        m.max_boundary = std::max(m.max_boundary, d);
        const Vec3d e = own.Normal(p) * (Flipped(op, of_a) ? -1.0 : 1.0);
        m.wrong_normal += n.dot(e) <= 0;
    }
    // No holes: every exact boundary point within 2 local spacings (eta of the nearest output
    // sample, notes 1.1.1) of an output sample.
    if (c.size() >= 8) {
        const KdTree tree(c.positions);
        const SamplingDensity dens = ComputeSamplingDensity(tree, 6);
        for (const Vec3d& x : ExactBoundary(sa, sb, curve, op)) {
            const Neighbor nb = tree.Nearest(x.cast<float>());
            const double ratio = std::sqrt(double{nb.dist2}) / dens.spacing[nb.index];
            if (ratio > m.worst_hole) m.worst_at_curve = curve.Distance(x) / dens.spacing[nb.index];
            m.worst_hole = std::max(m.worst_hole, ratio);
        }
    }
    return m;
}

void ExpectExact(const BooleanResult& r, const Solid& sa, const Solid& sb, const Curve& curve,
                 BooleanOp op) {
    const Measures m = Measure(r, sa, sb, curve, op);
    const BooleanReport& rep = r.report;
    const double tol = 1e-3 * m.diag;
    std::printf(
        "  %-18s kept a %zu b %zu curve %zu (seeds %zu, refined %zu, failures %zu), newton %.2f, "
        "saved %.1f %%, "
        "boundary %.2e, curve %.2e (tol %.2e), holes %.2f spacings (%.1f from the curve), wrong "
        "side %zu, wrong normals %zu, %.0f ms\n",
        rep.op.c_str(), rep.kept_a, rep.kept_b, rep.curve_samples, rep.curve_seeds,
        rep.curve_refined, rep.newton_failures, rep.mean_newton_iterations,
        100 * rep.queries_saved_share, m.max_boundary, m.max_curve, tol, m.worst_hole,
        m.worst_at_curve, m.wrong_side, m.wrong_normal, rep.time_ms);
    EXPECT_LE(m.max_boundary, tol) << rep.op;
    EXPECT_LE(m.max_curve, tol) << rep.op;
    EXPECT_EQ(m.wrong_side, 0u) << rep.op;
    EXPECT_EQ(m.wrong_normal, 0u) << rep.op;
    EXPECT_LE(m.worst_hole, 2.0) << rep.op;
    EXPECT_GT(rep.curve_samples, 0u) << rep.op;
    EXPECT_LT(rep.mean_newton_iterations, 4.0) << rep.op;
    EXPECT_EQ(rep.kept_a + rep.added_a + rep.kept_b + rep.added_b + rep.curve_samples,
              r.cloud.size());
}

// Sphere (radius 1 at the origin) and a box of half-size 0.8 centred at (1.6, 0, 0): the face
// x = 0.8 cuts the sphere in the circle of radius 0.6 around the x axis, 0.2 inside the face.
class SphereBox : public ::testing::TestWithParam<BooleanOp> {};

TEST_P(SphereBox, MatchesExactCsg) {
    const PointCloud a = EvenSphere(20000, 1.0), b = EvenBox(64, 0.8);
    BooleanOptions opt;
    opt.transform.translation = Vec3d(1.6, 0, 0);
    const Solid sa{Shape::kSphere, 1.0, {}}, sb{Shape::kBox, 0.8, opt.transform};
    const Circle curve{Vec3d(0.8, 0, 0), Vec3d(1, 0, 0), 0.6};
    const BooleanResult r = Boolean(a, b, GetParam(), opt);
    ExpectExact(r, sa, sb, curve, GetParam());
}

// Two spheres, B placed by a rotation, a scale of 0.8 and a shift: the curve is the circle
// where |x| = 1 meets |x - t| = 0.8.
class TwoSpheres : public ::testing::TestWithParam<BooleanOp> {};

TEST_P(TwoSpheres, MatchesExactCsg) {
    const PointCloud a = EvenSphere(20000, 1.0), b = EvenSphere(20000, 1.0);
    BooleanOptions opt;
    opt.transform.rotation = Eigen::AngleAxisd(0.7, Vec3d(1, 2, 3).normalized()).toRotationMatrix();
    opt.transform.translation = Vec3d(1.1, 0.4, -0.3);
    opt.transform.scale = 0.8;
    const Solid sa{Shape::kSphere, 1.0, {}}, sb{Shape::kSphere, 1.0, opt.transform};
    const Vec3d t = opt.transform.translation;
    const double d = t.norm(), along = (d * d + 1.0 - 0.64) / (2 * d);
    const Circle curve{along * t / d, t / d, std::sqrt(1.0 - along * along)};
    const BooleanResult r = Boolean(a, b, GetParam(), opt);
    ExpectExact(r, sa, sb, curve, GetParam());
}

// Sphere − tilted cylinder (and the other three): a cylinder of radius 0.5, height 1, its axis
// tilted by 0.5 rad and its centre 0.9 from the sphere's: its side meets the unit sphere in the
// circle of radius 0.5 at 0.866 along the axis; its inner cap lies inside the sphere.
class SphereCylinder : public ::testing::TestWithParam<BooleanOp> {};

TEST_P(SphereCylinder, MatchesExactCsg) {
    const PointCloud a = EvenSphere(20000, 1.0), b = EvenCylinder(0.5, 0.025);
    BooleanOptions opt;
    opt.transform.rotation = Eigen::AngleAxisd(0.5, Vec3d(1, 1, 0).normalized()).toRotationMatrix();
    const Vec3d axis = opt.transform.rotation * Vec3d::UnitZ();
    opt.transform.translation = 0.9 * axis;
    const Solid sa{Shape::kSphere, 1.0, {}}, sb{Shape::kCylinder, 0.5, opt.transform};
    const Circle curve{std::sqrt(0.75) * axis, axis, 0.5};
    const BooleanResult r = Boolean(a, b, GetParam(), opt);
    ExpectExact(r, sa, sb, curve, GetParam());
}

// Torus ∪ tilted cylinder (and the other three): a cylinder of radius and half-height 0.25, its
// bottom cap's centre on the tube's core circle, tilted by 0.2 rad; its side cuts the tube
// (radius 0.35) in one loop, found exactly by bisection of the torus's signed distance along the
// side's lines.
class TorusCylinder : public ::testing::TestWithParam<BooleanOp> {};

TEST_P(TorusCylinder, MatchesExactCsg) {
    const PointCloud a = EvenTorus(0.02), b = EvenCylinder(0.25, 0.02);
    BooleanOptions opt;
    opt.transform.rotation = Eigen::AngleAxisd(0.2, Vec3d(1, 2, 0).normalized()).toRotationMatrix();
    opt.transform.translation = Vec3d(1, 0, 0.25);
    const Solid sa{Shape::kTorus, 1.0, {}}, sb{Shape::kCylinder, 0.25, opt.transform};
    static const std::vector<Vec3d> pts = [&] {
        std::vector<Vec3d> out;
        for (int i = 0; i < 20000; ++i) {  // 8e-5 apart
            const double phi = 2 * kPi * i / 20000;
            auto at = [&](double z) {
                return Vec3d(opt.transform.rotation *
                                 Vec3d(0.25 * std::cos(phi), 0.25 * std::sin(phi), z) +
                             opt.transform.translation);
            };
            double lo = -0.25, hi = 0.25;  // inside the tube at the bottom, outside at the top
            EXPECT_LT(sa.Sd(at(lo)), 0);
            EXPECT_GT(sa.Sd(at(hi)), 0);
            for (int it = 0; it < 40; ++it)
                (sa.Sd(at(0.5 * (lo + hi))) < 0 ? lo : hi) = 0.5 * (lo + hi);
            out.push_back(at(0.5 * (lo + hi)));
        }
        return out;
    }();
    const BooleanResult r = Boolean(a, b, GetParam(), opt);
    ExpectExact(r, sa, sb, Curve(pts), GetParam());
}

// A coarse sphere (3000 samples) and a fine one (30000): near the curve the coarse side is split
// to the fine side's density (3.1.2), and the result is as exact as with equal densities.
TEST(Boolean, UpsamplesTheCoarserInputNearTheCurve) {
    const PointCloud a = EvenSphere(3000, 1.0), b = EvenSphere(30000, 1.0);
    BooleanOptions opt;
    opt.transform.translation = Vec3d(1.2, 0, 0);
    const Solid sa{Shape::kSphere, 1.0, {}}, sb{Shape::kSphere, 1.0, opt.transform};
    const Circle curve{Vec3d(0.6, 0, 0), Vec3d(1, 0, 0), 0.8};
    for (BooleanOp op : {BooleanOp::kUnion, BooleanOp::kDifference}) {
        const BooleanResult r = Boolean(a, b, op, opt);
        EXPECT_GT(r.report.upsampled_a, 0u);
        EXPECT_GT(r.report.added_a, 4 * r.report.upsampled_a);
        EXPECT_EQ(r.report.upsampled_b, 0u);
        ExpectExact(r, sa, sb, curve, op);
        // Mean distance to the nearest other sample among A's samples within 0.1 of the curve:
        // near B's spacing (0.02), not A's (0.065).
        const ExtraAttribute* src = r.cloud.FindExtra(kSourceAttribute);
        std::vector<Vec3f> near;
        for (std::size_t i = 0; i < r.cloud.size(); ++i)
            if (src->values[i] == 0 && curve.Distance(r.cloud.positions[i].cast<double>()) < 0.1)
                near.push_back(r.cloud.positions[i]);
        ASSERT_GT(near.size(), 100u);
        const KdTree tree(near);
        double sum = 0;
        std::vector<Neighbor> nb;
        for (const Vec3f& p : near) {
            tree.Knn(p, 2, &nb);
            sum += std::sqrt(double{nb[1].dist2});
        }
        const double mean = sum / near.size();
        std::printf("  up-sampled %zu of A's samples into %zu; mean spacing near the curve %.4f\n",
                    r.report.upsampled_a, r.report.added_a, mean);
        EXPECT_LT(mean, 0.03);
    }
}

// Externally tangent spheres: the surfaces touch in one point. The union keeps (nearly) both,
// the intersection (nearly) nothing; nothing lands off the exact boundary or on the wrong side.
TEST(Boolean, TangentSpheres) {
    const PointCloud a = EvenSphere(20000, 1.0), b = EvenSphere(20000, 1.0);
    BooleanOptions opt;
    opt.transform.translation = Vec3d(2, 0, 0);
    const Solid sa{Shape::kSphere, 1.0, {}}, sb{Shape::kSphere, 1.0, opt.transform};
    const Circle touch{Vec3d(1, 0, 0), Vec3d(1, 0, 0), 0.0};
    for (BooleanOp op : kBooleanOps) {
        const BooleanResult r = Boolean(a, b, op, opt);
        const Measures m = Measure(r, sa, sb, touch, op);
        std::printf(
            "  tangent %-18s kept a %zu b %zu curve %zu, boundary %.2e, wrong side %zu, normals "
            "%zu, holes %.2f\n",
            r.report.op.c_str(), r.report.kept_a, r.report.kept_b, r.report.curve_samples,
            m.max_boundary, m.wrong_side, m.wrong_normal, m.worst_hole);
        EXPECT_LE(m.max_boundary, 1e-3 * m.diag) << r.report.op;
        EXPECT_EQ(m.wrong_side, 0u) << r.report.op;
        EXPECT_EQ(m.wrong_normal, 0u) << r.report.op;
        const std::size_t expected = op == BooleanOp::kUnion          ? 40000
                                     : op == BooleanOp::kIntersection ? 0
                                                                      : 20000;
        EXPECT_NEAR(static_cast<double>(r.report.kept_a + r.report.kept_b),
                    static_cast<double>(expected), 10.0)
            << r.report.op;
        if (op != BooleanOp::kIntersection) EXPECT_LE(m.worst_hole, 2.0) << r.report.op;
    }
}

// Boxes sharing part of a face. Touching (B beside A, the normals opposed): the contact patch
// is interior to the union, absent from the (empty) intersection, and A's (B's) side of it stays
// in A − B (B − A). Coincident (B shifted within A's face plane, same normals): the patch stays
// once in the union and the intersection and goes in both differences.
TEST(Boolean, CoincidentFaces) {
    const PointCloud a = EvenBox(40, 0.5), b = EvenBox(40, 0.5);
    for (const bool touching : {true, false}) {
        BooleanOptions opt;
        opt.transform.translation = touching ? Vec3d(1.0, 0.25, 0.25) : Vec3d(0, 0.25, 0.25);
        for (BooleanOp op : kBooleanOps) {
            const BooleanResult r = Boolean(a, b, op, opt);
            const ExtraAttribute* src = r.cloud.FindExtra(kSourceAttribute);
            ASSERT_NE(src, nullptr);
            // Samples on the patch x = 0.5, y and z in [-0.25, 0.5], 5 spacings (2.5 h) inside its
            // rim: nearer, the MLS surface rounds the other box's edge off by more than the
            // coincident_tolerance (0.01 spacings), and the samples there are classified by that
            // rounded surface (at 4.5 spacings one row still is).
            std::size_t on_a = 0, on_b = 0;
            for (std::size_t i = 0; i < r.cloud.size(); ++i) {
                const Vec3f& p = r.cloud.positions[i];
                if (std::abs(p.x() - 0.5f) > 1e-4f || std::min(p.y(), p.z()) < -0.125f ||
                    std::max(p.y(), p.z()) > 0.375f)
                    continue;
                (src->values[i] == 0 ? on_a : on_b) += 1;
            }
            const std::size_t patch = 20 * 20;  // (0.5 / 0.025)^2 grid cells of a face
            std::printf("  %s %-18s kept a %zu b %zu, on the patch: a %zu b %zu\n",
                        touching ? "touching  " : "coincident", r.report.op.c_str(),
                        r.report.kept_a, r.report.kept_b, on_a, on_b);
            const bool a_stays = touching
                                     ? op == BooleanOp::kDifference
                                     : op == BooleanOp::kUnion || op == BooleanOp::kIntersection;
            const bool b_stays = touching && op == BooleanOp::kReverseDifference;
            EXPECT_EQ(on_a, a_stays ? patch : 0u)
                << r.report.op << (touching ? " touching" : " coincident");
            EXPECT_EQ(on_b, b_stays ? patch : 0u)
                << r.report.op << (touching ? " touching" : " coincident");
        }
    }
}

std::string OpName(const ::testing::TestParamInfo<BooleanOp>& info) {
    std::string s = BooleanOpName(info.param);
    std::replace(s.begin(), s.end(), '-', '_');
    return s;
}
INSTANTIATE_TEST_SUITE_P(Ops, SphereBox, ::testing::ValuesIn(kBooleanOps), OpName);
INSTANTIATE_TEST_SUITE_P(Ops, TwoSpheres, ::testing::ValuesIn(kBooleanOps), OpName);
INSTANTIATE_TEST_SUITE_P(Ops, SphereCylinder, ::testing::ValuesIn(kBooleanOps), OpName);
INSTANTIATE_TEST_SUITE_P(Ops, TorusCylinder, ::testing::ValuesIn(kBooleanOps), OpName);

// Inputs without normals: estimated and oriented outward, same answer.
TEST(Boolean, EstimatesNormals) {
    PointCloud a = EvenSphere(20000, 1.0), b = EvenSphere(16000, 1.0);
    a.normals.clear();
    b.normals.clear();
    BooleanOptions opt;
    opt.transform.translation = Vec3d(1.2, 0, 0);
    const Solid sa{Shape::kSphere, 1.0, {}}, sb{Shape::kSphere, 1.0, opt.transform};
    const Circle curve{Vec3d(0.6, 0, 0), Vec3d(1, 0, 0), 0.8};
    const BooleanResult r = Boolean(a, b, BooleanOp::kIntersection, opt);
    EXPECT_TRUE(r.report.normals_estimated_a);
    EXPECT_TRUE(r.report.normals_estimated_b);
    ExpectExact(r, sa, sb, curve, BooleanOp::kIntersection);
}

// The coherence shortcut changes the work, not the answer.
TEST(Boolean, CoherenceSavesQueriesWithoutChangingTheResult) {
    const PointCloud a = Sample(Shape::kSphere, 20000, 1.0, 7),
                     b = Sample(Shape::kSphere, 20000, 1.0, 8);
    BooleanOptions opt;
    opt.transform.translation = Vec3d(1.2, 0, 0);
    const BooleanResult with = Boolean(a, b, BooleanOp::kUnion, opt);
    opt.coherence = false;
    const BooleanResult without = Boolean(a, b, BooleanOp::kUnion, opt);
    EXPECT_EQ(without.report.queries_saved, 0u);
    EXPECT_GT(with.report.queries_saved_share, 0.3);
    EXPECT_EQ(with.report.classification_queries, 40000u);
    EXPECT_EQ(with.report.kept_a, without.report.kept_a);
    EXPECT_EQ(with.report.kept_b, without.report.kept_b);
    std::printf("  coherence saved %.1f %% of %zu queries\n", 100 * with.report.queries_saved_share,
                with.report.classification_queries);
}

// Disjoint inputs: the trivial answer with a note; an empty intersection is a valid empty cloud.
TEST(Boolean, DisjointInputsGiveTheTrivialAnswer) {
    const PointCloud a = Sample(Shape::kSphere, 2000, 1.0, 9),
                     b = Sample(Shape::kBox, 2000, 0.5, 10);
    BooleanOptions opt;
    opt.transform.translation = Vec3d(3, 0, 0);
    const BooleanResult u = Boolean(a, b, BooleanOp::kUnion, opt);
    EXPECT_FALSE(u.report.overlap);
    ASSERT_FALSE(u.report.notes.empty());
    EXPECT_NE(u.report.notes[0].find("do not overlap"), std::string::npos);
    ASSERT_EQ(u.cloud.size(), 4000u);
    EXPECT_NEAR(u.cloud.positions[2000].x(), b.positions[0].x() + 3.0f, 1e-6);
    const BooleanResult i = Boolean(a, b, BooleanOp::kIntersection, opt);
    EXPECT_TRUE(i.cloud.empty());
    i.cloud.CheckConsistent();
    EXPECT_NE(i.cloud.FindExtra(kCreaseAttribute), nullptr);
    const BooleanResult d = Boolean(a, b, BooleanOp::kDifference, opt);
    EXPECT_EQ(d.cloud.size(), 2000u);
    const BooleanResult rd = Boolean(a, b, BooleanOp::kReverseDifference, opt);
    EXPECT_EQ(rd.cloud.size(), 2000u);
}

// A box inside a sphere: the surfaces do not meet; B − A is empty, A ∩ B is the box.
TEST(Boolean, NestedSolids) {
    const PointCloud a = Sample(Shape::kSphere, 8000, 1.0, 11),
                     b = Sample(Shape::kBox, 8000, 0.4, 12);
    const BooleanResult i = Boolean(a, b, BooleanOp::kIntersection);
    EXPECT_EQ(i.report.kept_a, 0u);
    EXPECT_EQ(i.report.kept_b, b.size());
    EXPECT_EQ(i.report.curve_samples, 0u);
    const BooleanResult rd = Boolean(a, b, BooleanOp::kReverseDifference);
    EXPECT_TRUE(rd.cloud.empty());
    const BooleanResult d = Boolean(a, b, BooleanOp::kDifference);
    EXPECT_EQ(d.cloud.size(), a.size() + b.size());  // a hollow sphere: the box's faces inward
    const ExtraAttribute* src = d.cloud.FindExtra(kSourceAttribute);
    ASSERT_NE(src, nullptr);
    for (std::size_t k = 0; k < d.cloud.size(); ++k) {
        if (src->values[k] != 1) continue;
        const Vec3d p = d.cloud.positions[k].cast<double>();
        ASSERT_LT(d.cloud.normals[k].cast<double>().dot(ShapeNormal(Shape::kBox, p, 0.4)), 0) << k;
    }
}

ErrorCode CodeOf(const std::function<void()>& f, std::string* what) {
    try {
        f();
    } catch (const Error& e) {
        *what = e.what();
        return e.code();
    }
    *what = "";
    return ErrorCode::kInternal;
}

void ExpectInvalid(const std::function<void()>& f, const std::string& field) {
    std::string what;
    EXPECT_EQ(CodeOf(f, &what), ErrorCode::kInvalidArgument) << what;
    EXPECT_EQ(what.rfind(field + ":", 0), 0u) << what;
}

TEST(Boolean, RejectsBadOptions) {
    const PointCloud a = Sample(Shape::kSphere, 2000, 1.0, 13);
    auto run = [&](const BooleanOptions& o) {
        return [&a, o] { Boolean(a, a, BooleanOp::kUnion, o); };
    };
    BooleanOptions o;
    o.transform.scale = 0;
    ExpectInvalid(run(o), "transform.scale");
    o = {};
    o.transform.rotation(0, 1) = 0.3;
    ExpectInvalid(run(o), "transform.rotation");
    o = {};
    o.transform.rotation = Eigen::Vector3d(1, 1, -1).asDiagonal();  // a reflection
    ExpectInvalid(run(o), "transform.rotation");
    o = {};
    o.transform.translation.x() = std::nan("");
    ExpectInvalid(run(o), "transform.translation");
    o = {};
    o.mls.degree = 5;
    ExpectInvalid(run(o), "mls.degree");
    o = {};
    o.normals.k = 1;
    ExpectInvalid(run(o), "normals.k");
    o = {};
    o.curve_band = 0;
    ExpectInvalid(run(o), "curve_band");
    o = {};
    o.max_newton_iterations = 0;
    ExpectInvalid(run(o), "max_newton_iterations");
    o = {};
    o.newton_tolerance = 1;
    ExpectInvalid(run(o), "newton_tolerance");
    o = {};
    o.max_refinement_rounds = -1;
    ExpectInvalid(run(o), "max_refinement_rounds");
    o = {};
    o.max_open_area = 1.5;
    ExpectInvalid(run(o), "max_open_area");
    o = {};
    o.coincident_tolerance = 2;
    ExpectInvalid(run(o), "coincident_tolerance");
    o = {};
    o.upsample_ratio = 0.5;
    ExpectInvalid(run(o), "upsample_ratio");
}

TEST(Boolean, RejectsInputsThatDoNotBoundAVolume) {
    const PointCloud sphere = Sample(Shape::kSphere, 20000, 1.0, 14);
    PointCloud tiny = Sample(Shape::kSphere, 5, 1.0, 15);
    ExpectInvalid([&] { Boolean(tiny, sphere, BooleanOp::kUnion); }, "a");
    // A sphere with its cap z > 0.5 cut off: the hole's area pi 0.75 against 3 pi left, 0.25.
    PointCloud open;
    for (std::size_t i = 0; i < sphere.size(); ++i) {
        if (sphere.positions[i].z() > 0.5f) continue;
        open.positions.push_back(sphere.positions[i]);
        open.normals.push_back(sphere.normals[i]);
    }
    ExpectInvalid([&] { Boolean(sphere, open, BooleanOp::kUnion); }, "b");
    std::string what;
    CodeOf([&] { Boolean(sphere, open, BooleanOp::kUnion); }, &what);
    EXPECT_NE(what.find("does not bound a volume"), std::string::npos) << what;
    // A plane sheet is open too; a closed box, cylinder and torus pass.
    ExpectInvalid(
        [&] { Boolean(Sample(Shape::kPlane, 10000, 1.0, 16), sphere, BooleanOp::kUnion); }, "a");
    for (Shape s : {Shape::kBox, Shape::kCylinder, Shape::kTorus})
        EXPECT_NO_THROW(Boolean(Sample(s, 20000, 1.0, 17), sphere, BooleanOp::kUnion))
            << ShapeName(s);
}

// Real scans (skipped without ../shared/data): closed reconstructions pass, with estimated
// normals; a single range scan (one side of the bunny) does not bound a volume.
TEST(Boolean, SharedDataVolumes) {
    const std::string dir = SURFEL_SHARED_DATA_DIR;
    if (!std::filesystem::exists(dir + "/bunny.ply") ||
        !std::filesystem::exists(dir + "/bunny_scan.ply"))
        GTEST_SKIP() << "no shared data at " << dir;
    const PointCloud bunny = ReadPointCloud(dir + "/bunny.ply");
    const PointCloud scan = ReadPointCloud(dir + "/bunny_scan.ply");
    BooleanOptions opt;
    opt.transform.rotation = Eigen::AngleAxisd(0.6, Vec3d::UnitY()).toRotationMatrix();
    opt.transform.translation = Vec3d(0.03, 0.01, 0);
    const BooleanResult r = Boolean(bunny, bunny, BooleanOp::kUnion, opt);
    EXPECT_TRUE(r.report.normals_estimated_a);
    EXPECT_GT(r.report.curve_samples, 100u);
    EXPECT_LT(r.report.mean_newton_iterations, 4.0);
    std::printf(
        "  bunny ∪ rotated bunny: kept %zu + %zu, curve %zu, newton %.2f, saved %.1f %%, %.0f ms\n",
        r.report.kept_a, r.report.kept_b, r.report.curve_samples, r.report.mean_newton_iterations,
        100 * r.report.queries_saved_share, r.report.time_ms);
    ExpectInvalid([&] { Boolean(bunny, scan, BooleanOp::kUnion); }, "b");
}

// The same output, bit for bit, on one thread and on all.
TEST(Boolean, IndependentOfTheThreadCount) {
    const PointCloud a = Sample(Shape::kSphere, 8000, 1.0, 19),
                     b = Sample(Shape::kTorus, 8000, 1.0, 20);
    BooleanOptions opt;
    opt.transform.translation = Vec3d(0.5, 0.2, 0.1);
    const BooleanResult all = Boolean(a, b, BooleanOp::kDifference, opt);
    BooleanResult one;
    {
        tbb::global_control limit(tbb::global_control::max_allowed_parallelism, 1);
        one = Boolean(a, b, BooleanOp::kDifference, opt);
    }
    ASSERT_GT(all.report.curve_samples, 0u);
    EXPECT_EQ(all.cloud.positions, one.cloud.positions);
    EXPECT_EQ(all.cloud.normals, one.cloud.normals);
    EXPECT_EQ(all.cloud.radii, one.cloud.radii);
    EXPECT_EQ(all.report.queries_saved, one.report.queries_saved);
    EXPECT_EQ(all.report.mean_newton_iterations, one.report.mean_newton_iterations);
}

// B the same cloud as A (the notes' Figure 3.3: a solid and a moved copy of itself) is prepared
// once; the result equals that of preparing the copy on its own (here: B given the normals A's
// preparation estimates, which makes it a different input to share).
TEST(Boolean, ACopyOfItselfIsPreparedOnceWithTheSameResult) {
    PointCloud a = Sample(Shape::kTorus, 12000, 1.0, 21);
    a.normals.clear();
    PointCloud b = a;
    {
        const KdTree tree(a.positions);
        NormalOptions no;
        no.orient = true;
        b.normals = EstimateNormals(tree, no).normals;
    }
    BooleanOptions opt;
    opt.transform.rotation = Eigen::AngleAxisd(0.7, Vec3d(0.3, 1, 0.2).normalized()).toRotationMatrix();
    opt.transform.translation = Vec3d(0.4, 0.1, 0.05);
    for (BooleanOp op : {BooleanOp::kUnion, BooleanOp::kDifference}) {
        const BooleanResult shared = Boolean(a, a, op, opt);
        const BooleanResult own = Boolean(a, b, op, opt);
        ASSERT_GT(shared.report.curve_samples, 0u) << BooleanOpName(op);
        EXPECT_TRUE(shared.report.normals_estimated_b);
        EXPECT_FALSE(own.report.normals_estimated_b);
        EXPECT_EQ(shared.cloud.positions, own.cloud.positions) << BooleanOpName(op);
        EXPECT_EQ(shared.cloud.normals, own.cloud.normals) << BooleanOpName(op);
        EXPECT_EQ(shared.cloud.radii, own.cloud.radii) << BooleanOpName(op);
        EXPECT_EQ(shared.report.curve_samples, own.report.curve_samples);
        EXPECT_EQ(shared.report.mean_newton_iterations, own.report.mean_newton_iterations);
    }
}

TEST(Boolean, Cancels) {
    const PointCloud a = Sample(Shape::kSphere, 5000, 1.0, 18);
    BooleanOptions opt;
    opt.transform.translation = Vec3d(1, 0, 0);
    std::string what;
    EXPECT_EQ(
        CodeOf([&] { Boolean(a, a, BooleanOp::kUnion, opt, [](double) { return false; }); }, &what),
        ErrorCode::kCancelled);
}

TEST(Boolean, OpNamesRoundTrip) {
    for (BooleanOp op : kBooleanOps) EXPECT_EQ(ParseBooleanOp(BooleanOpName(op)), op);
    EXPECT_FALSE(ParseBooleanOp("xor").has_value());
}

// ---- Blending (3.1.4) --------------------------------------------------------------------------

// The cuboid centre +- half, an even grid of cell centres (spacing about `spacing`) on each face,
// exact outward normals.
PointCloud EvenCuboid(const Vec3d& centre, const Vec3d& half, double spacing) {
    PointCloud c;
    for (int axis = 0; axis < 3; ++axis)
        for (int sign = -1; sign <= 1; sign += 2) {
            const int u = (axis + 1) % 3, v = (axis + 2) % 3;
            const int mu = std::max(1, static_cast<int>(std::lround(2 * half[u] / spacing)));
            const int mv = std::max(1, static_cast<int>(std::lround(2 * half[v] / spacing)));
            for (int i = 0; i < mu; ++i)
                for (int j = 0; j < mv; ++j) {
                    Vec3d p = centre, n = Vec3d::Zero();
                    p[axis] += sign * half[axis];
                    p[u] += half[u] * (2.0 * (i + 0.5) / mu - 1.0);
                    p[v] += half[v] * (2.0 * (j + 0.5) / mv - 1.0);
                    n[axis] = sign;
                    c.positions.push_back(p.cast<float>());
                    c.normals.push_back(n.cast<float>());
                }
        }
    return c;
}

// A ridge (|x| <= 0.3, |y| <= 0.6, z up to 0.6) standing in a slab (top face z = 0): their union
// has two straight concave 90-degree creases along y at x = +-0.3, z = 0. Blended with radius R
// and the ring beyond R held, co-circularity relaxes the band into the fillet cylinder of radius R
// tangent to both faces at distance R from the crease: in the cross-section (u = |x| - 0.3,
// v = z), the quarter circle about (R, R).
constexpr double kRidgeSpacing = 0.025, kBlendR = 0.15;
const PointCloud& RidgeSlab(int which) {
    static const PointCloud slab = EvenCuboid(Vec3d(0, 0, -0.3), Vec3d(1, 1, 0.3), kRidgeSpacing);
    static const PointCloud ridge = EvenCuboid(Vec3d(0, 0, 0.1), Vec3d(0.3, 0.6, 0.5), kRidgeSpacing);
    return which == 0 ? slab : ridge;
}
double FilletDistance(double u, double v) {
    if (u <= kBlendR && v <= kBlendR) return std::abs(std::hypot(u - kBlendR, v - kBlendR) - kBlendR);
    return u > kBlendR ? std::abs(v) : std::abs(u);
}
Vec3d FilletNormal(const Vec3d& p) {  // outward normal of the blended union, x > 0 side mirrored
    const double sx = p.x() < 0 ? -1.0 : 1.0, u = std::abs(p.x()) - 0.3, v = p.z();
    if (u <= kBlendR && v <= kBlendR) {
        const Eigen::Vector2d d = Eigen::Vector2d(kBlendR - u, kBlendR - v).normalized();  // towards the axis
        return Vec3d(sx * d.x(), 0, d.y());
    }
    return u > kBlendR ? Vec3d(0, 0, 1) : Vec3d(sx, 0, 0);
}

TEST(BooleanBlend, RelaxesAConcaveCreaseIntoTheFilletCylinder) {
    BooleanOptions opt;
    const BooleanResult sharp = Boolean(RidgeSlab(0), RidgeSlab(1), BooleanOp::kUnion, opt);
    opt.blend_radius = kBlendR;
    const BooleanResult blended = Boolean(RidgeSlab(0), RidgeSlab(1), BooleanOp::kUnion, opt);
    ASSERT_GT(sharp.report.curve_samples, 100u);
    ASSERT_EQ(sharp.cloud.size(), blended.cloud.size());
    const BlendReport& br = blended.report.blend;
    EXPECT_EQ(br.creases_cleared, sharp.report.curve_samples);
    EXPECT_EQ(br.knife_edges, 0u);  // a 90-degree crease
    EXPECT_GT(br.moved, 0u);
    EXPECT_GT(br.fixed, 0u);
    EXPECT_EQ(br.iterations, kDefaultBlendIterations);
    const ExtraAttribute* crease = blended.cloud.FindExtra(kCreaseAttribute);
    ASSERT_NE(crease, nullptr);
    EXPECT_EQ(std::count(crease->values.begin(), crease->values.end(), 1.0), 0);

    // In the middle of the straight creases (away from the ridge's ends and their corners).
    double worst_sharp = 0, worst = 0, worst_angle = 0, sum = 0;
    std::size_t count = 0, unchanged_far = 0, far = 0;
    for (std::size_t i = 0; i < blended.cloud.size(); ++i) {
        const Vec3d p0 = sharp.cloud.positions[i].cast<double>(), p = blended.cloud.positions[i].cast<double>();
        const double u0 = std::abs(p0.x()) - 0.3, v0 = p0.z();
        const bool near = u0 > -0.01 && u0 < 2 * kBlendR && v0 > -0.01 && v0 < 2 * kBlendR;
        if (!near || std::abs(p0.y()) > 0.3) {
            if (std::abs(p0.y()) < 0.3 && std::abs(p0.x()) > 0.3 + 2.5 * kBlendR) {
                ++far;
                unchanged_far += p == p0 && blended.cloud.normals[i] == sharp.cloud.normals[i];
            }
            continue;
        }
        const double u = std::abs(p.x()) - 0.3, v = p.z();
        worst_sharp = std::max(worst_sharp, FilletDistance(u0, v0));
        const double d = FilletDistance(u, v);
        worst = std::max(worst, d);
        sum += d;
        ++count;
        const double cosine = std::clamp(blended.cloud.normals[i].cast<double>().dot(FilletNormal(p)), -1.0, 1.0);
        worst_angle = std::max(worst_angle, std::acos(cosine) * 180 / kPi);
    }
    ASSERT_GT(count, 200u);
    std::printf("blend: %zu samples in the section, distance to the fillet: sharp max %.4f, blended max %.4f "
                "mean %.4f (R %.3f, spacing %.3f), worst normal %.1f deg; %zu moved, %zu fixed\n",
                count, worst_sharp, worst, sum / count, kBlendR, kRidgeSpacing, worst_angle, br.moved, br.fixed);
    // The sharp corner lies (sqrt 2 - 1) R = 0.41 R from the fillet; the blend lies within a fifth
    // of a spacing on average and 0.08 R at worst (measured 0.0005 and 0.019 R), its normals within
    // 12 degrees of the cylinder's (measured 9.4).
    EXPECT_GT(worst_sharp, 0.4 * kBlendR);
    EXPECT_LE(worst, 0.08 * kBlendR);
    EXPECT_LE(sum / count, 0.2 * kRidgeSpacing);
    EXPECT_LE(worst_angle, 12.0);
    // No holes: the fillet of the section (both creases) sampled finely, each point within a
    // spacing of an output sample (measured 0.9 spacings). The band shrinks from 2R to the
    // arc's 1.57R, so samples crowd: the closest pair measured 0.14 spacings (0.5 before the
    // blend, a face sample beside a curve sample); asserted: none merge (>= 0.1).
    const KdTree tree(blended.cloud.positions);
    double gap = 0, closest = 1e9;
    for (int side = -1; side <= 1; side += 2)
        for (double y = -0.25; y <= 0.25; y += 0.005)
            for (int k = 0; k <= 40; ++k) {
                const double t = 0.5 * kPi * k / 40;  // from the slab's tangent line to the ridge's
                const double u = kBlendR - kBlendR * std::sin(t), v = kBlendR - kBlendR * std::cos(t);
                const Vec3f q(static_cast<float>(side * (0.3 + u)), static_cast<float>(y), static_cast<float>(v));
                gap = std::max(gap, static_cast<double>(std::sqrt(tree.Nearest(q).dist2)));
            }
    std::vector<Neighbor> nb;
    for (std::size_t i = 0; i < blended.cloud.size(); ++i) {
        const Vec3f& p = blended.cloud.positions[i];
        if (std::abs(p.y()) > 0.25 || std::abs(p.x()) < 0.29 || std::abs(p.x()) > 0.3 + kBlendR || p.z() > kBlendR)
            continue;
        tree.Knn(p, 2, &nb);
        closest = std::min(closest, static_cast<double>(std::sqrt(nb.back().dist2)));
    }
    std::printf("blend: largest gap %.4f, closest pair %.4f (spacing %.3f)\n", gap, closest, kRidgeSpacing);
    EXPECT_LE(gap, kRidgeSpacing);
    EXPECT_GE(closest, 0.1 * kRidgeSpacing);
    // Far from the curve nothing moves.
    EXPECT_GT(far, 100u);
    EXPECT_EQ(unchanged_far, far);
}

TEST(BooleanBlend, IndependentOfTheThreadCountAndChecksItsOptions) {
    BooleanOptions opt;
    opt.blend_radius = kBlendR;
    opt.blend_iterations = 40;
    const BooleanResult all = Boolean(RidgeSlab(0), RidgeSlab(1), BooleanOp::kUnion, opt);
    BooleanResult one;
    {
        tbb::global_control limit(tbb::global_control::max_allowed_parallelism, 1);
        one = Boolean(RidgeSlab(0), RidgeSlab(1), BooleanOp::kUnion, opt);
    }
    EXPECT_EQ(all.cloud.positions, one.cloud.positions);
    EXPECT_EQ(all.cloud.normals, one.cloud.normals);
    EXPECT_EQ(all.report.blend.max_displacement, one.report.blend.max_displacement);

    for (double bad : {-1.0, std::nan(""), HUGE_VAL}) {
        opt.blend_radius = bad;
        std::string what;
        EXPECT_EQ(CodeOf([&] { opt.Validate(); }, &what), ErrorCode::kInvalidArgument);
        EXPECT_NE(what.find("blend_radius"), std::string::npos) << what;
    }
    opt.blend_radius = kBlendR;
    for (int bad : {0, kMaxBlendIterations + 1}) {
        opt.blend_iterations = bad;
        std::string what;
        EXPECT_EQ(CodeOf([&] { opt.Validate(); }, &what), ErrorCode::kInvalidArgument);
        EXPECT_NE(what.find("blend_iterations"), std::string::npos) << what;
    }
    // A bite out of a sphere: its rim is sharper than 60 degrees all round (normals 136 degrees
    // apart), every pair a knife edge. Blending it tore the render, so the result stays as it
    // is, and the report says so.
    {
        const PointCloud a = test::EvenSphere(8000), b = test::EvenSphere(8000, 0.8);
        BooleanOptions bite;
        bite.transform.translation = Vec3d(0.7, 0, 0);
        const BooleanResult sharp = Boolean(a, b, BooleanOp::kDifference, bite);
        bite.blend_radius = 0.1;
        const BooleanResult kept = Boolean(a, b, BooleanOp::kDifference, bite);
        ASSERT_GT(sharp.report.curve_samples, 50u);
        EXPECT_EQ(kept.report.blend.knife_edges, sharp.report.curve_samples);
        EXPECT_EQ(kept.report.blend.moved, 0u);
        EXPECT_EQ(kept.cloud.positions, sharp.cloud.positions);
        EXPECT_EQ(kept.cloud.normals, sharp.cloud.normals);
        ASSERT_FALSE(kept.report.notes.empty());
        EXPECT_NE(kept.report.notes.back().find("knife edges"), std::string::npos) << kept.report.notes.back();
    }
    // Disjoint inputs have no curve: the blend leaves them as they are and says so.
    BooleanOptions apart;
    apart.blend_radius = kBlendR;
    apart.transform.translation = Vec3d(5, 0, 0);
    const BooleanResult r = Boolean(RidgeSlab(0), RidgeSlab(1), BooleanOp::kUnion, apart);
    EXPECT_EQ(r.report.blend.moved, 0u);
    EXPECT_EQ(r.cloud.size(), RidgeSlab(0).size() + RidgeSlab(1).size());
}

}  // namespace
}  // namespace surfel
