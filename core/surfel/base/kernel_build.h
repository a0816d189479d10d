#pragma once
/// \file
/// Which build of a hot loop to run: the loops compiled twice, for the x86-64 baseline and for
/// AVX2 (the fits' kernels, surface/fit_kernels.h; hierarchical clustering's split pass,
/// simplify/split_pass.h), pick their build here, so every such loop follows one rule and one
/// switch.

namespace surfel {

/// The builds a twice-compiled loop comes in.
enum class KernelBuild {
    kBaseline,  ///< the x86-64 baseline (SSE2), runs on any CPU
    kAvx2,      ///< compiled with -mavx2 (no FMA, no contraction)
};

/// The build to run in this process: kBaseline when the environment variable
/// SURFEL_FIT_KERNELS is exactly "baseline" (to compare the builds, or on a CPU that misreports),
/// otherwise kAvx2 when the CPU supports AVX2 (`__builtin_cpu_supports("avx2")`; never on a
/// non-x86 target), otherwise kBaseline. Reads the environment and the CPU on every call: callers
/// decide once and keep their choice (each in a function-local static, which is thread-safe).
KernelBuild PickKernelBuild();

}  // namespace surfel
