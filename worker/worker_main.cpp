// surfel-worker: runs jobs from a shared store (PostgreSQL) and a shared blob directory; no gRPC
// port. Scaling out is starting more of these (and more surfel-server API nodes).
#include <signal.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <thread>

#include "surfel/base/error.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/job_manager.h"
#include "surfel/worker/store.h"
#include "surfel/worker/store_postgres.h"

int main(int argc, char** argv) {
    using namespace surfel;
    CLI::App app{"surfel-worker: runs surfel jobs (" + worker::JobKindNames() +
                 ") from a shared PostgreSQL store"};
    std::string store_url, blobs, name, log_level = "info";
    std::size_t threads = 1;
    double lease_s = 30, grace_s = 10;
    int max_attempts = 3;
    std::uint64_t max_points = 50'000'000;
    double max_job_memory_mb = -1;  // -1: 3/4 of the memory available at start
    int job_nice = 10;
    bool json_logs = false;
    app.add_option("--store", store_url, "The shared store: postgres://user@host:port/db")
        ->required();
    app.add_option("--blobs", blobs,
                   "The shared blobs, as the servers' --blobs: dir:PATH (a shared mount), or "
                   "postgres (large objects in the --store database)")
        ->required();
    app.add_option("--threads", threads, "Jobs run at once (each claims its own)")
        ->default_val(1)
        ->check(CLI::Range(1, 1024));
    app.add_option(
           "--lease-s", lease_s,
           "Seconds a claimed job's lease lasts without a heartbeat (renewed every third of it)")
        ->default_val(30)
        ->check(CLI::Range(0.1, 86400.0));
    app.add_option("--max-attempts", max_attempts, "Expired leases before a job fails")
        ->default_val(3)
        ->check(CLI::Range(1, 1000));
    app.add_option("--grace", grace_s,
                   "SIGTERM: seconds running jobs get to finish before their leases are released")
        ->default_val(10)
        ->check(CLI::NonNegativeNumber);
    app.add_option("--max-points", max_points, "Largest point count a job may load")
        ->default_val(50'000'000);
    app.add_option("--job-nice", job_nice,
                   "Niceness added to job threads (and the TBB/Embree threads they start), so that API "
                   "calls stay responsive while jobs use the CPU; 0 = none")
        ->default_val(10)
        ->check(CLI::Range(0, 19));
    app.add_option("--max-job-memory", max_job_memory_mb,
                   "Largest memory estimate in MiB of a job run here (docs/memory.md); a claimed job above "
                   "it fails with RESOURCE_EXHAUSTED before its work; 0 = no limit. Default: 3/4 of the "
                   "memory available at start")
        ->check(CLI::NonNegativeNumber);
    app.add_option("--name", name, "Lease owner name (default <host>:<pid>)");
    app.add_option("--log-level", log_level, "trace, debug, info, warn, error")
        ->default_val("info")
        ->check(CLI::IsMember({"trace", "debug", "info", "warn", "error"}));
    app.add_flag("--json-logs", json_logs, "Log one JSON object per line");
    app.footer(
        "SIGTERM/SIGINT: claim nothing more, give running jobs --grace seconds, release the leases "
        "of the rest\n"
        "(another worker takes them at once), exit 0. kill -9: the job runs again elsewhere after "
        "--lease-s.\n"
        "Example:\n  surfel-worker --store postgres://surfel@db:5432/surfel --blobs "
        "dir:/mnt/surfel --threads 2\n  surfel-worker --store postgres://surfel@db:5432/surfel --blobs postgres");
    CLI11_PARSE(app, argc, argv);

    auto logger = spdlog::stderr_color_mt("surfel-worker");
    spdlog::set_default_logger(logger);
    spdlog::set_level(spdlog::level::from_str(log_level));
    if (json_logs)
        spdlog::set_pattern(
            R"({"time":"%Y-%m-%dT%H:%M:%S.%e%z","level":"%l","thread":%t,"msg":"%v"})");

    sigset_t signals;
    sigemptyset(&signals);
    sigaddset(&signals, SIGTERM);
    sigaddset(&signals, SIGINT);
    pthread_sigmask(SIG_BLOCK, &signals, nullptr);

    try {
        // Refused before anything is opened: a SQLite URL or directory would otherwise be
        // created or migrated by a process that then refuses to use it.
        if (!store_url.starts_with("postgres://") && !store_url.starts_with("postgresql://"))
            throw Error(ErrorCode::kInvalidArgument,
                        "--store " + store_url +
                            ": surfel-worker needs a shared store (postgres://...); a SQLite "
                            "server runs its own jobs");
        std::unique_ptr<worker::Store> store =
            worker::OpenStore(store_url, worker::BlobDirFromFlag(blobs, ""), blobs);
        if (!store->shared())
            throw Error(ErrorCode::kInvalidArgument,
                        "--store " + store_url +
                            ": surfel-worker needs a shared store (postgres://...); a SQLite "
                            "server runs its own jobs");
        worker::ManagerOptions mo;
        mo.workers = threads;
        mo.lease_ms = static_cast<std::int64_t>(lease_s * 1000);
        mo.max_attempts = max_attempts;
        mo.max_points = max_points;
        mo.worker_name = name;
        mo.job_nice = job_nice;
        mo.max_job_memory = max_job_memory_mb < 0
                                ? worker::DefaultMaxJobMemory()
                                : static_cast<std::uint64_t>(max_job_memory_mb * 1024 * 1024);
        worker::JobManager jobs(*store, mo);
        jobs.Start();
        spdlog::info("surfel-worker: {} threads on {} (blobs {})", threads,
                     worker::RedactDatabaseUrl(store_url), store->blobs().Describe());
        std::printf("worker running\n");
        std::fflush(stdout);
        int sig = 0;
        sigwait(&signals, &sig);
        spdlog::info("{}: stopping (grace {} s)", sig == SIGTERM ? "SIGTERM" : "SIGINT", grace_s);
        jobs.Shutdown(static_cast<std::int64_t>(grace_s * 1000));
        spdlog::info("stopped");
        return 0;
    } catch (const Error& e) {
        spdlog::error("{}", e.what());
        return 1;
    } catch (const std::exception& e) {
        spdlog::error("fatal: {}", e.what());
        return 1;
    }
}
