#pragma once
/// \file
/// A 6x6 symmetric solve (the degree-2 normal equations of PolyFit, eq. 10 of Adamson & Alexa)
/// that gives Eigen 3.4's `Eigen::LDLT<Matrix<double, 6, 6>>(A).solve(b)` to the bit, without
/// its dynamic-size blocks: the same diagonal pivoting, the same products and sums in the same
/// order (the factor's inner products and its matrix-vector update summed left to right, the
/// unit-lower solve's row sums split in halves as Eigen's unrolled reductions do, the
/// transposed solve's contiguous sums in SSE2 pairs as Eigen's vectorised reductions on the
/// x86-64 baseline). The render's fits spent ~7 % of their time in Eigen's generic code here.
/// tests/unit/surface/test_fit_kernels.cpp compares it with Eigen on random systems.

#include <cmath>
#include <limits>
#include <utility>  // std::swap, std::integer_sequence

namespace surfel {

namespace ldlt6_detail {
// Eigen's unrolled reduction of a fixed-size sum: the first half plus the second half.
inline double HalfSum(const double* p, int n) {
    if (n == 1) return p[0];
    const int h = n / 2;
    return HalfSum(p, h) + HalfSum(p + h, n - h);
}
// The same over pairs (one SSE2 packet each), lanes added at the end, then the odd last term.
inline void PairSums(const double* p, int start, int len, double* a, double* b) {
    if (len == 1) {
        *a = p[2 * start], *b = p[2 * start + 1];
        return;
    }
    const int h = len / 2;
    double a1, b1, a2, b2;
    PairSums(p, start, h, &a1, &b1);
    PairSums(p, start + h, len - h, &a2, &b2);
    *a = a1 + a2, *b = b1 + b2;
}
inline double PacketSum(const double* p, int n) {
    const int pairs = n / 2;
    if (pairs == 0) return HalfSum(p, n);
    double a, b;
    PairSums(p, 0, pairs, &a, &b);
    double s = a + b;
    if (2 * pairs != n) s = s + HalfSum(p + 2 * pairs, n - 2 * pairs);
    return s;
}
}  // namespace ldlt6_detail

/// Solves A x = b for a symmetric 6x6 A (column-major, both triangles; only the lower is read)
/// as Eigen::LDLT does. `d` receives the factor's diagonal D (Eigen's vectorD()). Returns false
/// where Eigen's info() is not Success (a zero pivot followed by a non-zero one) or the diagonal
/// is all zero (D = 0); x is then unset. x is computed whenever it returns true,
/// also for a D the caller will reject.
inline bool SolveLdlt6(const double* A, const double* b, double* x, double* d) {
    using ldlt6_detail::HalfSum;
    using ldlt6_detail::PacketSum;
    double m[6][6];  // m[column][row]
    for (int c = 0; c < 6; ++c)
        for (int r = 0; r < 6; ++r) m[c][r] = A[c * 6 + r];
    int transposition[6];
    bool ok = true, found_zero = false;
    double temp[6];
    // One step of the factorisation per column k, k a constant (the loops inside unroll).
    const auto step = [&]<int k>() -> bool {
        // The largest remaining diagonal element (the first of equals) moves to k.
        int big = k;
        double biggest = std::abs(m[k][k]);
        for (int i = k + 1; i < 6; ++i)
            if (std::abs(m[i][i]) > biggest) biggest = std::abs(m[i][i]), big = i;
        transposition[k] = big;
        if (big != k) {
            for (int j = 0; j < k; ++j) std::swap(m[j][k], m[j][big]);
            for (int i = big + 1; i < 6; ++i) std::swap(m[k][i], m[big][i]);
            std::swap(m[k][k], m[big][big]);
            for (int i = k + 1; i < big; ++i) {
                const double t = m[k][i];
                m[k][i] = m[i][big];
                m[i][big] = t;
            }
        }
        if constexpr (k > 0) {
            for (int j = 0; j < k; ++j) temp[j] = m[j][j] * m[j][k];
            double s = m[0][k] * temp[0];
            for (int j = 1; j < k; ++j) s = s + m[j][k] * temp[j];
            m[k][k] -= s;
            for (int i = k + 1; i < 6; ++i) {  // Eigen's gemv: res + (-1) (sum_j a_ij temp_j)
                double c = 0;
                for (int j = 0; j < k; ++j) c = m[j][i] * temp[j] + c;
                m[k][i] = c * -1.0 + m[k][i];
            }
        }
        const double akk = m[k][k];
        const bool valid = std::abs(akk) > 0;
        if (k == 0 && !valid) {  // an all-zero diagonal (Eigen: D = 0, which every caller rejects)
            for (int j = 0; j < 6; ++j) d[j] = m[j][j];
            return false;
        }
        if constexpr (k < 5) {
            if (valid)
                for (int i = k + 1; i < 6; ++i) m[k][i] /= akk;
            else
                for (int i = k + 1; i < 6; ++i) ok = ok && m[k][i] == 0;
        }
        if (found_zero && valid) ok = false;
        else if (!valid) found_zero = true;
        return true;
    };
    const bool nonzero = [&]<int... K>(std::integer_sequence<int, K...>) {
        return (step.template operator()<K>() && ...);
    }(std::make_integer_sequence<int, 6>{});
    if (!nonzero) return false;  // an all-zero diagonal: d was written
    for (int j = 0; j < 6; ++j) d[j] = m[j][j];
    if (!ok) return false;
    double y[6];
    for (int i = 0; i < 6; ++i) y[i] = b[i];
    for (int k = 0; k < 6; ++k)
        if (transposition[k] != k) std::swap(y[k], y[transposition[k]]);
    double p[6];
    for (int i = 1; i < 6; ++i) {  // L y = P b (unit lower; L's rows are strided: unrolled halves)
        for (int j = 0; j < i; ++j) p[j] = m[j][i] * y[j];
        y[i] -= HalfSum(p, i);
    }
    for (int i = 0; i < 6; ++i) y[i] = std::abs(m[i][i]) > std::numeric_limits<double>::min() ? y[i] / m[i][i] : 0.0;
    for (int i = 4; i >= 0; --i) {  // L^T x = D^-1 y (L^T's rows are L's columns: SSE2 pairs)
        const int n = 5 - i;
        for (int t = 0; t < n; ++t) p[t] = m[i][i + 1 + t] * y[i + 1 + t];
        y[i] -= PacketSum(p, n);
    }
    for (int k = 5; k >= 0; --k)
        if (transposition[k] != k) std::swap(y[k], y[transposition[k]]);
    for (int i = 0; i < 6; ++i) x[i] = y[i];
    return true;
}

}  // namespace surfel
