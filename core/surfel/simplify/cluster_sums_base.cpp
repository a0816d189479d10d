// cluster_sums.inc for the baseline, and the choice between the builds.
#include "surfel/base/kernel_build.h"
#include "surfel/simplify/cluster_sums.h"

#define SURFEL_CLUSTER_ISA baseline
#include "surfel/simplify/cluster_sums.inc"

namespace surfel::cluster_sums {

namespace avx2 {  // cluster_sums_avx2.cpp
void Moments(const float* xyz, const std::uint32_t* const* index, const std::uint32_t* size,
             double* out);
void Fit(const float* xyz, const std::uint32_t* const* index, const std::uint32_t* size,
         const double* frame, double* out);
}  // namespace avx2

const Kernels& Baseline() {
    static const Kernels k{&baseline::Moments, &baseline::Fit, "baseline"};
    return k;
}

const Kernels& Best() {
    static const Kernels& best = []() -> const Kernels& {
        static const Kernels k{&avx2::Moments, &avx2::Fit, "avx2"};
        return PickKernelBuild() == KernelBuild::kAvx2 ? k : Baseline();
    }();
    return best;
}

}  // namespace surfel::cluster_sums
