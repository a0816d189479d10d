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

// glibc's exp in double (sysdeps/ieee754/dbl-64/e_exp.c with __exp_data of e_exp_data.c,
// EXP_TABLE_BITS = 7, EXP_POLY_ORDER = 5), as its FMA build (__exp_fma, which glibc picks on a
// CPU with AVX2 and FMA) computes its fast path: k = round(x N / ln 2), r = x - k ln2/N (two fused
// steps, ln 2 / N split in two), exp(x) = 2^(k/N) (1 + tail + r + r^2 (C2 + C3 r) + r^4 (C4 + C5 r)),
// with the fused operations of that build's code, in its order. The table: 2^(i/N) as (tail,
// bits of the scale without k's exponent) pairs.
alignas(32) const std::uint64_t kExpTable[256] = {
0x0000000000000000, 0x3ff0000000000000, 0x3c9b3b4f1a88bf6e, 0x3feff63da9fb3335,
0xbc7160139cd8dc5d, 0x3fefec9a3e778061, 0xbc905e7a108766d1, 0x3fefe315e86e7f85,
0x3c8cd2523567f613, 0x3fefd9b0d3158574, 0xbc8bce8023f98efa, 0x3fefd06b29ddf6de,
0x3c60f74e61e6c861, 0x3fefc74518759bc8, 0x3c90a3e45b33d399, 0x3fefbe3ecac6f383,
0x3c979aa65d837b6d, 0x3fefb5586cf9890f, 0x3c8eb51a92fdeffc, 0x3fefac922b7247f7,
0x3c3ebe3d702f9cd1, 0x3fefa3ec32d3d1a2, 0xbc6a033489906e0b, 0x3fef9b66affed31b,
0xbc9556522a2fbd0e, 0x3fef9301d0125b51, 0xbc5080ef8c4eea55, 0x3fef8abdc06c31cc,
0xbc91c923b9d5f416, 0x3fef829aaea92de0, 0x3c80d3e3e95c55af, 0x3fef7a98c8a58e51,
0xbc801b15eaa59348, 0x3fef72b83c7d517b, 0xbc8f1ff055de323d, 0x3fef6af9388c8dea,
0x3c8b898c3f1353bf, 0x3fef635beb6fcb75, 0xbc96d99c7611eb26, 0x3fef5be084045cd4,
0x3c9aecf73e3a2f60, 0x3fef54873168b9aa, 0xbc8fe782cb86389d, 0x3fef4d5022fcd91d,
0x3c8a6f4144a6c38d, 0x3fef463b88628cd6, 0x3c807a05b0e4047d, 0x3fef3f49917ddc96,
0x3c968efde3a8a894, 0x3fef387a6e756238, 0x3c875e18f274487d, 0x3fef31ce4fb2a63f,
0x3c80472b981fe7f2, 0x3fef2b4565e27cdd, 0xbc96b87b3f71085e, 0x3fef24dfe1f56381,
0x3c82f7e16d09ab31, 0x3fef1e9df51fdee1, 0xbc3d219b1a6fbffa, 0x3fef187fd0dad990,
0x3c8b3782720c0ab4, 0x3fef1285a6e4030b, 0x3c6e149289cecb8f, 0x3fef0cafa93e2f56,
0x3c834d754db0abb6, 0x3fef06fe0a31b715, 0x3c864201e2ac744c, 0x3fef0170fc4cd831,
0x3c8fdd395dd3f84a, 0x3feefc08b26416ff, 0xbc86a3803b8e5b04, 0x3feef6c55f929ff1,
0xbc924aedcc4b5068, 0x3feef1a7373aa9cb, 0xbc9907f81b512d8e, 0x3feeecae6d05d866,
0xbc71d1e83e9436d2, 0x3feee7db34e59ff7, 0xbc991919b3ce1b15, 0x3feee32dc313a8e5,
0x3c859f48a72a4c6d, 0x3feedea64c123422, 0xbc9312607a28698a, 0x3feeda4504ac801c,
0xbc58a78f4817895b, 0x3feed60a21f72e2a, 0xbc7c2c9b67499a1b, 0x3feed1f5d950a897,
0x3c4363ed60c2ac11, 0x3feece086061892d, 0x3c9666093b0664ef, 0x3feeca41ed1d0057,
0x3c6ecce1daa10379, 0x3feec6a2b5c13cd0, 0x3c93ff8e3f0f1230, 0x3feec32af0d7d3de,
0x3c7690cebb7aafb0, 0x3feebfdad5362a27, 0x3c931dbdeb54e077, 0x3feebcb299fddd0d,
0xbc8f94340071a38e, 0x3feeb9b2769d2ca7, 0xbc87deccdc93a349, 0x3feeb6daa2cf6642,
0xbc78dec6bd0f385f, 0x3feeb42b569d4f82, 0xbc861246ec7b5cf6, 0x3feeb1a4ca5d920f,
0x3c93350518fdd78e, 0x3feeaf4736b527da, 0x3c7b98b72f8a9b05, 0x3feead12d497c7fd,
0x3c9063e1e21c5409, 0x3feeab07dd485429, 0x3c34c7855019c6ea, 0x3feea9268a5946b7,
0x3c9432e62b64c035, 0x3feea76f15ad2148, 0xbc8ce44a6199769f, 0x3feea5e1b976dc09,
0xbc8c33c53bef4da8, 0x3feea47eb03a5585, 0xbc845378892be9ae, 0x3feea34634ccc320,
0xbc93cedd78565858, 0x3feea23882552225, 0x3c5710aa807e1964, 0x3feea155d44ca973,
0xbc93b3efbf5e2228, 0x3feea09e667f3bcd, 0xbc6a12ad8734b982, 0x3feea012750bdabf,
0xbc6367efb86da9ee, 0x3fee9fb23c651a2f, 0xbc80dc3d54e08851, 0x3fee9f7df9519484,
0xbc781f647e5a3ecf, 0x3fee9f75e8ec5f74, 0xbc86ee4ac08b7db0, 0x3fee9f9a48a58174,
0xbc8619321e55e68a, 0x3fee9feb564267c9, 0x3c909ccb5e09d4d3, 0x3feea0694fde5d3f,
0xbc7b32dcb94da51d, 0x3feea11473eb0187, 0x3c94ecfd5467c06b, 0x3feea1ed0130c132,
0x3c65ebe1abd66c55, 0x3feea2f336cf4e62, 0xbc88a1c52fb3cf42, 0x3feea427543e1a12,
0xbc9369b6f13b3734, 0x3feea589994cce13, 0xbc805e843a19ff1e, 0x3feea71a4623c7ad,
0xbc94d450d872576e, 0x3feea8d99b4492ed, 0x3c90ad675b0e8a00, 0x3feeaac7d98a6699,
0x3c8db72fc1f0eab4, 0x3feeace5422aa0db, 0xbc65b6609cc5e7ff, 0x3feeaf3216b5448c,
0x3c7bf68359f35f44, 0x3feeb1ae99157736, 0xbc93091fa71e3d83, 0x3feeb45b0b91ffc6,
0xbc5da9b88b6c1e29, 0x3feeb737b0cdc5e5, 0xbc6c23f97c90b959, 0x3feeba44cbc8520f,
0xbc92434322f4f9aa, 0x3feebd829fde4e50, 0xbc85ca6cd7668e4b, 0x3feec0f170ca07ba,
0x3c71affc2b91ce27, 0x3feec49182a3f090, 0x3c6dd235e10a73bb, 0x3feec86319e32323,
0xbc87c50422622263, 0x3feecc667b5de565, 0x3c8b1c86e3e231d5, 0x3feed09bec4a2d33,
0xbc91bbd1d3bcbb15, 0x3feed503b23e255d, 0x3c90cc319cee31d2, 0x3feed99e1330b358,
0x3c8469846e735ab3, 0x3feede6b5579fdbf, 0xbc82dfcd978e9db4, 0x3feee36bbfd3f37a,
0x3c8c1a7792cb3387, 0x3feee89f995ad3ad, 0xbc907b8f4ad1d9fa, 0x3feeee07298db666,
0xbc55c3d956dcaeba, 0x3feef3a2b84f15fb, 0xbc90a40e3da6f640, 0x3feef9728de5593a,
0xbc68d6f438ad9334, 0x3feeff76f2fb5e47, 0xbc91eee26b588a35, 0x3fef05b030a1064a,
0x3c74ffd70a5fddcd, 0x3fef0c1e904bc1d2, 0xbc91bdfbfa9298ac, 0x3fef12c25bd71e09,
0x3c736eae30af0cb3, 0x3fef199bdd85529c, 0x3c8ee3325c9ffd94, 0x3fef20ab5fffd07a,
0x3c84e08fd10959ac, 0x3fef27f12e57d14b, 0x3c63cdaf384e1a67, 0x3fef2f6d9406e7b5,
0x3c676b2c6c921968, 0x3fef3720dcef9069, 0xbc808a1883ccb5d2, 0x3fef3f0b555dc3fa,
0xbc8fad5d3ffffa6f, 0x3fef472d4a07897c, 0xbc900dae3875a949, 0x3fef4f87080d89f2,
0x3c74a385a63d07a7, 0x3fef5818dcfba487, 0xbc82919e2040220f, 0x3fef60e316c98398,
0x3c8e5a50d5c192ac, 0x3fef69e603db3285, 0x3c843a59ac016b4b, 0x3fef7321f301b460,
0xbc82d52107b43e1f, 0x3fef7c97337b9b5f, 0xbc892ab93b470dc9, 0x3fef864614f5a129,
0x3c74b604603a88d3, 0x3fef902ee78b3ff6, 0x3c83c5ec519d7271, 0x3fef9a51fbc74c83,
0xbc8ff7128fd391f0, 0x3fefa4afa2a490da, 0xbc8dae98e223747d, 0x3fefaf482d8e67f1,
0x3c8ec3bc41aa2008, 0x3fefba1bee615a27, 0x3c842b94c3a9eb32, 0x3fefc52b376bba97,
0x3c8a64a931d185ee, 0x3fefd0765b6e4540, 0xbc8e37bae43be3ed, 0x3fefdbfdad9cbe14,
0x3c77893b4d91cd9d, 0x3fefe7c1819e90d8, 0x3c5305c14160cc89, 0x3feff3c22b8f71f1};
constexpr double kExpInvLn2N = 0x1.71547652b82fep+7, kExpShift = 0x1.8p+52;
constexpr double kExpNegLn2HiN = -0x1.62e42fefa0000p-8, kExpNegLn2LoN = -0x1.cf79abc9e3b3ap-47;
constexpr double kExpC2 = 0x1.ffffffffffdbdp-2, kExpC3 = 0x1.555555555543cp-3, kExpC4 = 0x1.55555cf172b91p-5,
                 kExpC5 = 0x1.1111167a4d017p-7;

// exp of four doubles in glibc's fast path (2^-54 <= |x| < 512; the callers send the rest to exp).
__attribute__((target("avx2,fma"))) inline __m256d ExpD4(__m256d x) {
    const __m256d shift = _mm256_set1_pd(kExpShift);
    __m256d kd = _mm256_fmadd_pd(x, _mm256_set1_pd(kExpInvLn2N), shift);
    const __m256i ki = _mm256_castpd_si256(kd);
    kd = _mm256_sub_pd(kd, shift);
    __m256d r = _mm256_fmadd_pd(kd, _mm256_set1_pd(kExpNegLn2HiN), x);
    r = _mm256_fmadd_pd(kd, _mm256_set1_pd(kExpNegLn2LoN), r);
    const __m256i idx = _mm256_slli_epi64(_mm256_and_si256(ki, _mm256_set1_epi64x(127)), 1);
    const long long* tab = reinterpret_cast<const long long*>(kExpTable);
    const __m256d tail = _mm256_castsi256_pd(_mm256_i64gather_epi64(tab, idx, 8));
    const __m256i sbits = _mm256_add_epi64(_mm256_i64gather_epi64(tab + 1, idx, 8), _mm256_slli_epi64(ki, 45));
    const __m256d p23 = _mm256_fmadd_pd(r, _mm256_set1_pd(kExpC3), _mm256_set1_pd(kExpC2));
    const __m256d tr = _mm256_add_pd(r, tail);
    __m256d r2 = _mm256_mul_pd(r, r);
    const __m256d p45 = _mm256_fmadd_pd(r, _mm256_set1_pd(kExpC5), _mm256_set1_pd(kExpC4));
    const __m256d t = _mm256_fmadd_pd(p23, r2, tr);
    r2 = _mm256_mul_pd(r2, r2);
    const __m256d tmp = _mm256_fmadd_pd(r2, p45, t);
    const __m256d scale = _mm256_castsi256_pd(sbits);
    return _mm256_fmadd_pd(scale, tmp, scale);
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

// GaussWeightsD four at a time with ExpD4, lanes outside its fast path (x = -0, |x| < 2^-54, |x| >=
// 512, NaN) by the C library's exp; the same values.
__attribute__((target("avx2,fma"))) void GaussWeightsDFma(const float* d2, float inv, double* w, std::size_t n) {
    const __m256d vinv = _mm256_set1_pd(static_cast<double>(inv)), sign = _mm256_set1_pd(-0.0);
    std::size_t j = 0;
    for (; j + 4 <= n; j += 4) {
        const __m256d x = _mm256_mul_pd(_mm256_xor_pd(_mm256_cvtps_pd(_mm_loadu_ps(d2 + j)), sign), vinv);
        // top12(x) & 0x7ff minus top12(2^-54) below top12(512) - top12(2^-54), unsigned: glibc's test
        const __m256i top = _mm256_and_si256(_mm256_srli_epi64(_mm256_castpd_si256(x), 52), _mm256_set1_epi64x(0x7ff));
        const __m256i off = _mm256_sub_epi64(top, _mm256_set1_epi64x(0x3c9));  // < 0 or > 0x3e: slow path
        const __m256i bad = _mm256_or_si256(_mm256_cmpgt_epi64(_mm256_setzero_si256(), off),
                                            _mm256_cmpgt_epi64(off, _mm256_set1_epi64x(0x3e)));
        if (_mm256_testz_si256(bad, bad)) {
            _mm256_storeu_pd(w + j, ExpD4(x));
        } else {
            alignas(32) double v[4];
            _mm256_store_pd(v, x);
            for (int l = 0; l < 4; ++l) w[j + l] = __builtin_exp(v[l]);
        }
    }
    GaussWeightsD(d2 + j, inv, w + j, n - j);
}

// Whether ExpD4 gives exp's bits here: a probe over the adaptive weights' range [-4, 0] and beyond
// (another C library, or glibc's non-FMA build, may round differently).
__attribute__((target("avx2,fma"))) bool ExpDMatchesLibm() {
    alignas(32) double x[4], y[4];
    for (int k = 0; k < 8192; k += 4) {
        for (int l = 0; l < 4; ++l) {
            const int m = k + l;
            x[l] = m < 7168 ? -20.0 + 20.25 * double(m) / 7168.0 : -1e-3 * double(m - 7167) / 1024.0;
        }
        _mm256_store_pd(y, ExpD4(_mm256_load_pd(x)));
        for (int l = 0; l < 4; ++l) {
            const double e = __builtin_exp(x[l]);
            if (__builtin_memcmp(&e, &y[l], sizeof e) != 0) return false;
        }
    }
    return true;
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
