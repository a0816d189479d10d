#include <gtest/gtest.h>

#include <cstdlib>
#include <optional>
#include <string>

#include "surfel/base/kernel_build.h"

namespace surfel {
namespace {

// Sets SURFEL_FIT_KERNELS for one scope (unset for nullopt) and restores what was there.
class ScopedKernelsEnv {
   public:
    explicit ScopedKernelsEnv(const char* value) {
        if (const char* old = std::getenv("SURFEL_FIT_KERNELS")) old_ = old;
        if (value) setenv("SURFEL_FIT_KERNELS", value, 1);
        else unsetenv("SURFEL_FIT_KERNELS");
    }
    ~ScopedKernelsEnv() {
        if (old_) setenv("SURFEL_FIT_KERNELS", old_->c_str(), 1);
        else unsetenv("SURFEL_FIT_KERNELS");
    }

   private:
    std::optional<std::string> old_;
};

KernelBuild WhatTheCpuSupports() {
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx2")) return KernelBuild::kAvx2;
#endif
    return KernelBuild::kBaseline;
}

TEST(PickKernelBuild, FollowsTheCpuWithoutTheOverride) {
    ScopedKernelsEnv env(nullptr);
    EXPECT_EQ(PickKernelBuild(), WhatTheCpuSupports());
}

TEST(PickKernelBuild, BaselineForcesTheBaselineBuild) {
    ScopedKernelsEnv env("baseline");
    EXPECT_EQ(PickKernelBuild(), KernelBuild::kBaseline);
}

TEST(PickKernelBuild, OnlyTheExactWordBaselineOverrides) {
    for (const char* other : {"", "avx2", "Baseline", "baseline ", "base"}) {
        ScopedKernelsEnv env(other);
        EXPECT_EQ(PickKernelBuild(), WhatTheCpuSupports()) << "SURFEL_FIT_KERNELS='" << other << "'";
    }
}

}  // namespace
}  // namespace surfel
