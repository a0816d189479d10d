// surfel-server: the gRPC service with its worker pool, SQLite store and metrics.
#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/server_builder.h>
#include <signal.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <chrono>
#include <fstream>
#include <thread>

#include "metrics.h"
#include "service.h"
#include "surfel/base/error.h"

namespace {

struct Flags {
    std::string host = "127.0.0.1";
    int port = 50051;
    std::string data_dir = "surfel-data";
    std::size_t workers = 0;
    std::size_t max_queued = 256;
    std::size_t ingest_threads = 2;
    std::size_t ingest_queue = 64;
    double max_upload_mb = 2048;
    std::uint64_t max_points = 50'000'000;
    std::string metrics;
    std::string port_file;
    double grace_s = 10;
    std::string log_level = "info";
    bool json_logs = false;
};

}  // namespace

int main(int argc, char** argv) {
    using namespace surfel;
    CLI::App app{"surfel-server: point-cloud jobs (render, simplify) over gRPC (surfel.v1.Surfel)"};
    Flags f;
    app.add_option("--host", f.host, "Address to listen on (0.0.0.0 for every interface)")->default_val("127.0.0.1");
    app.add_option("-p,--port", f.port, "gRPC port; 0 picks a free one (printed, and written to --port-file)")
        ->default_val(50051)
        ->check(CLI::Range(0, 65535));
    app.add_option("-d,--data-dir", f.data_dir, "Directory for the SQLite database and the blobs (created)")
        ->default_val("surfel-data");
    app.add_option("-w,--workers", f.workers, "Worker threads (0 = one per core)")->default_val(0);
    app.add_option("--max-queued", f.max_queued, "Jobs waiting before Submit answers RESOURCE_EXHAUSTED")
        ->default_val(256)
        ->check(CLI::Range(1, 1000000));
    app.add_option("--ingest-threads", f.ingest_threads,
                   "Threads that parse finished uploads (and hash resumed ones), off gRPC's threads; each "
                   "holds one upload's bytes and its parsed cloud in memory")
        ->default_val(2)
        ->check(CLI::Range(1, 256));
    app.add_option("--ingest-queue", f.ingest_queue,
                   "Uploads waiting for an ingest thread before Upload answers RESOURCE_EXHAUSTED "
                   "(the bytes are kept: the client resumes)")
        ->default_val(64)
        ->check(CLI::Range(1, 100000));
    app.add_option("--max-upload-mb", f.max_upload_mb, "Largest upload in MiB")->default_val(2048)->check(CLI::PositiveNumber);
    app.add_option("--max-points", f.max_points, "Largest accepted point count")->default_val(50'000'000);
    app.add_option("--metrics", f.metrics, "Serve Prometheus metrics at http://ADDR/metrics, e.g. 127.0.0.1:9464");
    app.add_option("--port-file", f.port_file, "Write the bound port to this file once serving (for scripts)");
    app.add_option("--grace", f.grace_s, "Seconds running jobs get to finish on SIGTERM before they are requeued")
        ->default_val(10)
        ->check(CLI::NonNegativeNumber);
    app.add_option("--log-level", f.log_level, "trace, debug, info, warn, error")
        ->default_val("info")
        ->check(CLI::IsMember({"trace", "debug", "info", "warn", "error"}));
    app.add_flag("--json-logs", f.json_logs, "Log one JSON object per line");
    app.footer(
        "Jobs persist in DATA_DIR: after a crash or restart, queued and running jobs run again.\n"
        "SIGTERM/SIGINT: stop accepting, give running jobs --grace seconds, requeue the rest, exit 0.\n"
        "Health: grpc.health.v1.Health (\"\" and \"surfel.v1.Surfel\"); server reflection is on.\n"
        "Example:\n  surfel-server --port 50051 --data-dir /var/lib/surfel --metrics 127.0.0.1:9464");
    CLI11_PARSE(app, argc, argv);

    auto logger = spdlog::stderr_color_mt("surfel");
    spdlog::set_default_logger(logger);
    spdlog::set_level(spdlog::level::from_str(f.log_level));
    if (f.json_logs)
        spdlog::set_pattern(R"({"time":"%Y-%m-%dT%H:%M:%S.%e%z","level":"%l","thread":%t,"msg":"%v"})");

    // Block the shutdown signals in every thread; one thread waits for them.
    sigset_t signals;
    sigemptyset(&signals);
    sigaddset(&signals, SIGTERM);
    sigaddset(&signals, SIGINT);
    pthread_sigmask(SIG_BLOCK, &signals, nullptr);

    try {
        server::Metrics metrics;
        if (!f.metrics.empty()) metrics.Serve(f.metrics);
        worker::Store store(f.data_dir);
        worker::ManagerOptions mo;
        mo.workers = f.workers;
        mo.max_queued = f.max_queued;
        mo.max_points = f.max_points;
        worker::JobManager jobs(store, mo,
                                [&](const v1::Job& job, v1::JobState from) { metrics.OnTransition(job, from); });
        server::ServiceLimits limits;
        limits.max_upload_bytes = static_cast<std::uint64_t>(f.max_upload_mb * 1024 * 1024);
        limits.max_points = f.max_points;
        // Declared before the service and the server: it outlives both, and runs its queue dry
        // while server->Shutdown waits for the upload calls its tasks finish.
        server::Executor ingest(f.ingest_threads, f.ingest_queue);
        server::SurfelService service(store, jobs, metrics, ingest, limits);

        grpc::EnableDefaultHealthCheckService(true);
        grpc::reflection::InitProtoReflectionServerBuilderPlugin();
        grpc::ServerBuilder builder;
        int bound_port = 0;
        builder.AddListeningPort(f.host + ":" + std::to_string(f.port), grpc::InsecureServerCredentials(), &bound_port);
        builder.RegisterService(&service);
        builder.SetMaxReceiveMessageSize(4 << 20);
        std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
        if (!server || bound_port == 0) {
            spdlog::error("cannot listen on {}:{}", f.host, f.port);
            return 1;
        }
        server->GetHealthCheckService()->SetServingStatus("surfel.v1.Surfel", true);
        jobs.Start();
        spdlog::info("surfel-server listening on {}:{} (data {}, {} workers, {} ingest threads{}{})", f.host,
                     bound_port, f.data_dir, mo.workers ? mo.workers : std::thread::hardware_concurrency(),
                     ingest.threads(),
                     f.metrics.empty() ? "" : ", metrics on http://", f.metrics.empty() ? "" : f.metrics + "/metrics");
        std::printf("listening on %s:%d\n", f.host.c_str(), bound_port);
        std::fflush(stdout);
        if (!f.port_file.empty()) {
            const std::string tmp = f.port_file + ".tmp";
            std::ofstream(tmp) << bound_port << "\n";
            std::rename(tmp.c_str(), f.port_file.c_str());
        }

        // Queue depth gauge, refreshed while serving.
        std::atomic<bool> done{false};
        std::thread gauge([&] {
            while (!done) {
                metrics.SetQueueDepth(jobs.QueueDepth());
                std::this_thread::sleep_for(std::chrono::milliseconds(500));
            }
        });

        int sig = 0;
        sigwait(&signals, &sig);
        spdlog::info("{}: shutting down (grace {} s)", sig == SIGTERM ? "SIGTERM" : "SIGINT", f.grace_s);
        server->GetHealthCheckService()->SetServingStatus(false);
        jobs.Shutdown(static_cast<std::int64_t>(f.grace_s * 1000));
        server->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(2));
        done = true;
        gauge.join();
        spdlog::info("stopped");
        return 0;
    } catch (const surfel::Error& e) {
        spdlog::error("{}", e.what());
        return 1;
    } catch (const std::exception& e) {
        spdlog::error("fatal: {}", e.what());
        return 1;
    }
}
