// Scale-out benchmark (issue 17): jobs/s and submit -> result latency (p50, p99) of tiny renders
// on the SQLite single node and on PostgreSQL with 1 API server and 1, 2, 4 surfel-worker
// processes (one thread each), all on this machine. On 2 cores the ceiling is the CPU, so the
// figures show the shared store's overhead per job rather than a speed-up.
// Run: build/bin/bench_scaleout [--jobs N] [--clients C]   (prints a markdown table)
#include <fcntl.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "pg_cluster.h"
#include "server_process.h"
#include "service_client.h"
#include "surfel/base/shapes.h"
#include "surfel/io/ply.h"

using Clock = std::chrono::steady_clock;
namespace fs = std::filesystem;

namespace {

/// A surfel-worker process (output discarded).
class Worker {
  public:
    Worker(const std::string& store, const std::string& blobs, int i) {
        pid_ = fork();
        if (pid_ == 0) {
            const int fd = ::open("/dev/null", O_WRONLY);
            ::dup2(fd, 1);
            ::dup2(fd, 2);
            const std::string bin = std::string(SURFEL_BIN_DIR) + "/surfel-worker";
            const std::string name = "bench-w" + std::to_string(i);
            execl(bin.c_str(), bin.c_str(), "--store", store.c_str(), "--blobs",
                  ("dir:" + blobs).c_str(), "--threads", "1", "--name", name.c_str(), "--log-level",
                  "warn", nullptr);
            _exit(127);
        }
    }
    ~Worker() {
        ::kill(pid_, SIGKILL);
        waitpid(pid_, nullptr, 0);
    }

  private:
    pid_t pid_ = -1;
};

struct Figures {
    double jobs_per_s = 0, p50_ms = 0, p99_ms = 0;
    double claim_p99_ms = 0;   ///< created -> started (in the queue until a worker claimed it)
    double notice_p99_ms = 0;  ///< finished -> the watcher had the result
};

std::int64_t UnixMs() {
    return std::chrono::duration_cast<std::chrono::milliseconds>(
               std::chrono::system_clock::now().time_since_epoch())
        .count();
}

double P99(std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v.empty() ? 0 : v[std::min(v.size() - 1, v.size() * 99 / 100)];
}

/// `jobs` distinct tiny renders from `clients` threads, each submit -> watch with the result.
Figures Drive(const std::string& target, const std::string& tiny, int jobs, int clients, int salt) {
    surfel::client::ServiceClient setup(target);
    const std::string cloud = setup.UploadFile(tiny).id();
    std::atomic<int> next{0};
    std::mutex m;
    std::vector<double> latencies, claims, notices;
    const auto t0 = Clock::now();
    std::vector<std::thread> threads;
    for (int c = 0; c < clients; ++c)
        threads.emplace_back([&] {
            surfel::client::ServiceClient client(target);
            for (int i; (i = next++) < jobs;) {
                surfel::v1::JobSpec spec;
                auto* r = spec.mutable_render();
                r->set_cloud_id(cloud);
                r->set_width(16 + i % 64);  // distinct specs: no job is reused
                r->set_height(16 + i / 64 + 8 * salt);
                const auto s = Clock::now();
                const std::string id = client.Submit(spec).id();
                const auto out = client.Watch(id, true, false);
                const double ms =
                    std::chrono::duration<double, std::milli>(Clock::now() - s).count();
                const std::int64_t seen = UnixMs();
                const surfel::v1::Job job = client.GetJob(id);
                if (out.state != surfel::v1::SUCCEEDED)
                    std::fprintf(stderr, "job failed: %s\n", out.status_message.c_str());
                std::lock_guard lock(m);
                latencies.push_back(ms);
                claims.push_back(double(job.started_unix_ms() - job.created_unix_ms()));
                notices.push_back(double(seen - job.finished_unix_ms()));
            }
        });
    for (auto& t : threads) t.join();
    const double seconds = std::chrono::duration<double>(Clock::now() - t0).count();
    std::sort(latencies.begin(), latencies.end());
    Figures f;
    f.jobs_per_s = jobs / seconds;
    f.p50_ms = latencies[latencies.size() / 2];
    f.p99_ms = latencies[std::min(latencies.size() - 1, latencies.size() * 99 / 100)];
    f.claim_p99_ms = P99(claims);
    f.notice_p99_ms = P99(notices);
    return f;
}

}  // namespace

int main(int argc, char** argv) {
    int jobs = 200, clients = 4;
    for (int i = 1; i + 1 < argc; i += 2) {
        if (std::string(argv[i]) == "--jobs") jobs = std::stoi(argv[i + 1]);
        if (std::string(argv[i]) == "--clients") clients = std::stoi(argv[i + 1]);
    }
    const fs::path dir =
        fs::temp_directory_path() / ("surfel-bench-scaleout-" + std::to_string(getpid()));
    fs::create_directories(dir);
    surfel::ShapeOptions o;
    o.points = 2000;
    o.normals = true;
    const std::string tiny = (dir / "tiny.ply").string();
    surfel::WritePly(surfel::SampleShape(surfel::Shape::kSphere, o), tiny);

    std::printf(
        "| setup (%d tiny renders 16..79 x 16..%d px, %d clients) | jobs/s | p50 ms | p99 ms | "
        "p99 queued->claimed ms | p99 finished->client ms |\n",
        jobs, 16 + jobs / 64 + 40, clients);
    std::printf("|---|---|---|---|---|---|\n");
    {
        surfel::testing::ServerProcess single((dir / "single").string());
        Drive(single.target(), tiny, 4, clients, 100);  // warm-up, as below
        const Figures f = Drive(single.target(), tiny, jobs, clients, 0);
        std::printf(
            "| SQLite single node (in-process pool, 2 threads) | %.1f | %.1f | %.1f | %.0f | %.0f "
            "|\n",
            f.jobs_per_s, f.p50_ms, f.p99_ms, f.claim_p99_ms, f.notice_p99_ms);
        std::fflush(stdout);
    }
    auto& cluster = surfel::testing_pg::Cluster::Get();
    if (!cluster.ok()) {
        std::fprintf(stderr, "PostgreSQL did not start: %s\n", cluster.why_not().c_str());
        return 1;
    }
    int salt = 1;
    for (int workers : {1, 2, 4}) {
        const std::string url = cluster.NewSchema("bench_" + std::to_string(workers));
        const std::string blobs = (dir / ("blobs-" + std::to_string(workers))).string();
        fs::create_directories(blobs);
        surfel::testing::ServerProcess api(
            (dir / ("api-" + std::to_string(workers))).string(),
            {"--store", url, "--blobs", "dir:" + blobs, "--workers", "0"});
        std::vector<std::unique_ptr<Worker>> pool;
        for (int i = 0; i < workers; ++i) pool.push_back(std::make_unique<Worker>(url, blobs, i));
        // Warm-up: until every worker has started (connected, LISTENing, first claim), which on a
        // loaded machine takes seconds; not part of the figures.
        Drive(api.target(), tiny, 4 * workers, clients, 100 + salt);
        const Figures f = Drive(api.target(), tiny, jobs, clients, salt++);
        std::printf(
            "| PostgreSQL, 1 API server + %d worker%s | %.1f | %.1f | %.1f | %.0f | %.0f |\n",
            workers, workers > 1 ? "s" : "", f.jobs_per_s, f.p50_ms, f.p99_ms, f.claim_p99_ms,
            f.notice_p99_ms);
        std::fflush(stdout);
    }
    fs::remove_all(dir);
    return 0;
}
