// The CSG render and the crease-aware render of a boolean result (issue 14, items 6 and 9)
// against an analytic ray cast of the exact solid: ray-sphere and ray-box slab intervals combined
// by the CSG interval logic. Small images and ~20k points per solid keep it quick.

#include <gtest/gtest.h>
#include <tbb/global_control.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstring>
#include <optional>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/boolean/boolean.h"
#include "surfel/render/csg_render.h"
#include "surfel/render/renderer.h"
#include "../even_solids.h"

namespace surfel {
namespace {

constexpr double kPi = 3.14159265358979323846;

// ---- Inputs: evenly spaced samples with exact outward normals ----------------------------------

using test::EvenBox;
using test::EvenSphere;

// ---- The exact solids and their ray cast --------------------------------------------------------

// A sphere or an axis-aligned box in world coordinates (the placed inputs).
struct ExactSolid {
    bool box = false;
    Vec3d c = Vec3d::Zero();
    double r = 1.0;  // radius, or half the edge

    // The ray's interval inside the solid, or nullopt.
    std::optional<std::pair<double, double>> Interval(const Vec3d& o, const Vec3d& d) const {
        if (!box) {
            const Vec3d oc = o - c;
            const double b = oc.dot(d), disc = b * b - (oc.squaredNorm() - r * r);
            if (disc < 0) return std::nullopt;
            return std::make_pair(-b - std::sqrt(disc), -b + std::sqrt(disc));
        }
        double t0 = -1e300, t1 = 1e300;
        for (int a = 0; a < 3; ++a) {
            if (d[a] == 0) {
                if (std::abs(o[a] - c[a]) > r) return std::nullopt;
                continue;
            }
            double u = (c[a] - r - o[a]) / d[a], v = (c[a] + r - o[a]) / d[a];
            if (u > v) std::swap(u, v);
            t0 = std::max(t0, u);
            t1 = std::min(t1, v);
        }
        if (t0 > t1) return std::nullopt;
        return std::make_pair(t0, t1);
    }
    // Outward normal and face label (0 for the sphere, 1..6 for the box's faces) at boundary point p.
    std::pair<Vec3d, int> Normal(const Vec3d& p) const {
        if (!box) return {(p - c).normalized(), 0};
        const Vec3d q = p - c;
        int a = 0;
        for (int k = 1; k < 3; ++k)
            if (std::abs(q[k]) > std::abs(q[a])) a = k;
        Vec3d n = Vec3d::Zero();
        n[a] = q[a] > 0 ? 1 : -1;
        return {n, 1 + 2 * a + (q[a] > 0)};
    }
};

struct ExactHit {
    double t;
    Vec3d n;    // outward normal of the result
    int label;  // which surface: solid * 8 + face
};

// The first boundary point of op(A, B) on the ray (t > 0): the candidates are the four interval
// ends; one is an entry of the result when the point just before lies outside and just after
// inside.
std::optional<ExactHit> Cast(const ExactSolid& A, const ExactSolid& B, BooleanOp op, const Vec3d& o, const Vec3d& d) {
    const auto ia = A.Interval(o, d), ib = B.Interval(o, d);
    auto in = [](const std::optional<std::pair<double, double>>& i, double t) {
        return i && i->first < t && t < i->second;
    };
    auto in_result = [&](double t) {
        const bool a = in(ia, t), b = in(ib, t);
        switch (op) {
            case BooleanOp::kUnion: return a || b;
            case BooleanOp::kIntersection: return a && b;
            case BooleanOp::kDifference: return a && !b;
            case BooleanOp::kReverseDifference: return b && !a;
        }
        return false;
    };
    std::vector<std::pair<double, int>> ends;  // t, solid
    if (ia) ends.insert(ends.end(), {{ia->first, 0}, {ia->second, 0}});
    if (ib) ends.insert(ends.end(), {{ib->first, 1}, {ib->second, 1}});
    std::sort(ends.begin(), ends.end());
    for (const auto& [t, solid] : ends) {
        if (t <= 0) continue;
        const double eps = 1e-9;
        if (in_result(t - eps) || !in_result(t + eps)) continue;
        const ExactSolid& S = solid == 0 ? A : B;
        auto [n, face] = S.Normal(o + t * d);
        const bool subtracted = (op == BooleanOp::kDifference && solid == 1) ||
                                (op == BooleanOp::kReverseDifference && solid == 0);
        return ExactHit{t, subtracted ? Vec3d(-n) : n, solid * 8 + face};
    }
    return std::nullopt;
}

// ---- Comparisons ---------------------------------------------------------------------------------

struct Scene {
    PointCloud a, b;  // b in its own frame, placed by `options.transform`
    ExactSolid ea, eb;
    BooleanOp op;
    BooleanOptions options;
    RenderOptions render;
    double diag;  // of the box around both placed solids
    Vec3d crease; // a point of the exact intersection curve

    // The same scene seen up close at the crease: 64 x 64 pixels over 0.3 x 0.3 model units
    // (a pixel is about h / 10), from the mean of the two normals there, tilted a little.
    Scene AtCrease() const {
        Scene z = *this;
        const Vec3d n = (ea.Normal(crease).first + eb.Normal(crease).first).normalized();
        const Vec3d from = (n + Vec3d(0.1, 0.15, 0.05)).normalized();
        z.render.camera.width = z.render.camera.height = 64;
        z.render.camera.target = crease;
        z.render.camera.eye = crease + 2.5 * from;
        z.render.camera.up = std::abs(from.y()) > 0.9 ? Vec3d(1, 0, 0) : Vec3d(0, 1, 0);
        z.render.camera.fovy_deg = 2 * std::atan(0.15 / 2.5) * 180 / kPi;
        return z;
    }
};

// A camera framing `ea` (and `eb` when `both`: the result of a union) from `from`.
RenderOptions SmallRender(const ExactSolid& ea, const ExactSolid& eb, bool both, const Vec3d& from, int side) {
    BoundingBox box;
    for (const ExactSolid* s : {&ea, &eb}) {
        if (s == &eb && !both) continue;
        box.Extend((s->c - Vec3d::Constant(s->r)).cast<float>());
        box.Extend((s->c + Vec3d::Constant(s->r)).cast<float>());
    }
    RenderOptions r;
    r.camera = Camera::Framing(box, side, side, from);
    r.shadows = false;
    return r;
}

double Diag(const ExactSolid& ea, const ExactSolid& eb) {
    const Vec3d lo = (ea.c - Vec3d::Constant(ea.r)).cwiseMin(eb.c - Vec3d::Constant(eb.r));
    const Vec3d hi = (ea.c + Vec3d::Constant(ea.r)).cwiseMax(eb.c + Vec3d::Constant(eb.r));
    return (hi - lo).norm();
}

// Sphere (20k) minus the box [-1, 1]^3 placed at (0, 0, 1.4): its bottom face cuts the cap off in
// the circle z = 0.4 (a convex crease of 66 degrees).
Scene SphereMinusBox() {
    Scene s;
    s.a = EvenSphere(20000);
    s.b = EvenBox(58);
    s.ea = {false, Vec3d::Zero(), 1.0};
    s.eb = {true, Vec3d(0, 0, 1.4), 1.0};
    s.op = BooleanOp::kDifference;
    s.options.transform.translation = Vec3d(0, 0, 1.4);
    s.render = SmallRender(s.ea, s.eb, false, Vec3d(0.5, 0.6, 1.0), 96);
    s.crease = Vec3d(std::sqrt(1 - 0.16), 0, 0.4);
    s.diag = Diag(s.ea, s.eb);
    return s;
}

// Two spheres: B = the unit sphere rotated, scaled by 0.8 and moved to (0.9, 0, 0); a concave
// crease in the circle x = 0.65.
Scene SphereUnionSphere() {
    Scene s;
    s.a = EvenSphere(20000);
    s.b = EvenSphere(20000);
    s.ea = {false, Vec3d::Zero(), 1.0};
    s.eb = {false, Vec3d(0.9, 0, 0), 0.8};
    s.op = BooleanOp::kUnion;
    s.options.transform.rotation = Eigen::AngleAxisd(0.7, Vec3d(1, 2, 3).normalized()).toRotationMatrix();
    s.options.transform.scale = 0.8;
    s.options.transform.translation = Vec3d(0.9, 0, 0);
    s.render = SmallRender(s.ea, s.eb, true, Vec3d(0.3, 0.4, 1.0), 96);
    s.crease = Vec3d(0.65, 0, std::sqrt(1 - 0.65 * 0.65));
    s.diag = Diag(s.ea, s.eb);
    return s;
}

// The unit sphere intersected with the box [-0.75, 0.75]^3: six flat discs of radius 0.66.
Scene SphereIntersectBox() {
    Scene s;
    s.a = EvenSphere(20000);
    s.b = EvenBox(58);
    s.ea = {false, Vec3d::Zero(), 1.0};
    s.eb = {true, Vec3d::Zero(), 0.75};
    s.op = BooleanOp::kIntersection;
    s.options.transform.scale = 0.75;
    s.render = SmallRender(s.ea, s.eb, false, Vec3d(0.6, 0.5, 1.0), 96);
    s.crease = Vec3d(0.75, 0, std::sqrt(1 - 0.75 * 0.75));
    s.diag = Diag(s.ea, s.eb);
    return s;
}

struct Agreement {
    double agree_share = 0;   // pixels with the same coverage and depth within 1e-2 diag
    double p95_depth = 0;     // over pixels both hit, in units of diag
    int transition_width = 0; // largest distance (pixels) from a pixel whose normal is off by
                              // more than off_deg (5) degrees to a change of the exact surface
    int pixels = 0;
};

Agreement Compare(const Image& img, const Scene& s, double off_deg = 5.0) {
    const RenderOptions& r = s.render;
    const int W = r.camera.width, H = r.camera.height;
    const Camera::Frame f = r.camera.MakeFrame();
    std::vector<std::optional<ExactHit>> exact(std::size_t(W) * H);
    for (int y = 0; y < H; ++y)
        for (int x = 0; x < W; ++x) exact[y * W + x] = Cast(s.ea, s.eb, s.op, r.camera.eye, f.Direction(x + 0.5, y + 0.5));
    auto label = [&](int x, int y) { return exact[y * W + x] ? exact[y * W + x]->label : -1; };
    // Distance (Chebyshev, pixels) from (x, y) to the nearest pixel whose exact surface differs
    // from a neighbour's: 0 on such a pixel.
    auto edge_distance = [&](int x, int y) {
        for (int k = 0; k < std::max(W, H); ++k)
            for (int yy = std::max(0, y - k); yy <= std::min(H - 1, y + k); ++yy)
                for (int xx = std::max(0, x - k); xx <= std::min(W - 1, x + k); ++xx) {
                    const int l = label(xx, yy);
                    for (int dy = -1; dy <= 1; ++dy)
                        for (int dx = -1; dx <= 1; ++dx) {
                            const int nx = xx + dx, ny = yy + dy;
                            if (nx >= 0 && ny >= 0 && nx < W && ny < H && label(nx, ny) != l) return k;
                        }
                }
        return std::max(W, H);
    };
    Agreement a;
    std::vector<double> depth;
    int agree = 0;
    for (int y = 0; y < H; ++y)
        for (int x = 0; x < W; ++x) {
            const auto& e = exact[y * W + x];
            const bool hit = img.At(x, y, 3) > 0.5f;
            ++a.pixels;
            if (hit != e.has_value()) continue;
            if (!hit) {
                ++agree;
                continue;
            }
            const double dz = std::abs(img.At(x, y, 4) - e->t);
            depth.push_back(dz / s.diag);
            agree += dz <= 1e-2 * s.diag;
            const Vec3d n(img.At(x, y, 5), img.At(x, y, 6), img.At(x, y, 7));
            if (n.dot(e->n) < std::cos(off_deg * kPi / 180.0))
                a.transition_width = std::max(a.transition_width, edge_distance(x, y));
        }
    a.agree_share = double(agree) / a.pixels;
    if (!depth.empty()) {
        std::sort(depth.begin(), depth.end());
        a.p95_depth = depth[std::size_t(0.95 * (depth.size() - 1))];
    }
    return a;
}

void ExpectMatchesExact(const Scene& s, const char* name) {
    SCOPED_TRACE(name);
    const CsgRenderResult r = RenderCsg(s.a, s.b, s.op, s.render, s.options);
    const Agreement g = Compare(r.render.image, s);
    EXPECT_GE(g.agree_share, 0.995);
    EXPECT_LE(g.p95_depth, 1e-3);
    EXPECT_LE(g.transition_width, 1);
    // Up close the normal still jumps within one pixel (a crease, not a fillet).
    const Scene z = s.AtCrease();
    const Agreement gz = Compare(RenderCsg(z.a, z.b, z.op, z.render, z.options).render.image, z);
    EXPECT_GE(gz.agree_share, 0.995);
    EXPECT_LE(gz.p95_depth, 1e-3);
    EXPECT_LE(gz.transition_width, 1);
    EXPECT_GT(r.report.classifications, 0u);
    EXPECT_GT(r.report.queries_saved, 0u);  // the coherence spheres answer some hits
    std::printf("[ %s ] CSG render: agree %.4f, p95 depth %.2e diag, transition %d px; at the crease: agree %.4f, "
                "p95 %.2e, transition %d px; %llu queries, %.1f%% saved, %.0f ms\n",
                name, g.agree_share, g.p95_depth, g.transition_width, gz.agree_share, gz.p95_depth,
                gz.transition_width,
                static_cast<unsigned long long>(r.report.classifications),
                100.0 * r.report.queries_saved / std::max<std::uint64_t>(1, r.report.classifications),
                r.render.stats.time_ms);
}

TEST(CsgRender, SphereMinusBoxMatchesTheExactCast) { ExpectMatchesExact(SphereMinusBox(), "sphere - box"); }
TEST(CsgRender, SphereUnionSphereMatchesTheExactCast) { ExpectMatchesExact(SphereUnionSphere(), "sphere u sphere"); }
TEST(CsgRender, SphereIntersectBoxMatchesTheExactCast) { ExpectMatchesExact(SphereIntersectBox(), "sphere n box"); }

// The normal of the subtracted solid is turned over: on the cut face of sphere - box, N = +z.
TEST(CsgRender, SubtractedSolidNormalsPointOut) {
    Scene s = SphereMinusBox();
    s.render.camera.width = s.render.camera.height = 32;
    s.render.camera.eye = Vec3d(0, 0, 5);
    s.render.camera.target = Vec3d(0, 0, 0);
    s.render.camera.fovy_deg = 8;  // the centre of the cut face only
    const Image img = RenderCsg(s.a, s.b, s.op, s.render, s.options).render.image;
    for (int y = 0; y < 32; ++y)
        for (int x = 0; x < 32; ++x) {
            ASSERT_GT(img.At(x, y, 3), 0.5f);
            const Vec3d d = s.render.camera.Direction(x + 0.5, y + 0.5);
            EXPECT_NEAR(img.At(x, y, 4), 4.6 / -d.z(), 1e-3);  // the face z = 0.4
            EXPECT_GT(img.At(x, y, 7), 0.999f);
        }
}

// Both renders of the same boolean agree: the CSG render and the crease-aware render of
// Boolean()'s output; the latter also matches the exact cast, and without the crease handling the
// MLS surface rounds the edge off (the measure sees the fillet).
TEST(CsgRender, CreaseAwareRenderOfTheBooleanOutputAgrees) {
    for (const Scene& s : {SphereMinusBox(), SphereUnionSphere()}) {
        SCOPED_TRACE(BooleanOpName(s.op));
        const BooleanResult b = Boolean(s.a, s.b, s.op, s.options);
        ASSERT_TRUE(HasSurfelPairs(b.cloud));
        const Image csg = RenderCsg(s.a, s.b, s.op, s.render, s.options).render.image;
        const Image creased = Render(b.cloud, s.render).image;
        const int W = s.render.camera.width, H = s.render.camera.height;
        int agree = 0;
        std::vector<double> dz;
        for (int y = 0; y < H; ++y)
            for (int x = 0; x < W; ++x) {
                const bool h1 = csg.At(x, y, 3) > 0.5f, h2 = creased.At(x, y, 3) > 0.5f;
                if (h1 != h2) continue;
                if (!h1) {
                    ++agree;
                    continue;
                }
                const double d = std::abs(csg.At(x, y, 4) - creased.At(x, y, 4)) / s.diag;
                dz.push_back(d);
                agree += d <= 1e-2;
            }
        std::sort(dz.begin(), dz.end());
        const double share = double(agree) / (W * H), p95 = dz[std::size_t(0.95 * (dz.size() - 1))];
        EXPECT_GE(share, 0.99);
        EXPECT_LE(p95, 1e-3);
        const Agreement g = Compare(creased, s);
        EXPECT_GE(g.agree_share, 0.99);
        EXPECT_LE(g.p95_depth, 1e-3);
        EXPECT_LE(g.transition_width, 1);
        const Scene z = s.AtCrease();
        const Agreement gz = Compare(Render(b.cloud, z.render).image, z);
        EXPECT_GE(gz.agree_share, 0.99);
        EXPECT_LE(gz.transition_width, 1);
        RenderOptions smooth = z.render;
        smooth.creases = false;
        const Image smooth_img = Render(b.cloud, smooth).image;
        const Agreement f = Compare(smooth_img, z);
        EXPECT_GE(f.transition_width, 2);  // the fillet the crease handling removes (4-5 px at h = 2 spacings, 2-3 at 1.4)
        std::printf("[ %s ] CSG vs boolean output: agree %.4f, p95 %.2e diag; crease-aware vs exact: agree %.4f, "
                    "p95 %.2e, transition %d px, at the crease %d px; smooth: at the crease %d px\n",
                    BooleanOpName(s.op), share, p95, g.agree_share, g.p95_depth, g.transition_width,
                    gz.transition_width, f.transition_width);
    }
}

TEST(CsgRender, DoesNotDependOnTheThreadCount) {
    Scene s = SphereUnionSphere();
    s.render.camera.width = s.render.camera.height = 48;
    s.render.shadows = true;
    const Image many = RenderCsg(s.a, s.b, s.op, s.render, s.options).render.image;
    Image one;
    {
        tbb::global_control single(tbb::global_control::max_allowed_parallelism, 1);
        one = RenderCsg(s.a, s.b, s.op, s.render, s.options).render.image;
    }
    ASSERT_EQ(many.pixels.size(), one.pixels.size());
    EXPECT_EQ(0, std::memcmp(many.pixels.data(), one.pixels.data(), many.pixels.size() * sizeof(float)));
}

// Shadow rays see the boolean too: with the light straight down, the cut face of sphere - box is
// lit (the box, which would shade it, is not there).
TEST(CsgRender, ShadowRaysSeeTheBoolean) {
    Scene s = SphereMinusBox();
    s.render.camera.width = s.render.camera.height = 16;
    s.render.camera.eye = Vec3d(0, 0, 5);
    s.render.camera.target = Vec3d(0, 0, 0);
    s.render.camera.fovy_deg = 8;
    s.render.shadows = true;
    s.render.lights = {{Light::Kind::kDirectional, {0, 0, -1}, {1, 1, 1}, 1.0}};
    s.render.ambient = 0.1;
    s.render.specular = 0;
    const Image img = RenderCsg(s.a, s.b, s.op, s.render, s.options).render.image;
    for (int y = 0; y < 16; ++y)
        for (int x = 0; x < 16; ++x) EXPECT_GT(img.At(x, y, 0), 0.5f) << x << "," << y;
}

void ExpectInvalid(const std::function<void()>& f, const std::string& what) {
    try {
        f();
        ADD_FAILURE() << "no error, expected " << what;
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
        EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
}

TEST(CsgRender, ErrorsNameTheField) {
    const Scene s = SphereMinusBox();
    BooleanOptions bad = s.options;
    bad.transform.scale = 0;
    ExpectInvalid([&] { RenderCsg(s.a, s.b, s.op, s.render, bad); }, "transform.scale");
    RenderOptions r = s.render;
    r.camera.width = 0;
    ExpectInvalid([&] { RenderCsg(s.a, s.b, s.op, r, s.options); }, "width");
    PointCloud tiny;
    tiny.positions = {Vec3f(0, 0, 0), Vec3f(1, 0, 0), Vec3f(0, 1, 0)};
    ExpectInvalid([&] { RenderCsg(s.a, tiny, s.op, s.render, s.options); }, "b: needs at least");
    ExpectInvalid([&] { RenderWithCreases(s.a, s.render); }, "no surfel pairs");
}

}  // namespace
}  // namespace surfel
