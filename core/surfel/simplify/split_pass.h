#pragma once
// The split pass of hierarchical clustering (clustering.cpp, notes 2.1.2), compiled twice like
// the fits' kernels (surface/fit_kernels.h): for the x86-64 baseline and for AVX2, the one to run
// picked once from the CPU. Each build lives in its own translation unit (split_pass_base.cpp,
// split_pass_avx2.cpp); the AVX2 one includes nothing but <cstddef>, <cstdint> and the loops of
// split_pass.inc, so no inline function of a shared header is compiled with AVX2.
//
// Both builds give the same bits: every sum adds the same terms in the same order (one
// accumulator per sum, the AVX2 build holds three of them in the lanes of one register), the
// products and differences are elementwise, no FMA and no contraction. Setting the environment
// variable SURFEL_FIT_KERNELS=baseline picks the baseline build on any CPU (the one rule for every
// twice-compiled loop: PickKernelBuild(), base/kernel_build.h).

#include <cstddef>
#include <cstdint>

namespace surfel::split_pass {

/// One split of `n` items, each 16 bytes {float x, y, z; uint32 id} at `src`: the items with
/// x ax + y ay + z az < cut (in float, in that order) are written to dst[0, k) in the order they
/// come, the others to dst[k, n) from the end backwards; returns k. Each side's sums about
/// o = (ox, oy, oz), with d = double(p - o) (the difference in float): sums[0..8] the negative
/// side's sum dx, dy, dz, dx dx, dx dy, dx dz, dy dy, dy dz, dz dz, sums[9..17] the positive side's,
/// each added in item order.
using SplitFn = std::uint32_t (*)(const void* src, std::size_t n, void* dst, const float* o, const float* axis,
                                  float cut, double* sums);

/// The sums of one side of Split over all `n` items at `items`, in item order: sums[0..8] as
/// Split's negative side (a node's own statistics without a split).
using SumsFn = void (*)(const void* items, std::size_t n, const float* o, double* sums);

struct Kernels {
    SplitFn split;
    SumsFn sums;
    const char* isa;  ///< "avx2" or "baseline"
};

/// The build for this CPU (decided once per process, thread-safe).
const Kernels& Best();
/// The baseline build (any CPU).
const Kernels& Baseline();

}  // namespace surfel::split_pass
