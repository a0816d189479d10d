// fit_kernels.inc for AVX2 (this file alone is compiled with -mavx2 -mno-fma -ffp-contract=off:
// see core/CMakeLists.txt). Only <cstddef> is included, so no inline function of a shared
// header is compiled for AVX2 here.
#include <cstddef>

#define SURFEL_FIT_ISA avx2
#include "surfel/surface/fit_kernels.inc"
