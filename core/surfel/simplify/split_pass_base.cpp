// split_pass.inc for the baseline, and the choice between the builds.
#include "surfel/simplify/split_pass.h"

#include "surfel/base/kernel_build.h"

#define SURFEL_SPLIT_ISA baseline
#include "surfel/simplify/split_pass.inc"

namespace surfel::split_pass {

namespace avx2 {  // split_pass_avx2.cpp
std::uint32_t Split(const void* src, std::size_t n, void* dst, const float* o, const float* axis, float cut,
                    double* sums);
void Sums(const void* items, std::size_t n, const float* o, double* sums);
}  // namespace avx2

const Kernels& Baseline() {
    static const Kernels k{&baseline::Split, &baseline::Sums, "baseline"};
    return k;
}

const Kernels& Best() {
    static const Kernels& best = []() -> const Kernels& {
        static const Kernels k{&avx2::Split, &avx2::Sums, "avx2"};
        return PickKernelBuild() == KernelBuild::kAvx2 ? k : Baseline();
    }();
    return best;
}

}  // namespace surfel::split_pass
