// fit_kernels.inc for the x86-64 baseline, and the choice between the builds.
#include "surfel/surface/fit_kernels.h"

#include "surfel/base/kernel_build.h"

#define SURFEL_FIT_ISA baseline
#include "surfel/surface/fit_kernels.inc"

namespace surfel::fit_kernels {

namespace avx2 {  // fit_kernels_avx2.cpp
void Moments(const float* x, const float* y, const float* z, const float* w, std::size_t n, double* out);
void PolySums(const double* x, const double* y, const double* z, const float* w, std::size_t n, double ih,
              double* out);
void SquaredDistances(const float* x, const float* y, const float* z, std::size_t n, float ox, float oy, float oz,
                      float* out);
void GaussWeights(const float* d2, float inv_h2, float* w, std::size_t n);
void SquaredDistancesAround(const float* x, const float* y, const float* z, std::size_t n, double cx, double cy,
                            double cz, float* out);
void ToLocal(const float* x, const float* y, const float* z, std::size_t n, const double* f, double* lx, double* ly,
             double* lz);
void NormalFactors(const float* NX, const float* NY, const float* NZ, std::size_t n, const float* ref, float inv,
                   float* w);
void NormalFactorsFma(const float* NX, const float* NY, const float* NZ, std::size_t n, const float* ref, float inv,
                      float* w);
bool ExpMatchesLibm();
void GaussWeightsD(const float* d2, float inv, double* w, std::size_t n);
void GaussWeightsDFma(const float* d2, float inv, double* w, std::size_t n);
bool ExpDMatchesLibm();
std::size_t GatherWithinPacked(const float* X, const float* Y, const float* Z, const std::uint32_t* I,
                               const float* const* C, std::size_t n, float ox, float oy, float oz, float r2, float* OX,
                               float* OY, float* OZ, float* OD, std::uint32_t* OI, float* const* OC);
std::size_t SelectWithinPacked(const float* X, const float* Y, const float* Z, const std::uint32_t* I,
                               const float* const* C, std::size_t n, float ox, float oy, float oz, float r2, float* OX,
                               float* OY, float* OZ, std::uint32_t* OI, float* const* OC);
}  // namespace avx2

const Kernels& Baseline() {
    static const Kernels k{&baseline::Moments, &baseline::PolySums, &baseline::SquaredDistances,
                           &baseline::GaussWeights, &baseline::SquaredDistancesAround, &baseline::ToLocal,
                           &baseline::NormalFactors, &baseline::GatherWithin, &baseline::SelectWithin,
                           &baseline::GaussWeightsD, "baseline"};
    return k;
}

const Kernels& Best() {
    static const Kernels& best = []() -> const Kernels& {
        static Kernels k{&avx2::Moments,      &avx2::PolySums,
                         &avx2::SquaredDistances, &avx2::GaussWeights,
                         &avx2::SquaredDistancesAround, &avx2::ToLocal,
                         &avx2::NormalFactors, &avx2::GatherWithinPacked, &avx2::SelectWithinPacked,
                         &avx2::GaussWeightsD, "avx2"};
        if (PickKernelBuild() != KernelBuild::kAvx2) return Baseline();
#if defined(__x86_64__) || defined(__i386__)
        // The eight-wide exp only where it is this process's expf to the bit.
        if (__builtin_cpu_supports("fma") && avx2::ExpMatchesLibm()) k.normal_factors = &avx2::NormalFactorsFma;
        // The same for the four-wide exp in double.
        if (__builtin_cpu_supports("fma") && avx2::ExpDMatchesLibm()) k.gauss_weights_d = &avx2::GaussWeightsDFma;
#endif
        return k;
    }();
    return best;
}

bool NormalFactorsVectorised() { return Best().normal_factors == &avx2::NormalFactorsFma; }
bool GaussWeightsDVectorised() { return Best().gauss_weights_d == &avx2::GaussWeightsDFma; }

}  // namespace surfel::fit_kernels
