// The fits' weighted sums (surface/fit_kernels.h): both builds against sums in long double, on
// the sizes a fit sees (none, fewer than a vector, ~110 neighbours, many), and against each
// other. They add the same terms in another order, so they agree to rounding, not to the bit.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "surfel/surface/fit_kernels.h"

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

}  // namespace
}  // namespace surfel
