// cluster_sums.inc for AVX2 (compiled with -mavx2 -mno-fma -ffp-contract=off on x86-64; elsewhere
// the same portable loops as the baseline).
#include <cstddef>
#include <cstdint>

#include "surfel/simplify/cluster_sums.h"

#define SURFEL_CLUSTER_ISA avx2
#include "surfel/simplify/cluster_sums.inc"
