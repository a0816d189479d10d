#pragma once
/// \file
/// Local frames and weighted least-squares bivariate polynomials over them: the shared pieces of
/// MLS projection (notes eq. 1.3) and the Adamson-Alexa iteration (paper eq. 10).

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "surfel/base/point_cloud.h"

namespace surfel {

/// e^a for the Gaussian weights theta = exp(-d^2 / h^2) (a <= 0), relative error below 1e-8:
/// a = n ln 2 + y with |y| <= ln2 / 2, e^y by its degree-7 Taylor polynomial, 2^n by the
/// exponent bits. About 4x faster than std::exp, which dominated MLS projection.
inline double GaussExp(double a) {
    if (a < -700.0) return 0.0;
    const double t = a * 1.4426950408889634;                          // a / ln 2
    const double r = (t + 6755399441055744.0) - 6755399441055744.0;  // round to nearest
    const double y = (t - r) * 0.6931471805599453;                    // |y| <= ln2 / 2
    double p = 1.0 / 5040.0;
    p = p * y + 1.0 / 720.0;
    p = p * y + 1.0 / 120.0;
    p = p * y + 1.0 / 24.0;
    p = p * y + 1.0 / 6.0;
    p = p * y + 0.5;
    p = p * y + 1.0;
    p = p * y + 1.0;
    const std::int64_t bits = (static_cast<std::int64_t>(r) + 1023) << 52;
    double scale;
    std::memcpy(&scale, &bits, sizeof scale);
    return p * scale;
}

/// An orthonormal frame: origin, tangents u and v, normal n (right-handed).
struct LocalFrame {
    Vec3d origin, u, v, n;

    static LocalFrame FromNormal(const Vec3d& origin, const Vec3d& normal) {
        LocalFrame f;
        f.origin = origin;
        f.n = normal.normalized();
        const Vec3d a = std::abs(f.n.x()) < 0.9 ? Vec3d::UnitX() : Vec3d::UnitY();
        f.u = f.n.cross(a).normalized();
        f.v = f.n.cross(f.u);
        return f;
    }
    /// (x, y, height) of a world point.
    Vec3d ToLocal(const Vec3d& p) const {
        const Vec3d d = p - origin;
        return {d.dot(u), d.dot(v), d.dot(n)};
    }
    Vec3d ToWorld(double x, double y, double z) const { return origin + x * u + y * v + z * n; }
    /// Direction to local coordinates.
    Vec3d DirToLocal(const Vec3d& d) const { return {d.dot(u), d.dot(v), d.dot(n)}; }

    /// Unit normal of the graph z = g(x, y) at (x, y), in world coordinates (on the +n side).
    template <typename Coeffs>
    Vec3d NormalAt(const Coeffs& g, double x, double y) const {
        const double gx = g.Dx(x, y), gy = g.Dy(x, y);
        return (n - gx * u - gy * v).normalized();
    }
};

/// Coefficients of g(x, y) = c0 + c1 x + c2 y + c3 x^2 + c4 x y + c5 y^2 (unused ones are 0),
/// in unscaled local units.
struct PolyCoeffs {
    double c[6] = {0, 0, 0, 0, 0, 0};
    double operator()(double x, double y) const {
        return c[0] + c[1] * x + c[2] * y + c[3] * x * x + c[4] * x * y + c[5] * y * y;
    }
    double Dx(double x, double y) const { return c[1] + 2 * c[3] * x + c[4] * y; }
    double Dy(double x, double y) const { return c[2] + c[4] * x + 2 * c[5] * y; }
};

/// Accumulates the weighted normal equations of a degree 0, 1 or 2 bivariate fit. Local
/// coordinates are scaled by 1/h for conditioning. Fixed-size: no heap allocation.
class PolyFit {
public:
    PolyFit(int degree, double h) : inv_h_(1.0 / h) {
        terms_ = degree == 0 ? 1 : degree == 1 ? 3 : 6;
        b_.setZero();
    }
    /// Adds sample (x, y) with height z and weight w. Accumulates the 15 distinct moments
    /// sum w x^a y^b (a + b <= 4) the normal matrix is made of, not the matrix itself.
    void Add(double x, double y, double z, double w) {
        const double xs = x * inv_h_, ys = y * inv_h_;
        const double wx = w * xs, wy = w * ys;
        const double wxx = wx * xs, wxy = wx * ys, wyy = wy * ys;
        double* m = mom_;
        m[0] += w;
        m[1] += wx;
        m[2] += wy;
        m[3] += wxx;
        m[4] += wxy;
        m[5] += wyy;
        m[6] += wxx * xs;   // x^3
        m[7] += wxx * ys;   // x^2 y
        m[8] += wxy * ys;   // x y^2
        m[9] += wyy * ys;   // y^3
        m[10] += wxx * xs * xs;  // x^4
        m[11] += wxx * xs * ys;  // x^3 y
        m[12] += wxx * ys * ys;  // x^2 y^2
        m[13] += wxy * ys * ys;  // x y^3
        m[14] += wyy * ys * ys;  // y^4
        b_[0] += w * z;
        b_[1] += wx * z;
        b_[2] += wy * z;
        b_[3] += wxx * z;
        b_[4] += wxy * z;
        b_[5] += wyy * z;
        wsum_ += w;
    }
    double weight_sum() const { return wsum_; }
    /// Solves; falls back to lower degrees when the system is singular. False when even the
    /// constant fit has no weight.
    bool Solve(PolyCoeffs* out) const {
        // The normal matrix M(i, j) = sum w t_i t_j from the moments, t = (1, x, y, x^2, xy, y^2).
        static constexpr int kMoment[6][6] = {{0, 1, 2, 3, 4, 5},     {1, 3, 4, 6, 7, 8},
                                              {2, 4, 5, 7, 8, 9},     {3, 6, 7, 10, 11, 12},
                                              {4, 7, 8, 11, 12, 13},  {5, 8, 9, 12, 13, 14}};
        Eigen::Matrix<double, 6, 6> M;
        for (int i = 0; i < 6; ++i)
            for (int j = 0; j < 6; ++j) M(i, j) = mom_[kMoment[i][j]];
        for (int terms = terms_; terms >= 1; terms = terms == 6 ? 3 : terms == 3 ? 1 : 0) {
            Eigen::Matrix<double, 6, 1> sol = Eigen::Matrix<double, 6, 1>::Zero();
            if (terms == 6) {
                Eigen::LDLT<Eigen::Matrix<double, 6, 6>> s(M);
                if (s.info() != Eigen::Success || !Conditioned(s.vectorD())) continue;
                sol = s.solve(b_);
            } else if (terms == 3) {
                Eigen::LDLT<Eigen::Matrix3d> s(M.topLeftCorner<3, 3>());
                if (s.info() != Eigen::Success || !Conditioned(s.vectorD())) continue;
                sol.head<3>() = s.solve(b_.head<3>());
            } else {
                if (!(M(0, 0) > 1e-300)) return false;
                sol[0] = b_[0] / M(0, 0);
            }
            if (!sol.allFinite()) continue;
            const double ih = inv_h_;
            out->c[0] = sol[0];
            out->c[1] = sol[1] * ih;
            out->c[2] = sol[2] * ih;
            out->c[3] = sol[3] * ih * ih;
            out->c[4] = sol[4] * ih * ih;
            out->c[5] = sol[5] * ih * ih;
            return true;
        }
        return false;
    }

private:
    template <typename D>
    static bool Conditioned(const D& d) {
        const double mx = d.cwiseAbs().maxCoeff(), mn = d.minCoeff();
        return mn > 1e-10 * mx && mx > 0;
    }
    int terms_;
    double inv_h_;
    double wsum_ = 0;
    double mom_[15] = {};
    Eigen::Matrix<double, 6, 1> b_;
};

}  // namespace surfel
