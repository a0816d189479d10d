// The host's memory latency: nanoseconds per dependent load while following a random cycle
// through a buffer far larger than the caches (256 MiB by default). Not a Surfel figure: a
// reading of the machine, printed by bench/regress before and after its rows, because this
// project's VM moves by 30-40 % on memory-bound rows (iterative simplification) within hours
// with the same binary (bench/README.md, session 16). Usage: bench_host_latency [MiB] [loads].
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <numeric>
#include <vector>

int main(int argc, char** argv) {
    const std::size_t mib = argc > 1 ? std::strtoull(argv[1], nullptr, 10) : 256;
    const std::size_t loads = argc > 2 ? std::strtoull(argv[2], nullptr, 10) : 20'000'000;
    const std::size_t n = (mib << 20) / sizeof(std::uint64_t);
    if (n < 2 || loads == 0) {
        std::fprintf(stderr, "usage: %s [MiB >= 1] [loads >= 1]\n", argv[0]);
        return 2;
    }
    // Sattolo's shuffle: one cycle through every slot, so the chase never settles in a short loop.
    std::vector<std::uint64_t> next(n);
    std::iota(next.begin(), next.end(), std::uint64_t{0});
    std::uint64_t s = 88172645463325252ull;  // xorshift64: the same cycle on every run
    for (std::size_t i = n - 1; i > 0; --i) {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        std::swap(next[i], next[s % i]);
    }
    std::uint64_t p = 0;
    const auto t0 = std::chrono::steady_clock::now();
    for (std::size_t k = 0; k < loads; ++k) p = next[p];
    const auto t1 = std::chrono::steady_clock::now();
    const double ns = std::chrono::duration<double, std::nano>(t1 - t0).count() / static_cast<double>(loads);
    std::printf("{\"ns_per_load\":%.1f,\"mib\":%zu,\"loads\":%zu,\"end\":%llu}\n", ns, mib, loads,
                static_cast<unsigned long long>(p));
    return 0;
}
