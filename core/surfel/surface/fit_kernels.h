#pragma once
/// \file
/// The loops that dominate a surface fit: two weighted sums (about a quarter of a render's instructions:
/// the covariance of the support plane, eq. 8-9, and the normal equations of the polynomial,
/// eq. 10), the neighbours' squared distances and Gaussian weights, compiled twice: for the x86-64 baseline Debian builds for (SSE2: two doubles a
/// vector) and for AVX2 (four), the one to run picked once from the CPU. Each build lives in its
/// own translation unit (fit_kernels_base.cpp, fit_kernels_avx2.cpp) that includes nothing but
/// <cstddef> and the loops of fit_kernels.inc, so no inline function of a shared header is ever
/// compiled with AVX2 (two copies of one inline function under different flags are one symbol
/// to the linker, which may keep either).
///
/// The elementwise loops give the same bits in both builds (no FMA, no contraction). The two
/// builds of the sums add the same terms in a different order (2 against 4 partial sums per sum), so
/// their results can differ in the last bits of a double; bench/README.md ("Render at the
/// paper's framing") measures what that does to an image. Setting the environment variable
/// SURFEL_FIT_KERNELS=baseline picks the baseline build on any CPU.

#include <cstddef>
#include <cstdint>

namespace surfel::fit_kernels {

/// out[0..9] = sum w, sum w x, sum w y, sum w z, sum w xx, w xy, w xz, w yy, w yz, w zz over n
/// samples (float inputs, double sums).
using MomentsFn = void (*)(const float* x, const float* y, const float* z, const float* w, std::size_t n,
                           double* out);
/// The 15 moments sum w xs^a ys^b (a + b <= 4, PolyFit's order) into out[0..14] and the 6 sums
/// sum w z t_k (t = 1, xs, ys, xs^2, xs ys, ys^2) into out[15..20], with xs = x * ih, ys = y * ih.
using PolySumsFn = void (*)(const double* x, const double* y, const double* z, const float* w, std::size_t n,
                            double ih, double* out);

/// out[j] = |(X, Y, Z)[j] - o|^2 in float, as x^2 + (y^2 + z^2) (Eigen's squaredNorm order).
using SquaredDistancesFn = void (*)(const float* x, const float* y, const float* z, std::size_t n, float ox,
                                    float oy, float oz, float* out);
/// poly_fit.h's GaussWeights: w[i] = exp(-d2[i] * inv_h2) (elementwise: the same bits in both builds).
using GaussWeightsFn = void (*)(const float* d2, float inv_h2, float* w, std::size_t n);

/// poly_fit.h's NeighborBatch::WeightsAround distances: out[j] = float(|(X, Y, Z)[j] - c|^2) with
/// the differences and squares in double (elementwise: the same bits in both builds).
using SquaredDistancesAroundFn = void (*)(const float* x, const float* y, const float* z, std::size_t n, double cx,
                                          double cy, double cz, float* out);
/// poly_fit.h's NeighborBatch::ToLocal: (lx, ly, lz)[j] = ((X, Y, Z)[j] - o) . (u, v, nrm) in double,
/// frame = {o, u, v, nrm} as 12 doubles (elementwise: the same bits in both builds).
using ToLocalFn = void (*)(const float* x, const float* y, const float* z, std::size_t n, const double* frame,
                           double* lx, double* ly, double* lz);

/// The adaptive scales' smoothing weights: w[j] = exp(-double(d2[j]) * inv) in double, exp as the
/// C library's exp. The AVX2 build computes four at once with glibc's exp algorithm (its FMA
/// variant, which glibc itself runs on such a CPU) and is chosen only where it reproduces this
/// process's exp to the bit on a probe (GaussWeightsDVectorised); elsewhere each weight calls exp.
using GaussWeightsDFn = void (*)(const float* d2, float inv, double* w, std::size_t n);

/// The normal-aware weights (AaOptions::normal_sigma): w[j] *= exp(-c^2), c = (1 - n_j . ref) * inv,
/// n_j = (nx, ny, nz)[j] the neighbour's normal, in float, the dot as Eigen's x + (y + z), exp as
/// the C library's expf. The AVX2 build computes eight at once with glibc's expf algorithm (the
/// FMA variant glibc itself runs on such a CPU) and is chosen only where it reproduces this
/// process's expf to the bit (NormalFactorsVectorised); elsewhere each factor calls expf.
using NormalFactorsFn = void (*)(const float* nx, const float* ny, const float* nz, std::size_t n, const float* ref,
                                 float inv, float* w);

/// The neighbours of a gather among candidates: for each j with d2 = |(X, Y, Z)[j] - o|^2 <= r2
/// (float, as SquaredDistances), in order, appends the offset (X, Y, Z)[j] - o to (out_x, out_y,
/// out_z), d2 to out_d2, I[j] to out_i and, when `carry` is not null, carry[c][j] to
/// carry_out[c] (c = 0, 1, 2: three float attributes that travel with the points, e.g. normals);
/// returns how many. The outputs need room for n + 8 entries (the AVX2 build stores eight at a
/// time). Data movement after elementwise arithmetic: the same bits in both builds.
using GatherWithinFn = std::size_t (*)(const float* X, const float* Y, const float* Z, const std::uint32_t* I,
                                       const float* const* carry, std::size_t n, float ox, float oy, float oz,
                                       float r2, float* out_x, float* out_y, float* out_z, float* out_d2,
                                       std::uint32_t* out_i, float* const* carry_out);
/// GatherWithin's filter keeping the points themselves: for each j with |(X, Y, Z)[j] - o|^2 <= r2
/// (the same float test), in order, appends (X, Y, Z)[j], I[j] and the carried attributes;
/// returns how many. Room for n + 8 entries.
using SelectWithinFn = std::size_t (*)(const float* X, const float* Y, const float* Z, const std::uint32_t* I,
                                       const float* const* carry, std::size_t n, float ox, float oy, float oz,
                                       float r2, float* out_x, float* out_y, float* out_z, std::uint32_t* out_i,
                                       float* const* carry_out);

struct Kernels {
    MomentsFn moments;
    PolySumsFn poly_sums;
    SquaredDistancesFn squared_distances;
    GaussWeightsFn gauss_weights;
    SquaredDistancesAroundFn squared_distances_around;
    ToLocalFn to_local;
    NormalFactorsFn normal_factors;
    GatherWithinFn gather_within;
    SelectWithinFn select_within;
    GaussWeightsDFn gauss_weights_d;
    const char* isa;  ///< "avx2" or "baseline"
};

/// The build for this CPU (decided once per process, thread-safe).
const Kernels& Best();
/// The baseline build (any x86-64).
const Kernels& Baseline();
/// Whether Best().normal_factors is the eight-wide one (AVX2, FMA, and its exp agreed with
/// expf on a probe of arguments when the kernels were chosen).
bool NormalFactorsVectorised();
/// Whether Best().gauss_weights_d is the four-wide one (AVX2, FMA, and its exp agreed with exp on a
/// probe of arguments when the kernels were chosen).
bool GaussWeightsDVectorised();

}  // namespace surfel::fit_kernels
