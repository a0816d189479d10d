// fit_kernels.inc for AVX2 (this file alone is compiled with -mavx2 -mno-fma -ffp-contract=off:
// see core/CMakeLists.txt). Only <cstddef>, <cstdint> and the intrinsics are included, so no
// inline function of a shared header is compiled for AVX2 here.
#include <cstddef>
#include <cstdint>
#include <immintrin.h>

#define SURFEL_FIT_ISA avx2
#include "surfel/surface/fit_kernels.inc"

namespace surfel::fit_kernels::avx2 {

namespace {

// glibc's expf (sysdeps/ieee754/flt-32/e_expf.c, __exp2f_data of e_exp2f_data.c with
// EXP2F_TABLE_BITS = 5), as its FMA build (__expf_fma, which glibc picks on a CPU with AVX2 and
// FMA) computes it: k = round(x N / ln 2), r = x N / ln 2 - k, exp(x) = 2^(k/N) (1 + C2 r + (C1 +
// C0 r) r^2), each step in double with the same fused operations, rounded to float once.
alignas(32) const std::uint64_t kExp2Table[32] = {
    0x3ff0000000000000, 0x3fefd9b0d3158574, 0x3fefb5586cf9890f, 0x3fef9301d0125b51, 0x3fef72b83c7d517b,
    0x3fef54873168b9aa, 0x3fef387a6e756238, 0x3fef1e9df51fdee1, 0x3fef06fe0a31b715, 0x3feef1a7373aa9cb,
    0x3feedea64c123422, 0x3feece086061892d, 0x3feebfdad5362a27, 0x3feeb42b569d4f82, 0x3feeab07dd485429,
    0x3feea47eb03a5585, 0x3feea09e667f3bcd, 0x3fee9f75e8ec5f74, 0x3feea11473eb0187, 0x3feea589994cce13,
    0x3feeace5422aa0db, 0x3feeb737b0cdc5e5, 0x3feec49182a3f090, 0x3feed503b23e255d, 0x3feee89f995ad3ad,
    0x3feeff76f2fb5e47, 0x3fef199bdd85529c, 0x3fef3720dcef9069, 0x3fef5818dcfba487, 0x3fef7c97337b9b5f,
    0x3fefa4afa2a490da, 0x3fefd0765b6e4540};
constexpr double kInvLn2N = 0x1.71547652b82fep+5;  // N / ln 2
constexpr double kShift = 0x1.8p+52;               // rounds to an integer when added
constexpr double kC0 = 0x1.c6af84b912394p-20, kC1 = 0x1.ebfce50fac4f3p-13, kC2 = 0x1.62e42ff0c52d6p-6;

// expf of four floats with |x| < 88 (glibc's fast path; the callers send the rest to expf).
__attribute__((target("avx2,fma"))) inline __m128 Exp4(__m128 x) {
    const __m256d xd = _mm256_cvtps_pd(x);
    const __m256d inv = _mm256_set1_pd(kInvLn2N), shift = _mm256_set1_pd(kShift);
    __m256d kd = _mm256_fmadd_pd(inv, xd, shift);
    const __m256i ki = _mm256_castpd_si256(kd);
    kd = _mm256_sub_pd(kd, shift);
    const __m256d r = _mm256_fmsub_pd(inv, xd, kd);
    const __m256i slot = _mm256_and_si256(ki, _mm256_set1_epi64x(31));
    __m256i t = _mm256_i64gather_epi64(reinterpret_cast<const long long*>(kExp2Table), slot, 8);
    t = _mm256_add_epi64(t, _mm256_slli_epi64(ki, 47));
    const __m256d s = _mm256_castsi256_pd(t);
    const __m256d z = _mm256_fmadd_pd(r, _mm256_set1_pd(kC0), _mm256_set1_pd(kC1));
    const __m256d r2 = _mm256_mul_pd(r, r);
    __m256d y = _mm256_fmadd_pd(r, _mm256_set1_pd(kC2), _mm256_set1_pd(1.0));
    y = _mm256_fmadd_pd(z, r2, y);
    y = _mm256_mul_pd(y, s);
    return _mm256_cvtpd_ps(y);
}

// Exp4 on eight floats, or expf lane by lane where one of them is outside glibc's fast path
// (|x| >= 88, NaN).
__attribute__((target("avx2,fma"))) inline __m256 Exp8(__m256 a) {
    const __m256i abs = _mm256_and_si256(_mm256_castps_si256(a), _mm256_set1_epi32(0x7fffffff));
    if (_mm256_movemask_epi8(_mm256_cmpgt_epi32(abs, _mm256_set1_epi32(0x42afffff))) != 0) {
        alignas(32) float v[8];
        _mm256_store_ps(v, a);
        for (float& e : v) e = __builtin_expf(e);
        return _mm256_load_ps(v);
    }
    const __m128 lo = Exp4(_mm256_castps256_ps128(a)), hi = Exp4(_mm256_extractf128_ps(a, 1));
    return _mm256_set_m128(hi, lo);
}

// The lanes of a left-pack: for each 8-bit mask, the positions of its set bits, in order.
struct PackTable {
    alignas(32) std::int32_t lanes[256][8];
    constexpr PackTable() : lanes{} {
        for (int m = 0; m < 256; ++m) {
            int k = 0;
            for (int l = 0; l < 8; ++l)
                if (m & (1 << l)) lanes[m][k++] = l;
            for (; k < 8; ++k) lanes[m][k] = 0;
        }
    }
};
constexpr PackTable kPack;

}  // namespace

// The filter of GatherWithin and SelectWithin eight candidates at a time: the distances as
// SquaredDistances, then the accepted lanes packed to the front (a permutation from kPack) and
// stored eight wide; `offsets`: store p - o (GatherWithin, with d2) or p (SelectWithin).
template <bool offsets>
std::size_t FilterPacked(const float* X, const float* Y, const float* Z, const std::uint32_t* I, const float* const* C,
                         std::size_t n, float ox, float oy, float oz, float r2, float* OX, float* OY, float* OZ,
                         float* OD, std::uint32_t* OI, float* const* OC) {
    const __m256 vx = _mm256_set1_ps(ox), vy = _mm256_set1_ps(oy), vz = _mm256_set1_ps(oz), vr = _mm256_set1_ps(r2);
    std::size_t j = 0, k = 0;
    for (; j + 8 <= n; j += 8) {
        const __m256 px = _mm256_loadu_ps(X + j), py = _mm256_loadu_ps(Y + j), pz = _mm256_loadu_ps(Z + j);
        const __m256 ex = _mm256_sub_ps(px, vx), ey = _mm256_sub_ps(py, vy), ez = _mm256_sub_ps(pz, vz);
        const __m256 d2 = _mm256_add_ps(_mm256_mul_ps(ex, ex), _mm256_add_ps(_mm256_mul_ps(ey, ey), _mm256_mul_ps(ez, ez)));
        const int mask = _mm256_movemask_ps(_mm256_cmp_ps(d2, vr, _CMP_LE_OQ));
        if (mask == 0) continue;
        const __m256i p = _mm256_load_si256(reinterpret_cast<const __m256i*>(kPack.lanes[mask]));
        _mm256_storeu_ps(OX + k, _mm256_permutevar8x32_ps(offsets ? ex : px, p));
        _mm256_storeu_ps(OY + k, _mm256_permutevar8x32_ps(offsets ? ey : py, p));
        _mm256_storeu_ps(OZ + k, _mm256_permutevar8x32_ps(offsets ? ez : pz, p));
        if (offsets) _mm256_storeu_ps(OD + k, _mm256_permutevar8x32_ps(d2, p));
        const __m256i idx = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(I + j));
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(OI + k), _mm256_permutevar8x32_epi32(idx, p));
        if (C)
            for (int c = 0; c < 3; ++c) _mm256_storeu_ps(OC[c] + k, _mm256_permutevar8x32_ps(_mm256_loadu_ps(C[c] + j), p));
        k += static_cast<std::size_t>(__builtin_popcount(static_cast<unsigned>(mask)));
    }
    const float* const tail_in[3] = {C ? C[0] + j : nullptr, C ? C[1] + j : nullptr, C ? C[2] + j : nullptr};
    float* const tail_out[3] = {C ? OC[0] + k : nullptr, C ? OC[1] + k : nullptr, C ? OC[2] + k : nullptr};
    if (offsets)
        return k + GatherWithin(X + j, Y + j, Z + j, I + j, C ? tail_in : nullptr, n - j, ox, oy, oz, r2, OX + k,
                                OY + k, OZ + k, OD + k, OI + k, tail_out);
    return k + SelectWithin(X + j, Y + j, Z + j, I + j, C ? tail_in : nullptr, n - j, ox, oy, oz, r2, OX + k, OY + k,
                            OZ + k, OI + k, tail_out);
}

std::size_t GatherWithinPacked(const float* X, const float* Y, const float* Z, const std::uint32_t* I,
                               const float* const* C, std::size_t n, float ox, float oy, float oz, float r2, float* OX,
                               float* OY, float* OZ, float* OD, std::uint32_t* OI, float* const* OC) {
    return FilterPacked<true>(X, Y, Z, I, C, n, ox, oy, oz, r2, OX, OY, OZ, OD, OI, OC);
}

std::size_t SelectWithinPacked(const float* X, const float* Y, const float* Z, const std::uint32_t* I,
                               const float* const* C, std::size_t n, float ox, float oy, float oz, float r2, float* OX,
                               float* OY, float* OZ, std::uint32_t* OI, float* const* OC) {
    return FilterPacked<false>(X, Y, Z, I, C, n, ox, oy, oz, r2, OX, OY, OZ, nullptr, OI, OC);
}

// NormalFactors eight at a time (the same operations in the same order, exp as Exp8).
__attribute__((target("avx2,fma"))) void NormalFactorsFma(const float* NX, const float* NY, const float* NZ,
                                                          std::size_t n, const float* ref, float inv, float* w) {
    const __m256 rx = _mm256_set1_ps(ref[0]), ry = _mm256_set1_ps(ref[1]), rz = _mm256_set1_ps(ref[2]);
    const __m256 one = _mm256_set1_ps(1.0f), vinv = _mm256_set1_ps(inv);
    const __m256 sign = _mm256_set1_ps(-0.0f);
    std::size_t j = 0;
    for (; j + 8 <= n; j += 8) {
        const __m256 nx = _mm256_loadu_ps(NX + j), ny = _mm256_loadu_ps(NY + j), nz = _mm256_loadu_ps(NZ + j);
        const __m256 d = _mm256_add_ps(_mm256_mul_ps(nx, rx), _mm256_add_ps(_mm256_mul_ps(ny, ry), _mm256_mul_ps(nz, rz)));
        const __m256 c = _mm256_mul_ps(_mm256_sub_ps(one, d), vinv);
        const __m256 a = _mm256_mul_ps(_mm256_xor_ps(c, sign), c);
        _mm256_storeu_ps(w + j, _mm256_mul_ps(_mm256_loadu_ps(w + j), Exp8(a)));
    }
    NormalFactors(NX + j, NY + j, NZ + j, n - j, ref, inv, w + j);
}

// Whether Exp8 gives expf's bits here: a probe of arguments over the normal weights' range
// [-16, 0] and beyond (another C library, or glibc's non-FMA build, may round differently).
__attribute__((target("avx2,fma"))) bool ExpMatchesLibm() {
    alignas(32) float x[8], y[8];
    for (int k = 0; k < 8192; k += 8) {
        for (int l = 0; l < 8; ++l) {
            const int m = k + l;
            // 7168 spread over [-20, 0.25], then 1024 of the small arguments near 0.
            x[l] = m < 7168 ? -20.0f + 20.25f * float(m) / 7168.0f : -1e-3f * float(m - 7168) / 1024.0f;
        }
        _mm256_store_ps(y, Exp8(_mm256_load_ps(x)));
        for (int l = 0; l < 8; ++l) {
            const float e = __builtin_expf(x[l]);
            if (__builtin_memcmp(&e, &y[l], sizeof e) != 0) return false;
        }
    }
    return true;
}

}  // namespace surfel::fit_kernels::avx2
