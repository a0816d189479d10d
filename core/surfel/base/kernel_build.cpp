#include "surfel/base/kernel_build.h"

#include <cstdlib>
#include <cstring>

namespace surfel {

KernelBuild PickKernelBuild() {
    const char* force = std::getenv("SURFEL_FIT_KERNELS");
    if (force && std::strcmp(force, "baseline") == 0) return KernelBuild::kBaseline;
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx2")) return KernelBuild::kAvx2;
#endif
    return KernelBuild::kBaseline;
}

}  // namespace surfel
