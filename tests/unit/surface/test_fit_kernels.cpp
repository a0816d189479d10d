// The fits' weighted sums (surface/fit_kernels.h): both builds against sums in long double, on
// the sizes a fit sees (none, fewer than a vector, ~110 neighbours, many), and against each
// other. They add the same terms in another order, so they agree to rounding, not to the bit.
#include <gtest/gtest.h>

#include <Eigen/Cholesky>

#include <cmath>
#include <cstring>
#include <iterator>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "surfel/surface/fit_kernels.h"
#include "surfel/surface/ldlt6.h"
#include "surfel/surface/poly_fit.h"

namespace surfel {
namespace {

struct Samples {
    std::vector<float> fx, fy, fz, w;
    std::vector<double> dx, dy, dz;
};

Samples Make(std::size_t n, unsigned seed) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<float> pos(-0.01f, 0.01f), weight(0.0f, 1.0f);
    Samples s;
    for (std::size_t i = 0; i < n; ++i) {
        s.fx.push_back(pos(rng)), s.fy.push_back(pos(rng)), s.fz.push_back(0.1f * pos(rng)), s.w.push_back(weight(rng));
        s.dx.push_back(s.fx.back()), s.dy.push_back(s.fy.back()), s.dz.push_back(s.fz.back());
    }
    return s;
}

// Reference sums in long double, in fit_kernels.h's order.
std::vector<long double> MomentsRef(const Samples& s) {
    std::vector<long double> r(10, 0.0L);
    for (std::size_t i = 0; i < s.w.size(); ++i) {
        const long double x = s.fx[i], y = s.fy[i], z = s.fz[i], w = s.w[i];
        const long double t[10] = {w, w * x, w * y, w * z, w * x * x, w * x * y, w * x * z, w * y * y, w * y * z, w * z * z};
        for (int k = 0; k < 10; ++k) r[k] += t[k];
    }
    return r;
}

std::vector<long double> PolyRef(const Samples& s, double ih) {
    std::vector<long double> r(21, 0.0L);
    for (std::size_t i = 0; i < s.w.size(); ++i) {
        const long double x = s.dx[i] * ih, y = s.dy[i] * ih, z = s.dz[i], w = s.w[i];
        const long double t[21] = {w,         w * x,         w * y,         w * x * x,     w * x * y,     w * y * y,
                                   w * x * x * x, w * x * x * y, w * x * y * y, w * y * y * y, w * x * x * x * x,
                                   w * x * x * x * y, w * x * x * y * y, w * x * y * y * y, w * y * y * y * y,
                                   w * z,     w * x * z,     w * y * z,     w * x * x * z, w * x * y * z, w * y * y * z};
        for (int k = 0; k < 21; ++k) r[k] += t[k];
    }
    return r;
}

// |a - ref| within 1e-13 of the sum of the terms' magnitudes (a bound on any order's rounding
// error of ~1000 terms in double: n * 2^-53 ~ 1e-13), here taken as the weight-scaled bound.
void ExpectClose(const double* a, const std::vector<long double>& ref, double scale, const char* what, std::size_t n) {
    for (std::size_t k = 0; k < ref.size(); ++k)
        EXPECT_NEAR(a[k], double(ref[k]), 1e-13 * scale + 1e-300) << what << " sum " << k << ", n = " << n;
}

TEST(FitKernels, BothBuildsGiveTheSumsToRounding) {
    const double ih = 1.0 / 0.0025;
    for (const std::size_t n : {std::size_t(0), std::size_t(1), std::size_t(3), std::size_t(7), std::size_t(110),
                                std::size_t(1000)}) {
        const Samples s = Make(n, 17 + unsigned(n));
        const auto mref = MomentsRef(s);
        const auto pref = PolyRef(s, ih);
        for (const fit_kernels::Kernels* k : {&fit_kernels::Baseline(), &fit_kernels::Best()}) {
            double m[10], p[21];
            k->moments(s.fx.data(), s.fy.data(), s.fz.data(), s.w.data(), n, m);
            k->poly_sums(s.dx.data(), s.dy.data(), s.dz.data(), s.w.data(), n, ih, p);
            // Scales: sum w for the moments (|x| < 0.01), and sum w (|x ih| < 4)^4 for the polynomial's.
            ExpectClose(m, mref, double(mref[0]) + 1e-30, k->isa, n);
            ExpectClose(p, pref, 256.0 * double(pref[0]) + 1e-30, k->isa, n);
            if (n == 0) EXPECT_EQ(m[0], 0.0);
        }
    }
    EXPECT_TRUE(std::string(fit_kernels::Best().isa) == "avx2" || std::string(fit_kernels::Best().isa) == "baseline");
}

// The elementwise kernels MLS uses in place of poly_fit.h's NeighborBatch::WeightsAround and
// ToLocal: the same bits as those in both builds (no sums, no reordering; products rounded alike).
TEST(FitKernels, ElementwiseKernelsGiveNeighborBatchsBits) {
    for (const std::size_t n : {std::size_t(1), std::size_t(5), std::size_t(110), std::size_t(1001)}) {
        const Samples s = Make(n, 5 + unsigned(n));
        NeighborBatch nb;
        for (std::size_t i = 0; i < n; ++i) nb.Push(std::uint32_t(i), Vec3f(s.fx[i], s.fy[i], s.fz[i]));
        const Vec3d c(1e-3, -2e-3, 4e-4), u = Vec3d(1, 2, 3).normalized(), v = u.cross(Vec3d::UnitZ()).normalized(),
                    nrm = u.cross(v);
        const double h = 0.0031;
        nb.WeightsAround(c, h);
        const std::vector<float> d2(nb.d2.begin(), nb.d2.begin() + n), w(nb.w.begin(), nb.w.begin() + n);
        nb.ToLocal(c, u, v, nrm);
        const double f[12] = {c.x(), c.y(), c.z(), u.x(), u.y(), u.z(), v.x(), v.y(), v.z(), nrm.x(), nrm.y(), nrm.z()};
        for (const fit_kernels::Kernels* k : {&fit_kernels::Baseline(), &fit_kernels::Best()}) {
            std::vector<float> kd(n), kw(n);
            std::vector<double> lx(n), ly(n), lz(n);
            k->squared_distances_around(s.fx.data(), s.fy.data(), s.fz.data(), n, c.x(), c.y(), c.z(), kd.data());
            k->gauss_weights(kd.data(), static_cast<float>(1.0 / (h * h)), kw.data(), n);
            k->to_local(s.fx.data(), s.fy.data(), s.fz.data(), n, f, lx.data(), ly.data(), lz.data());
            for (std::size_t i = 0; i < n; ++i) {
                ASSERT_EQ(kd[i], d2[i]) << k->isa << " i = " << i;
                ASSERT_EQ(kw[i], w[i]) << k->isa << " i = " << i;
                ASSERT_EQ(lx[i], nb.lx[i]) << k->isa << " i = " << i;
                ASSERT_EQ(ly[i], nb.ly[i]) << k->isa << " i = " << i;
                ASSERT_EQ(lz[i], nb.lz[i]) << k->isa << " i = " << i;
            }
        }
    }
}

// The normal-aware weight factors: every build gives, to the bit, what the scalar formula of
// AaSurface's fits gives with std::exp (Eigen's float dot, expf), on unit normals at every angle
// to the reference (c^2 up to (2 / sigma)^2) and on sizes below, at and above the vector width;
// with sigma = 0.05 the arguments leave expf's fast path (|x| >= 88) and the lanes fall back.
TEST(FitKernels, NormalFactorsAreExpfToTheBit) {
    std::mt19937 rng(29);
    std::normal_distribution<float> g(0.0f, 1.0f);
    const std::size_t points = 4000;
    std::vector<Vec3f> normals(points);
    for (Vec3f& n : normals) n = Vec3f(g(rng), g(rng), g(rng)).normalized();
    normals[7] = Vec3f(std::nanf(""), 0, 0);  // a NaN lane takes the slow path too
    std::uniform_int_distribution<std::uint32_t> pick(0, points - 1);
    const Vec3f ref = Vec3f(0.3f, -0.5f, 0.8f).normalized();
    const float r[3] = {ref.x(), ref.y(), ref.z()};
    for (const float sigma : {0.5f, 0.25f, 1.0f, 0.05f})
        for (const std::size_t n : {std::size_t(0), std::size_t(5), std::size_t(8), std::size_t(110), std::size_t(3001)}) {
            std::vector<std::uint32_t> index(n);
            for (auto& i : index) i = pick(rng);
            if (n > 3) index[3] = 7;
            std::vector<float> w0(n);
            for (auto& w : w0) w = std::abs(g(rng));
            const float inv = 1.0f / sigma;
            std::vector<float> want = w0;
            for (std::size_t j = 0; j < n; ++j) {
                const float c = (1.0f - normals[index[j]].dot(ref)) * inv;
                want[j] *= std::exp(-c * c);
            }
            std::vector<float> nx(n), ny(n), nz(n);
            for (std::size_t j = 0; j < n; ++j)
                nx[j] = normals[index[j]].x(), ny[j] = normals[index[j]].y(), nz[j] = normals[index[j]].z();
            for (const fit_kernels::Kernels* k : {&fit_kernels::Baseline(), &fit_kernels::Best()}) {
                std::vector<float> w = w0;
                k->normal_factors(nx.data(), ny.data(), nz.data(), n, r, inv, w.data());
                for (std::size_t j = 0; j < n; ++j)  // (a NaN's sign depends on the operand order)
                    ASSERT_TRUE(std::memcmp(&w[j], &want[j], sizeof(float)) == 0 || (std::isnan(w[j]) && std::isnan(want[j])))
                        << k->isa << " sigma " << sigma << " j = " << j << ": " << w[j] << " vs " << want[j];
            }
        }
    RecordProperty("normal_factors_vectorised", fit_kernels::NormalFactorsVectorised() ? "yes" : "no");
}

// The adaptive scales' weights exp(-d^2 inv) in double: both builds give std::exp's bits, on
// arguments over the smoothing's range (d^2 inv in [0, 4]) and beyond, on sizes below, at and above
// the vector width, and on the lanes glibc's fast path leaves (d^2 = 0, |x| < 2^-54, |x| >= 512,
// infinity, NaN), which take the C library's exp.
TEST(FitKernels, GaussWeightsDAreExpToTheBit) {
    std::mt19937 rng(31);
    std::uniform_real_distribution<float> unit(0.0f, 1.0f);
    const std::size_t count = std::size_t(1) << 21;
    std::vector<float> d2(count);
    for (std::size_t j = 0; j < count; ++j) d2[j] = j % 7 == 6 ? 30.0f * unit(rng) : 4.0f * unit(rng);
    const float specials[] = {0.0f, 1e-30f, 1e-20f, 1e-17f, 600.0f, 1e30f, std::numeric_limits<float>::infinity(),
                              std::nanf(""), 5e-17f};
    for (std::size_t j = 0; j < std::size(specials); ++j) d2[1000 + 5 * j] = specials[j];
    for (const float inv : {1.0f, 0.37f, 2.5f, 1.0f / 3.0f})
        for (const std::size_t n : {std::size_t(0), std::size_t(3), std::size_t(4), std::size_t(110), count}) {
            std::vector<double> want(n);
            for (std::size_t j = 0; j < n; ++j) want[j] = std::exp(-double(d2[j]) * inv);
            for (const fit_kernels::Kernels* k : {&fit_kernels::Baseline(), &fit_kernels::Best()}) {
                std::vector<double> w(n, -1.0);
                k->gauss_weights_d(d2.data(), inv, w.data(), n);
                for (std::size_t j = 0; j < n; ++j)
                    ASSERT_TRUE(std::memcmp(&w[j], &want[j], sizeof(double)) == 0 || (std::isnan(w[j]) && std::isnan(want[j])))
                        << k->isa << " inv " << inv << " d2 " << d2[j] << ": " << w[j] << " vs " << want[j];
            }
        }
    RecordProperty("gauss_weights_d_vectorised", fit_kernels::GaussWeightsDVectorised() ? "yes" : "no");
}

// The gather's filter: both builds keep the same candidates, in order, with the offsets and
// distances of NeighborBatch::PushWithin (the float test of the grid walk) to the bit; the
// superset's (SelectWithin) keeps the same candidates as points.
TEST(FitKernels, GatherWithinIsPushWithinToTheBit) {
    std::mt19937 rng(41);
    std::uniform_real_distribution<float> pos(-0.01f, 0.01f);
    for (const std::size_t n : {std::size_t(0), std::size_t(3), std::size_t(8), std::size_t(9), std::size_t(261),
                                std::size_t(2000)}) {
        std::vector<Vec3f> pts(n);
        std::vector<std::uint32_t> idx(n);
        std::vector<float> X(n), Y(n), Z(n);
        for (std::size_t j = 0; j < n; ++j) {
            pts[j] = Vec3f(pos(rng), pos(rng), pos(rng));
            X[j] = pts[j].x(), Y[j] = pts[j].y(), Z[j] = pts[j].z();
            idx[j] = std::uint32_t(7 * j + 3);
        }
        const Vec3f o(0.001f, -0.002f, 0.0005f);
        const float r2 = 0.006f * 0.006f;
        NeighborBatch want;
        want.PushWithin(pts.data(), idx.data(), n, o, r2);
        for (const fit_kernels::Kernels* k : {&fit_kernels::Baseline(), &fit_kernels::Best()}) {
            std::vector<float> ox(n + 8), oy(n + 8), oz(n + 8), od(n + 8);
            std::vector<std::uint32_t> oi(n + 8);
            // Three attributes carried along: the points' x, y, z again, times 2, 3, 4.
            std::vector<float> c0(n), c1(n), c2(n), g0(n + 8), g1(n + 8), g2(n + 8), s0(n + 8), s1(n + 8), s2(n + 8);
            for (std::size_t j = 0; j < n; ++j) c0[j] = 2 * X[j], c1[j] = 3 * Y[j], c2[j] = 4 * Z[j];
            const float* const carry[3] = {c0.data(), c1.data(), c2.data()};
            float* const gout[3] = {g0.data(), g1.data(), g2.data()};
            float* const sout[3] = {s0.data(), s1.data(), s2.data()};
            const std::size_t m = k->gather_within(X.data(), Y.data(), Z.data(), idx.data(), carry, n, o.x(), o.y(),
                                                   o.z(), r2, ox.data(), oy.data(), oz.data(), od.data(), oi.data(), gout);
            ASSERT_EQ(k->gather_within(X.data(), Y.data(), Z.data(), idx.data(), nullptr, n, o.x(), o.y(), o.z(), r2,
                                       ox.data(), oy.data(), oz.data(), od.data(), oi.data(), nullptr),
                      m);
            ASSERT_EQ(m, want.size()) << k->isa << " n = " << n;
            std::vector<float> px(n + 8), py(n + 8), pz(n + 8);
            std::vector<std::uint32_t> pi(n + 8);
            const std::size_t ms = k->select_within(X.data(), Y.data(), Z.data(), idx.data(), carry, n, o.x(), o.y(),
                                                    o.z(), r2, px.data(), py.data(), pz.data(), pi.data(), sout);
            ASSERT_EQ(ms, m) << k->isa << " n = " << n;
            for (std::size_t j = 0; j < m; ++j) {
                ASSERT_EQ(pi[j], want.index[j]) << k->isa << " j = " << j;
                const std::size_t src = (want.index[j] - 3) / 7;
                ASSERT_EQ(px[j], X[src]);
                ASSERT_EQ(py[j], Y[src]);
                ASSERT_EQ(pz[j], Z[src]);
                ASSERT_EQ(g0[j], c0[src]);
                ASSERT_EQ(g1[j], c1[src]);
                ASSERT_EQ(g2[j], c2[src]);
                ASSERT_EQ(s0[j], c0[src]);
                ASSERT_EQ(s1[j], c1[src]);
                ASSERT_EQ(s2[j], c2[src]);
            }
            for (std::size_t j = 0; j < m; ++j) {
                ASSERT_EQ(ox[j], want.x[j]) << k->isa << " j = " << j;
                ASSERT_EQ(oy[j], want.y[j]) << k->isa << " j = " << j;
                ASSERT_EQ(oz[j], want.z[j]) << k->isa << " j = " << j;
                ASSERT_EQ(od[j], want.d2[j]) << k->isa << " j = " << j;
                ASSERT_EQ(oi[j], want.index[j]) << k->isa << " j = " << j;
            }
        }
    }
}

// The 6x6 solve of the degree-2 fits: Eigen::LDLT's D, success and solution to the bit, on the
// normal equations of random weighted samples (3 to 120 of them: singular ones included), with
// PolyFit's acceptance (info() == Success and a conditioned D) deciding which solutions count.
TEST(FitKernels, SolveLdlt6IsEigensLdltToTheBit) {
    std::mt19937_64 rng(3);
    std::normal_distribution<double> g;
    int compared = 0;
    for (int it = 0; it < 20000; ++it) {
        Eigen::Matrix<double, 6, 6> M = Eigen::Matrix<double, 6, 6>::Zero();
        Eigen::Matrix<double, 6, 1> b = Eigen::Matrix<double, 6, 1>::Zero();
        const int n = 3 + it % 118;
        const double scale = it % 3 == 0 ? 4.0 : 1.0;  // the 1/h-scaled coordinates reach a few units
        for (int j = 0; j < n; ++j) {
            const double x = scale * g(rng), y = g(rng), w = std::abs(g(rng)), z = 0.1 * g(rng);
            Eigen::Matrix<double, 6, 1> t;
            t << 1, x, y, x * x, x * y, y * y;
            M += w * t * t.transpose();
            b += w * z * t;
        }
        const Eigen::LDLT<Eigen::Matrix<double, 6, 6>> ldlt(M);
        const Eigen::Matrix<double, 6, 1> want_d = ldlt.vectorD();
        double x[6], d[6];
        const bool ok = SolveLdlt6(M.data(), b.data(), x, d);
        ASSERT_EQ(ok, ldlt.info() == Eigen::Success) << "case " << it;
        ASSERT_EQ(std::memcmp(d, want_d.data(), sizeof d), 0) << "case " << it;
        if (!ok) continue;
        const double mx = want_d.cwiseAbs().maxCoeff(), mn = want_d.minCoeff();
        if (!(mn > 1e-10 * mx && mx > 0)) continue;
        const Eigen::Matrix<double, 6, 1> want = ldlt.solve(b);
        ASSERT_EQ(std::memcmp(x, want.data(), sizeof x), 0) << "case " << it;
        ++compared;
    }
    EXPECT_GT(compared, 15000);
}

}  // namespace
}  // namespace surfel
