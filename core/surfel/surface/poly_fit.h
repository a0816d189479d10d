#pragma once
/// \file
/// Local frames and weighted least-squares bivariate polynomials over them: the shared pieces of
/// MLS projection (notes eq. 1.3) and the Adamson-Alexa iteration (paper eq. 10).

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <algorithm>
#include <bit>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/surface/ldlt6.h"

namespace surfel {

/// w[i] = exp(-d2[i] * inv_h2) for n weights at once, in single precision (Cephes' expf:
/// Cody-Waite reduction, degree-6 polynomial; relative error below 3e-7). Written so that the
/// compiler vectorises it (-fopenmp-simd): the per-neighbour exponential was the largest single
/// cost of the surface fits. Arguments below -87 are clamped (weight ~1.6e-38, not 0).
inline void GaussWeights(const float* d2, float inv_h2, float* w, std::size_t n) {
#pragma omp simd
    for (std::size_t i = 0; i < n; ++i) {
        const float e = -d2[i] * inv_h2;
        const float a = e > -87.0f ? e : -87.0f;
        const float r = (a * 1.44269504f + 12582912.0f) - 12582912.0f;  // round(a / ln 2)
        const float y = a - r * 0.693359375f + r * 2.12194440e-4f;     // a - r ln 2, in two parts
        float p = 1.9875691500e-4f;
        p = p * y + 1.3981999507e-3f;
        p = p * y + 8.3334519073e-3f;
        p = p * y + 4.1665795894e-2f;
        p = p * y + 1.6666665459e-1f;
        p = p * y + 5.0000001201e-1f;
        p = p * (y * y) + y + 1.0f;
        const std::int32_t bits = (static_cast<std::int32_t>(r) + 127) * (1 << 23);
        w[i] = p * std::bit_cast<float>(bits);
    }
}

/// The neighbours of one surface evaluation as arrays (structure of arrays, so the kernels
/// vectorise), kept per thread and reused: no allocation once grown.
struct NeighborBatch {
    std::vector<float> x, y, z;      ///< p_j - o in world axes, o the gather's origin (a float point).
    std::vector<double> lx, ly, lz;  ///< Local frame coordinates (filled by ToLocal).
    std::vector<float> d2, w;        ///< Squared distance to the centre of the weights; weight.
    std::vector<std::uint32_t> index;

    std::size_t size() const { return n_; }
    void clear() { n_ = 0; }
    /// Makes room for `count` entries (the arrays' size; existing entries are kept), for callers
    /// that write x, y, z, d2, index directly and then set the count with Resize().
    void Reserve(std::size_t count) {
        while (count > index.size()) Grow();
    }
    /// Sets the number of entries (at most the room Reserve made).
    void Resize(std::size_t count) { n_ = count; }
    /// Appends point i at offset d from the origin.
    void Push(std::uint32_t i, const Vec3f& d) {
        if (n_ == index.size()) Grow();
        x[n_] = d.x();
        y[n_] = d.y();
        z[n_] = d.z();
        d2[n_] = d.squaredNorm();
        index[n_] = i;
        ++n_;
    }
    /// Appends the points pts[0..count) (indices idx) that lie within sqrt(r2) of the origin o,
    /// as offsets p - o, with ForEachWithin's float distance test. Branch-free: every candidate
    /// is written and the count advances only for those inside, so the unpredictable in/out
    /// test costs no mispredictions. Offsets of a few h are exact to float rounding of p - o
    /// (relative 6e-8), far below any fit's precision; the kernels sum them in double.
    void PushWithin(const Vec3f* pts, const std::uint32_t* idx, std::size_t count, const Vec3f& o, float r2) {
        while (n_ + count > index.size()) Grow();
        std::size_t n = n_;
        float *X = x.data(), *Y = y.data(), *Z = z.data(), *D = d2.data();
        std::uint32_t* I = index.data();
        for (std::size_t j = 0; j < count; ++j) {
            const Vec3f e = pts[j] - o;
            const float df = e.squaredNorm();
            X[n] = e.x();
            Y[n] = e.y();
            Z[n] = e.z();
            D[n] = df;
            I[n] = idx[j];
            n += df <= r2 ? 1 : 0;
        }
        n_ = n;
    }
    /// d2 relative to centre c (in the same coordinates as x, y, z), then w = exp(-d2 / h^2).
    void WeightsAround(const Vec3d& c, double h) {
        const std::size_t n = size();
        const double cx = c.x(), cy = c.y(), cz = c.z();
        float* D = d2.data();
        const float *X = x.data(), *Y = y.data(), *Z = z.data();
#pragma omp simd
        for (std::size_t i = 0; i < n; ++i) {
            const double ex = X[i] - cx, ey = Y[i] - cy, ez = Z[i] - cz;
            D[i] = static_cast<float>(ex * ex + ey * ey + ez * ez);
        }
        GaussWeights(D, static_cast<float>(1.0 / (h * h)), w.data(), n);
    }
    /// Weights from the stored d2 (relative to the point the batch was gathered around).
    void Weights(double h) {
        GaussWeights(d2.data(), static_cast<float>(1.0 / (h * h)), w.data(), size());
    }
    /// Per-point scales (AaBandwidth::kAdaptive): w_j = exp(-d2_j * inv_h2[index_j]), and 0 where
    /// d2_j * inv_h2[index_j] > cut2 (each point's own cutoff, so the weights do not depend on the
    /// gather's radius as long as it reaches every point's cutoff). `gauss` computes the
    /// exponentials: GaussWeights, or the run-time picked kernel of the same bits (fit_kernels.h).
    void WeightsPerPoint(const float* inv_h2, float cut2,
                         void (*gauss)(const float*, float, float*, std::size_t) = GaussWeights) {
        const std::size_t n = size();
        float* T = scaled.data();
        const float* D = d2.data();
        const std::uint32_t* I = index.data();
        for (std::size_t i = 0; i < n; ++i) T[i] = D[i] * inv_h2[I[i]];
        gauss(T, 1.0f, w.data(), n);
        float* W = w.data();
#pragma omp simd
        for (std::size_t i = 0; i < n; ++i) W[i] = T[i] <= cut2 ? W[i] : 0.0f;
    }
    /// lx, ly, lz = coordinates of (x, y, z) - o along the axes u, v, n.
    void ToLocal(const Vec3d& o, const Vec3d& u, const Vec3d& v, const Vec3d& nrm) {
        const std::size_t n = size();
        const float *X = x.data(), *Y = y.data(), *Z = z.data();
        double *LX = lx.data(), *LY = ly.data(), *LZ = lz.data();
        const double ox = o.x(), oy = o.y(), oz = o.z();
#pragma omp simd
        for (std::size_t i = 0; i < n; ++i) {
            const double ex = X[i] - ox, ey = Y[i] - oy, ez = Z[i] - oz;
            LX[i] = ex * u.x() + ey * u.y() + ez * u.z();
            LY[i] = ex * v.x() + ey * v.y() + ez * v.z();
            LZ[i] = ex * nrm.x() + ey * nrm.y() + ez * nrm.z();
        }
    }

private:
    void Grow() {
        const std::size_t cap = std::max<std::size_t>(256, 2 * index.size());
        for (auto* v : {&x, &y, &z}) v->resize(cap);
        for (auto* v : {&lx, &ly, &lz}) v->resize(cap);
        d2.resize(cap);
        w.resize(cap);
        scaled.resize(cap);
        index.resize(cap);
    }
    std::vector<float> scaled;  // scratch of WeightsPerPoint
    std::size_t n_ = 0;
};

/// sum w_j n_j of the cloud's normals over a batch: the orientation reference of a fit (zero when
/// the cloud has no normals).
inline Vec3d WeightedNormal(const PointCloud& cloud, const NeighborBatch& nb) {
    Vec3d sum = Vec3d::Zero();
    if (cloud.has_normals())
        for (std::size_t j = 0; j < nb.size(); ++j) sum += double(nb.w[j]) * cloud.normals[nb.index[j]].cast<double>();
    return sum;
}

/// Weighted sums for a covariance: sum w, sum w d, sum w d d^T (upper triangle) over a batch.
struct WeightedMoments {
    double w = 0, x = 0, y = 0, z = 0, xx = 0, xy = 0, xz = 0, yy = 0, yz = 0, zz = 0;

    static WeightedMoments Of(const NeighborBatch& b) {
        double w = 0, x = 0, y = 0, z = 0, xx = 0, xy = 0, xz = 0, yy = 0, yz = 0, zz = 0;
        const float *X = b.x.data(), *Y = b.y.data(), *Z = b.z.data();
        const float* W = b.w.data();
        const std::size_t n = b.size();
#pragma omp simd reduction(+ : w, x, y, z, xx, xy, xz, yy, yz, zz)
        for (std::size_t i = 0; i < n; ++i) {
            const double xi = X[i], yi = Y[i], zi = Z[i];
            const double wi = W[i], wx = wi * xi, wy = wi * yi, wz = wi * zi;
            w += wi;
            x += wx;
            y += wy;
            z += wz;
            xx += wx * xi;
            xy += wx * yi;
            xz += wx * zi;
            yy += wy * yi;
            yz += wy * zi;
            zz += wz * zi;
        }
        return {w, x, y, z, xx, xy, xz, yy, yz, zz};
    }
    /// sum w d d^T (second moments about the origin of the batch's coordinates).
    Eigen::Matrix3d Second() const {
        Eigen::Matrix3d m;
        m << xx, xy, xz, xy, yy, yz, xz, yz, zz;
        return m;
    }
};

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
    void Add(double x, double y, double z, double w) { AddBatch(&x, &y, &z, &w, 1); }
    /// Add() for n samples at once (vectorised): local coordinates x, y, z and weights w.
    template <typename Weight>
    void AddBatch(const double* x, const double* y, const double* z, const Weight* w, std::size_t n) {
        const double ih = inv_h_;
        double m0 = 0, m1 = 0, m2 = 0, m3 = 0, m4 = 0, m5 = 0, m6 = 0, m7 = 0, m8 = 0, m9 = 0, m10 = 0, m11 = 0,
               m12 = 0, m13 = 0, m14 = 0, b0 = 0, b1 = 0, b2 = 0, b3 = 0, b4 = 0, b5 = 0;
#pragma omp simd reduction(+ : m0, m1, m2, m3, m4, m5, m6, m7, m8, m9, m10, m11, m12, m13, m14, b0, b1, b2, b3, b4, b5)
        for (std::size_t i = 0; i < n; ++i) {
            const double xs = x[i] * ih, ys = y[i] * ih, wi = w[i], zi = z[i];
            const double wx = wi * xs, wy = wi * ys;
            const double wxx = wx * xs, wxy = wx * ys, wyy = wy * ys;
            m0 += wi;
            m1 += wx;
            m2 += wy;
            m3 += wxx;
            m4 += wxy;
            m5 += wyy;
            m6 += wxx * xs;
            m7 += wxx * ys;
            m8 += wxy * ys;
            m9 += wyy * ys;
            m10 += wxx * xs * xs;
            m11 += wxx * xs * ys;
            m12 += wxx * ys * ys;
            m13 += wxy * ys * ys;
            m14 += wyy * ys * ys;
            b0 += wi * zi;
            b1 += wx * zi;
            b2 += wy * zi;
            b3 += wxx * zi;
            b4 += wxy * zi;
            b5 += wyy * zi;
        }
        const double m[15] = {m0, m1, m2, m3, m4, m5, m6, m7, m8, m9, m10, m11, m12, m13, m14};
        for (int k = 0; k < 15; ++k) mom_[k] += m[k];
        b_[0] += b0;
        b_[1] += b1;
        b_[2] += b2;
        b_[3] += b3;
        b_[4] += b4;
        b_[5] += b5;
        wsum_ += m0;
    }
    /// Adds sums computed elsewhere, in AddBatch's order: the 15 moments s[0..14], then the 6
    /// right-hand sides s[15..20] (surfel/surface/fit_kernels.h's PolySums, with ih = inv_h()).
    void AddSums(const double* s) {
        for (int k = 0; k < 15; ++k) mom_[k] += s[k];
        for (int k = 0; k < 6; ++k) b_[k] += s[15 + k];
        wsum_ += s[0];
    }
    /// 1 / h: the scale of the local coordinates in the sums.
    double inv_h() const { return inv_h_; }
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
            if (terms == 6) {  // Eigen::LDLT's result to the bit, without its generic code (ldlt6.h)
                Eigen::Matrix<double, 6, 1> d;
                if (!SolveLdlt6(M.data(), b_.data(), sol.data(), d.data()) || !Conditioned(d)) continue;
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
