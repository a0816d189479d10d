#pragma once
// The sums of the on-surface representatives (simplify.cpp, RepresentativesOnSurface): each
// fitted cluster's moments and the sums of its quadratic fit, kLanes clusters at a time, one in
// each lane of a vector. Compiled twice like the split pass (split_pass.h): for the x86-64 baseline
// and for AVX2, the one to run picked once from the CPU (PickKernelBuild(), base/kernel_build.h:
// SURFEL_FIT_KERNELS=baseline picks the baseline). Each build lives in its own translation unit
// (cluster_sums_base.cpp, cluster_sums_avx2.cpp); the AVX2 one includes nothing but <cstddef>,
// <cstdint>, this header (declarations only) and the loops of cluster_sums.inc.
//
// Both builds give the same bits, and the bits of the scalar loops they replace: each lane adds its
// own cluster's terms one by one in member order, every product and difference is elementwise, no
// FMA and no contraction; a lane past its cluster's end adds zeros (+0 or -0), which leave every
// sum as it is (a sum that starts at +0 never becomes -0).

#include <cstddef>
#include <cstdint>

namespace surfel::cluster_sums {

inline constexpr int kLanes = 4;

/// Moments::Add's sums over the members of kLanes clusters: lane l reads the size[l] points
/// xyz[3 i], xyz[3 i + 1], xyz[3 i + 2] for i = index[l][0 .. size[l]) (float, widened to double);
/// out[k * kLanes + l] for k = 0..8: sum x, y, z, x x, x y, x z, y y, y z, z z, each added in
/// member order. A lane with size 0 gives zeros.
using MomentsFn = void (*)(const float* xyz, const std::uint32_t* const* index,
                           const std::uint32_t* size, double* out);
/// PolyFit::AddBatch's 21 sums for weight 1 (the 15 moments, then the 6 right-hand sides;
/// PolyFit::AddSums's order) over the same members in the local coordinates of each lane's frame:
/// frame[k * kLanes + l] for k = 0..12: origin x, y, z, u x, y, z, v x, y, z, n x, y, z, 1 / h;
/// (x, y, z) = ((p - origin) . u, (p - origin) . v, (p - origin) . n) in double, each dot as
/// (a0 b0 + a1 b1) + a2 b2 (LocalFrame::ToLocal), xs = x / h, ys = y / h. out[k * kLanes + l].
using FitFn = void (*)(const float* xyz, const std::uint32_t* const* index,
                       const std::uint32_t* size, const double* frame, double* out);

struct Kernels {
    MomentsFn moments;
    FitFn fit;
    const char* isa;  ///< "avx2" or "baseline"
};

/// The build for this CPU (decided once per process, thread-safe).
const Kernels& Best();
/// The baseline build (any CPU).
const Kernels& Baseline();

}  // namespace surfel::cluster_sums
