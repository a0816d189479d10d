// split_pass.inc for the baseline, and the choice between the builds.
#include "surfel/simplify/split_pass.h"

#include <cstdlib>
#include <cstring>

#define SURFEL_SPLIT_ISA baseline
#include "surfel/simplify/split_pass.inc"

namespace surfel::split_pass {

namespace avx2 {  // split_pass_avx2.cpp
std::uint32_t Split(const void* src, std::size_t n, void* dst, const float* o, const float* axis, float cut,
                    double* sums);
}  // namespace avx2

const Kernels& Baseline() {
    static const Kernels k{&baseline::Split, "baseline"};
    return k;
}

const Kernels& Best() {
    static const Kernels& best = []() -> const Kernels& {
        static const Kernels k{&avx2::Split, "avx2"};
        const char* force = std::getenv("SURFEL_FIT_KERNELS");
        if (force && std::strcmp(force, "baseline") == 0) return Baseline();
#if defined(__x86_64__) || defined(__i386__)
        __builtin_cpu_init();
        if (__builtin_cpu_supports("avx2")) return k;
#endif
        return Baseline();
    }();
    return best;
}

}  // namespace surfel::split_pass
