#pragma once
/// \file
/// Local frames and weighted least-squares bivariate polynomials over them: the shared pieces of
/// MLS projection (notes eq. 1.3) and the Adamson-Alexa iteration (paper eq. 10).

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <cmath>

#include "surfel/base/point_cloud.h"

namespace surfel {

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
        M_.setZero();
        b_.setZero();
    }
    void Add(double x, double y, double z, double w) {
        const double xs = x * inv_h_, ys = y * inv_h_;
        Eigen::Matrix<double, 6, 1> t;
        t << 1.0, xs, ys, xs * xs, xs * ys, ys * ys;
        M_.noalias() += w * t * t.transpose();
        b_.noalias() += (w * z) * t;
        wsum_ += w;
    }
    double weight_sum() const { return wsum_; }
    /// Solves; falls back to lower degrees when the system is singular. False when even the
    /// constant fit has no weight.
    bool Solve(PolyCoeffs* out) const {
        for (int terms = terms_; terms >= 1; terms = terms == 6 ? 3 : terms == 3 ? 1 : 0) {
            Eigen::Matrix<double, 6, 1> sol = Eigen::Matrix<double, 6, 1>::Zero();
            if (terms == 6) {
                Eigen::LDLT<Eigen::Matrix<double, 6, 6>> s(M_);
                if (s.info() != Eigen::Success || !Conditioned(s.vectorD())) continue;
                sol = s.solve(b_);
            } else if (terms == 3) {
                Eigen::LDLT<Eigen::Matrix3d> s(M_.topLeftCorner<3, 3>());
                if (s.info() != Eigen::Success || !Conditioned(s.vectorD())) continue;
                sol.head<3>() = s.solve(b_.head<3>());
            } else {
                if (!(M_(0, 0) > 1e-300)) return false;
                sol[0] = b_[0] / M_(0, 0);
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
    Eigen::Matrix<double, 6, 6> M_;
    Eigen::Matrix<double, 6, 1> b_;
};

}  // namespace surfel
