// Blob store benchmark (issue 17.7, 18.4): MB/s of storing ("upload": write + fsync + rename, or
// one large-object transaction of 1 MiB lo_writes) and of reading back with the SHA-256 check,
// into a directory on disk, a directory on tmpfs and PostgreSQL large objects (a cluster started
// as the tests start it, tests/pg_cluster.h, with fsync switched back on); and what the check on
// read costs a job: the read with and without hashing, next to parsing the same file.
// Rounds are interleaved (every backend once per round) and medians printed, since the machine
// is shared. Run: build/bin/bench_blobs [--mib N] [--rounds R]   (prints markdown tables)
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "pg_cluster.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/file_bytes.h"
#include "surfel/worker/blob_store.h"
#include "surfel/worker/store.h"

using Clock = std::chrono::steady_clock;
namespace fs = std::filesystem;
using namespace surfel;
using namespace surfel::worker;

namespace {

double Seconds(const std::function<void()>& f) {
    const auto t0 = Clock::now();
    f();
    return std::chrono::duration<double>(Clock::now() - t0).count();
}

double Median(std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v.empty() ? 0 : v[v.size() / 2];
}

std::string RandomBytes(std::size_t n, unsigned seed) {
    std::mt19937_64 rng(seed);
    std::string s(n, '\0');
    for (std::size_t i = 0; i + 8 <= n; i += 8) {
        const std::uint64_t x = rng();
        std::memcpy(s.data() + i, &x, 8);
    }
    return s;
}

}  // namespace

int main(int argc, char** argv) {
    std::size_t mib = 64;
    int rounds = 5;
    for (int i = 1; i + 1 < argc; i += 2) {
        if (!std::strcmp(argv[i], "--mib")) mib = std::stoul(argv[i + 1]);
        if (!std::strcmp(argv[i], "--rounds")) rounds = std::stoi(argv[i + 1]);
    }
    const fs::path disk = fs::temp_directory_path() / ("surfel-bench-blobs-" + std::to_string(getpid()));
    const fs::path shm = fs::path("/dev/shm") / ("surfel-bench-blobs-" + std::to_string(getpid()));
    fs::remove_all(disk);
    fs::remove_all(shm);

    std::map<std::string, std::unique_ptr<BlobStore>> backends;
    backends["dir on disk (" + disk.string() + ")"] = std::make_unique<DirBlobStore>(disk.string());
    backends["dir on tmpfs (/dev/shm)"] = std::make_unique<DirBlobStore>(shm.string());
    std::unique_ptr<Store> pg;
    auto& cluster = testing_pg::Cluster::Get();
    if (cluster.ok()) {
        const std::string url = cluster.NewSchema("bench_blobs");
        // The test cluster runs with fsync off; a benchmark of durable stores wants it on.
        const std::string admin = "postgresql://surfel@127.0.0.1:" + cluster.port() + "/postgres";
        testing_pg::Cluster::Exec(admin, "ALTER SYSTEM SET fsync = on");
        testing_pg::Cluster::Exec(admin, "ALTER SYSTEM SET synchronous_commit = on");
        testing_pg::Cluster::Exec(admin, "ALTER SYSTEM SET full_page_writes = on");
        testing_pg::Cluster::Exec(admin, "SELECT pg_reload_conf()");
        pg = OpenStore(url, (disk / "pg-local").string(), "postgres");
        backends["postgres large objects (cluster in " + testing_pg::ScratchDir() + ")"] =
            std::unique_ptr<BlobStore>();
    } else {
        std::fprintf(stderr, "no PostgreSQL: %s\n", cluster.why_not().c_str());
    }
    auto store_of = [&](const std::string& name) -> BlobStore& {
        return backends[name] ? *backends[name] : pg->blobs();
    };

    // ---- store and read back, interleaved rounds
    const std::size_t n = mib << 20;
    std::map<std::string, std::vector<double>> put_s, read_s;
    for (int r = 0; r < rounds; ++r) {
        const std::string bytes = RandomBytes(n, 1000 + r);
        const std::string sha = Sha256Hex(bytes);
        for (auto& [name, unused] : backends) {
            BlobStore& b = store_of(name);
            const std::string key = ResultBlobKey("bench-" + std::to_string(r));
            put_s[name].push_back(Seconds([&] { b.PutBytes(key, bytes, sha); }));
            read_s[name].push_back(Seconds([&] {
                if (ReadVerified(b, key, sha, "bench").size() != n) std::abort();
            }));
            b.Remove(key);
        }
    }
    std::printf("\n### Blobs of %zu MiB: store (durable) and read back with the SHA-256 check; "
                "median of %d interleaved rounds\n\n",
                mib, rounds);
    std::printf("| backend | store MB/s | store s (median) | read+verify MB/s |\n|---|---|---|---|\n");
    for (auto& [name, unused] : backends)
        std::printf("| %s | %.0f | %.3f | %.0f |\n", name.c_str(), n / 1e6 / Median(put_s[name]),
                    Median(put_s[name]), n / 1e6 / Median(read_s[name]));

    // ---- what the check costs a job that loads a real scan
    const std::string data = SURFEL_SHARED_DATA_DIR;
    std::printf("\n### The check on read, on shared scans (dir on disk, page cache warm; median "
                "of %d rounds)\n\n",
                rounds);
    std::printf("| file | MB | read ms | read + SHA-256 ms | parse ms | check / (read + parse) "
                "|\n|---|---|---|---|---|---|\n");
    for (const char* file : {"bunny_scans_merged.ply", "igea_mesh.ply"}) {
        const std::string path = data + "/" + file;
        if (!fs::exists(path)) continue;
        const std::string bytes = ReadFileBytes(path);
        const std::string sha = Sha256Hex(bytes);
        BlobStore& b = *backends.begin()->second;
        b.PutBytes(CloudBlobKey(sha), bytes, sha);
        std::vector<double> plain, checked, parse;
        for (int r = 0; r < rounds; ++r) {
            plain.push_back(Seconds([&] { ReadVerified(b, CloudBlobKey(sha), "", file); }));
            checked.push_back(Seconds([&] { ReadVerified(b, CloudBlobKey(sha), sha, file); }));
            parse.push_back(Seconds([&] { ParsePointCloud(bytes, file, {}); }));
        }
        const double p = Median(plain), c = Median(checked), q = Median(parse);
        std::printf("| %s | %.1f | %.2f | %.2f | %.2f | +%.1f %% |\n", file, bytes.size() / 1e6,
                    p * 1e3, c * 1e3, q * 1e3, 100.0 * (c - p) / (p + q));
    }
    fs::remove_all(disk);
    fs::remove_all(shm);
    return 0;
}
