// split_pass.inc for AVX2 (compiled with -mavx2 -mno-fma -ffp-contract=off on x86-64; elsewhere the
// same portable loop as the baseline).
#include <cstddef>
#include <cstdint>

#define SURFEL_SPLIT_ISA avx2
#include "surfel/simplify/split_pass.inc"
