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
}  // namespace avx2

const Kernels& Baseline() {
    static const Kernels k{&baseline::Moments, &baseline::PolySums, &baseline::SquaredDistances,
                           &baseline::GaussWeights, &baseline::SquaredDistancesAround, &baseline::ToLocal,
                           "baseline"};
    return k;
}

const Kernels& Best() {
    static const Kernels& best = []() -> const Kernels& {
        static const Kernels k{&avx2::Moments,      &avx2::PolySums,
                               &avx2::SquaredDistances, &avx2::GaussWeights,
                               &avx2::SquaredDistancesAround, &avx2::ToLocal,
                               "avx2"};
        return PickKernelBuild() == KernelBuild::kAvx2 ? k : Baseline();
    }();
    return best;
}

}  // namespace surfel::fit_kernels
