// surfel-server: the gRPC service with its worker pool, its store (SQLite in the data dir, or a
// shared PostgreSQL with --store) and metrics, and (with --http) the HTTP/JSON front and the web
// page.
#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server_builder.h>
#include <malloc.h>
#include <signal.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <optional>
#include <sstream>
#include <thread>

#include "auth.h"
#include "http_front.h"
#include "metrics.h"
#include "operations.h"
#include "service.h"
#include "surfel/base/error.h"
#include "surfel/io/image.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/memory.h"
#include "surfel/worker/retention.h"
#include "surfel/worker/store_postgres.h"

namespace {

// The page's files: <exe>/../share/surfel/web when installed, else the source tree's web/.
std::string DefaultWebRoot() {
    namespace fs = std::filesystem;
    std::error_code ec;
    const fs::path exe = fs::read_symlink("/proc/self/exe", ec);
    if (!ec) {
        const fs::path installed = exe.parent_path().parent_path() / "share" / "surfel" / "web";
        if (fs::is_directory(installed, ec)) return installed.string();
    }
    return SURFEL_SOURCE_WEB_DIR;
}

// Render jobs open the image plugin on first use (issue 19.2: the server starts without
// OpenImageIO). Say at start where it is, or that render jobs will fail without it.
void LogImagePlugin() {
    namespace fs = std::filesystem;
    const auto find = [](const std::vector<std::string>& paths, std::string& tried) -> std::string {
        for (const std::string& path : paths) {
            std::error_code ec;
            if (fs::is_regular_file(path, ec)) return path;
            tried += (tried.empty() ? "" : ", ") + path;
        }
        return {};
    };
    std::string tried_oiio, tried_exr;
    const std::string oiio = find(surfel::ImageCodecSearchPath(), tried_oiio);
    const std::string exr = find(surfel::ExrCodecSearchPath(), tried_exr);
    if (!exr.empty()) spdlog::info("EXR plugin: {} (opened by the first EXR render job)", exr);
    if (!oiio.empty()) {
        spdlog::info("image plugin: {} (opened by the first PNG render job{})", oiio,
                     exr.empty() ? ", and EXR ones: no EXR plugin" : "");
        return;
    }
    if (!exr.empty()) {
        spdlog::warn("no OpenImageIO plugin found (tried: {}): PNG output will fail with FAILED_PRECONDITION",
                     tried_oiio.empty() ? "nothing: /proc/self/exe unreadable" : tried_oiio);
        return;
    }
    spdlog::warn("no image plugin found (tried: {}; {}): render jobs will fail with FAILED_PRECONDITION",
                 tried_exr.empty() ? "nothing: /proc/self/exe unreadable" : tried_exr, tried_oiio);
}

// Writes `port` to `path` atomically (a reader never sees a partial file).
void WritePortFile(const std::string& path, int port) {
    const std::string tmp = path + ".tmp";
    std::ofstream(tmp) << port << "\n";
    std::rename(tmp.c_str(), path.c_str());
}

struct Flags {
    std::string host = "127.0.0.1";
    int port = 50051;
    std::string data_dir = "surfel-data";
    std::string store;
    std::string blobs;
    int workers = -1;
    double lease_s = 30;
    int max_attempts = 3;
    std::size_t max_queued = 256;
    std::size_t ingest_threads = 2;
    std::size_t ingest_queue = 64;
    std::size_t transfer_threads = 2;
    double upload_window_mib = 8;
    double max_upload_mb = 2048;
    std::uint64_t max_points = 50'000'000;
    double max_job_memory_mb = -1;  // -1: 3/4 of the memory available at start
    int job_nice = 10;
    std::size_t max_uploads = 64;
    double max_upload_inflight_mb = 4096;
    double max_disk_gb = 0;
    std::vector<std::string> ttl;
    double retention_sweep_s = 60;
    std::string upload_ttl = "24h";
    std::string metrics;
    std::string port_file;
    double grace_s = 10;
    std::string log_level = "info";
    bool json_logs = false;
    std::string http;
    std::string http_port_file;
    std::string http_cors_origins;
    std::string web_root;
    std::size_t http_threads = 16;
    double http_keepalive_s = 15;
    std::string auth_tokens;
    bool hash_token = false;
    std::string tls_cert, tls_key, tls_client_ca;
};

std::string ReadPem(const std::string& path, const char* flag) {
    std::ifstream in(path, std::ios::binary);
    if (!in) throw surfel::Error(surfel::ErrorCode::kInvalidArgument, std::string(flag) + ": cannot read " + path);
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
}

// The gRPC port's credentials: plaintext, TLS (--tls-cert/--tls-key), or mutual TLS
// (--tls-client-ca: a client certificate signed by that CA is required and verified).
std::shared_ptr<grpc::ServerCredentials> GrpcCredentials(const Flags& f) {
    using surfel::Error, surfel::ErrorCode;
    if (f.tls_cert.empty() != f.tls_key.empty())
        throw Error(ErrorCode::kInvalidArgument, "--tls-cert and --tls-key go together");
    if (f.tls_cert.empty()) {
        if (!f.tls_client_ca.empty())
            throw Error(ErrorCode::kInvalidArgument, "--tls-client-ca needs --tls-cert and --tls-key");
        return grpc::InsecureServerCredentials();
    }
    grpc::SslServerCredentialsOptions o(f.tls_client_ca.empty()
                                            ? GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE
                                            : GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY);
    o.pem_key_cert_pairs.push_back({ReadPem(f.tls_key, "--tls-key"), ReadPem(f.tls_cert, "--tls-cert")});
    if (!f.tls_client_ca.empty()) o.pem_root_certs = ReadPem(f.tls_client_ca, "--tls-client-ca");
    return grpc::SslServerCredentials(o);
}

bool IsLoopback(const std::string& host) {
    return host == "127.0.0.1" || host == "localhost" || host == "::1" || host == "[::1]" ||
           host.rfind("127.", 0) == 0;
}

}  // namespace

int main(int argc, char** argv) {
    using namespace surfel;
#ifdef __GLIBC__
    // Freed memory stays with the process up to 64 MiB per arena, and blocks up to 32 MiB come
    // from the heap (what glibc's dynamic thresholds reach anyway after a 32 MiB block is
    // freed): gRPC's receive buffers and an upload's chunks are reused instead of handed back
    // to the kernel after every message (madvise) and faulted in again, zeroed, for the next.
    mallopt(M_MMAP_THRESHOLD, 32 << 20);
    mallopt(M_TRIM_THRESHOLD, 64 << 20);
#endif
    CLI::App app{"surfel-server: point-cloud jobs (" + worker::JobKindNames() + ") over gRPC (surfel.v1.Surfel)"};
    Flags f;
    app.add_option("--host", f.host, "Address to listen on (0.0.0.0 for every interface)")->default_val("127.0.0.1");
    app.add_option("-p,--port", f.port, "gRPC port; 0 picks a free one (printed, and written to --port-file)")
        ->default_val(50051)
        ->check(CLI::Range(0, 65535));
    app.add_option("-d,--data-dir", f.data_dir, "Directory for the SQLite database and the blobs (created)")
        ->default_val("surfel-data");
    app.add_option("--store", f.store,
                   "Where jobs and clouds' records live: empty = SQLite in --data-dir (one node); "
                   "postgres://user@host:port/db = PostgreSQL shared by many servers and surfel-worker "
                   "processes (docs/scale-out.md)");
    app.add_option("--blobs", f.blobs,
                   "Where uploaded clouds and results live: dir:PATH (a shared mount when several machines "
                   "share --store), or postgres (large objects in the --store postgres://... database; "
                   "upload part files stay in --data-dir); default: --data-dir");
    app.add_option("-w,--workers", f.workers,
                   "Worker threads running jobs here (default: one per core); 0 = an API node only, which "
                   "needs a shared --store and surfel-worker processes")
        ->check(CLI::Range(0, 4096));
    app.add_option("--lease-s", f.lease_s,
                   "Shared store: seconds a claimed job's lease lasts without a heartbeat (renewed every "
                   "third of it); a dead worker's job runs again after it")
        ->default_val(30)
        ->check(CLI::Range(0.1, 86400.0));
    app.add_option("--max-attempts", f.max_attempts,
                   "Shared store: expired leases before a job fails (UNAVAILABLE, naming the attempts)")
        ->default_val(3)
        ->check(CLI::Range(1, 1000));
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
    app.add_option("--transfer-threads", f.transfer_threads,
                   "Threads that append and hash the chunks of gRPC uploads while gRPC's threads receive "
                   "the next ones (each upload reads at most 2 MiB ahead), and read and hash the next "
                   "chunk of a download while gRPC's threads send the last; 0 = both on gRPC's threads, "
                   "one chunk at a time")
        ->default_val(2)
        ->check(CLI::Range(0, 256));
    app.add_option("--upload-window-mib", f.upload_window_mib,
                   "HTTP/2 receive window of each gRPC stream in MiB (what a client may send ahead of "
                   "the server, buffered by gRPC outside --max-upload-inflight-mb); 0 = gRPC's adaptive window, which "
                   "grows with the link's bandwidth-delay product and buffers more (issue 19.3)")
        ->default_val(8)
        ->check(CLI::Range(0.0, 1024.0));
    app.add_option("--max-upload-mb", f.max_upload_mb, "Largest upload in MiB")->default_val(2048)->check(CLI::PositiveNumber);
    app.add_option("--max-points", f.max_points, "Largest accepted point count")->default_val(50'000'000);
    app.add_option("--job-nice", f.job_nice,
                   "Niceness added to job threads (and the TBB/Embree threads they start), so that API "
                   "calls stay responsive while jobs use the CPU; 0 = none")
        ->default_val(10)
        ->check(CLI::Range(0, 19));
    app.add_option("--max-job-memory", f.max_job_memory_mb,
                   "Largest memory estimate of a job in MiB (docs/memory.md): above it, or above what running "
                   "jobs leave of it, Submit answers RESOURCE_EXHAUSTED; 0 = no limit. Default: 3/4 of the "
                   "memory available at start (MemAvailable, or the cgroup's memory.max - memory.current)")
        ->check(CLI::NonNegativeNumber);
    app.add_option("--max-uploads", f.max_uploads,
                   "Upload calls in progress at once (gRPC and HTTP) before another answers RESOURCE_EXHAUSTED "
                   "(HTTP 429); each holds its chunks in flight (--max-upload-inflight-mb, docs/memory.md) "
                   "and, while parsed, its file and cloud")
        ->default_val(64)
        ->check(CLI::Range(1, 100000));
    app.add_option("--max-upload-inflight-mb", f.max_upload_inflight_mb,
                   "MiB of uploads received and not yet stored (part files of upload calls in progress, each "
                   "read whole to parse, and the chunks held in memory on the way there) before a chunk "
                   "answers RESOURCE_EXHAUSTED (the bytes are kept: resume later); 0 = no limit")
        ->default_val(4096)
        ->check(CLI::NonNegativeNumber);
    app.add_option("--max-disk-gb", f.max_disk_gb,
                   "Quota of blob bytes in GB (10^9): clouds, results and upload part files. Before a write "
                   "would pass it, least recently used results and clouds are evicted, never a cloud a "
                   "queued or running job needs; else RESOURCE_EXHAUSTED (docs/retention.md). 0 = none")
        ->default_val(0)
        ->check(CLI::NonNegativeNumber);
    app.add_option("--ttl", f.ttl,
                   "Time-to-live of results and cloud ownerships since their last use: DURATION for every "
                   "tenant, TENANT=DURATION for one (repeat the flag); 90s, 15m, 12h, 7d; 0 = keep")
        ->allow_extra_args(false)
        ->multi_option_policy(CLI::MultiOptionPolicy::TakeAll);
    app.add_option("--upload-ttl", f.upload_ttl,
                   "Time-to-live of an unfinished upload's part file since its last write: an upload abandoned "
                   "for longer is removed by the sweep and must start again; 90s, 15m, 12h, 7d; 0 = keep")
        ->default_val("24h");
    app.add_option("--retention-sweep-s", f.retention_sweep_s, "Seconds between time-to-live sweeps")
        ->default_val(60)
        ->check(CLI::Range(0.05, 86400.0));
    app.add_option("--metrics", f.metrics, "Serve Prometheus metrics at http://ADDR/metrics, e.g. 127.0.0.1:9464");
    app.add_option("--port-file", f.port_file, "Write the bound port to this file once serving (for scripts)");
    app.add_option("--grace", f.grace_s, "Seconds running jobs get to finish on SIGTERM before they are requeued")
        ->default_val(10)
        ->check(CLI::NonNegativeNumber);
    app.add_option("--log-level", f.log_level, "trace, debug, info, warn, error")
        ->default_val("info")
        ->check(CLI::IsMember({"trace", "debug", "info", "warn", "error"}));
    app.add_flag("--json-logs", f.json_logs, "Log one JSON object per line");
    app.add_option("--http", f.http,
                   "Serve the HTTP/JSON API and the web page at http://ADDR/ (HOST:PORT, port 0 picks one); "
                   "off unless given");
    app.add_option("--http-port-file", f.http_port_file, "Write the bound HTTP port to this file once serving");
    app.add_option("--http-cors-origins", f.http_cors_origins,
                   "Comma-separated origins allowed to call the HTTP API from other sites (\"*\" = any)");
    app.add_option("--web-root", f.web_root, "The web page's files (default: <exe>/../share/surfel/web, else the "
                                             "source tree's web/)");
    app.add_option("--http-threads", f.http_threads,
                   "HTTP connection threads; each open connection, event streams included, holds one")
        ->default_val(16)
        ->check(CLI::Range(2, 4096));
    app.add_option("--http-keepalive-s", f.http_keepalive_s, "Seconds between comment lines on an idle event stream")
        ->default_val(15)
        ->check(CLI::Range(0.05, 3600.0));
    app.add_option("--auth-tokens", f.auth_tokens,
                   "Bearer tokens, one 'NAME TOKEN' or 'NAME sha256:HEX' per line ('#' comments): every "
                   "API call needs 'authorization: Bearer TOKEN', and each NAME is a tenant that sees "
                   "only its own clouds and jobs (docs/security.md); off unless given")
        ->check(CLI::ExistingFile);
    app.add_flag("--hash-token", f.hash_token,
                 "Read a token from stdin, print its 'sha256:HEX' form for --auth-tokens, and exit");
    app.add_option("--tls-cert", f.tls_cert, "TLS certificate chain (PEM) for the gRPC and HTTP ports")
        ->check(CLI::ExistingFile);
    app.add_option("--tls-key", f.tls_key, "TLS private key (PEM) of --tls-cert")->check(CLI::ExistingFile);
    app.add_option("--tls-client-ca", f.tls_client_ca,
                   "Mutual TLS: require client certificates signed by this CA (PEM) on both ports")
        ->check(CLI::ExistingFile);
    app.footer(
        "Jobs persist in DATA_DIR: after a crash or restart, queued and running jobs run again.\n"
        "Scale-out: --store postgres://... --blobs dir:/shared on every server and surfel-worker; --workers 0 makes\n"
        "an API node; a dead worker's job runs again elsewhere after --lease-s (docs/scale-out.md).\n"
        "SIGTERM/SIGINT: stop accepting, give running jobs --grace seconds, requeue the rest, exit 0.\n"
        "Health: grpc.health.v1.Health (\"\" and \"surfel.v1.Surfel\"); server reflection is on.\n"
        "HTTP: --http HOST:PORT serves the same API as JSON (/v1/clouds, /v1/jobs, events as SSE) and the web\n"
        "page at / (docs/http.md).\n"
        "Example:\n  surfel-server --port 50051 --data-dir /var/lib/surfel --metrics 127.0.0.1:9464 --http 127.0.0.1:8080");
    CLI11_PARSE(app, argc, argv);
    if (f.hash_token) {
        std::string token;
        std::getline(std::cin, token);
        while (!token.empty() && (token.back() == '\r' || token.back() == ' ')) token.pop_back();
        if (token.size() < 16) {
            std::fprintf(stderr, "--hash-token: a token has at least 16 characters (got %zu)\n", token.size());
            return 2;
        }
        std::printf("%s\n", server::HashToken(token).c_str());
        return 0;
    }

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
        // The store: SQLite in DATA_DIR (the default), or a shared PostgreSQL; blobs in --blobs.
        const std::string blob_dir = worker::BlobDirFromFlag(f.blobs, f.data_dir);
        std::unique_ptr<worker::Store> store_ptr = worker::OpenStore(
            f.store.empty() ? "sqlite:" + f.data_dir + "/surfel.db" : f.store, blob_dir, f.blobs);
        worker::Store& store = *store_ptr;
        // Disk quota and retention (docs/retention.md): before the job manager, which reserves
        // results there.
        worker::RetentionOptions ro;
        ro.max_disk_bytes = static_cast<std::uint64_t>(f.max_disk_gb * 1e9);
        for (const std::string& t : f.ttl) worker::ApplyTtlFlag(t, &ro);
        ro.upload_ttl_ms = worker::ParseDurationMs(f.upload_ttl, "--upload-ttl");
        worker::Retention retention(store, ro, [&](const std::string& kind, const std::string& cause,
                                                   std::uint64_t bytes) { metrics.CountEviction(kind, cause, bytes); });
        retention.Load();
        worker::ManagerOptions mo;
        mo.retention = &retention;
        mo.workers = f.workers > 0 ? static_cast<std::size_t>(f.workers) : 0;
        mo.run_jobs = f.workers != 0;
        mo.lease_ms = static_cast<std::int64_t>(f.lease_s * 1000);
        mo.max_attempts = f.max_attempts;
        mo.max_queued = f.max_queued;
        mo.max_points = f.max_points;
        mo.job_nice = f.job_nice;
        mo.max_job_memory = f.max_job_memory_mb < 0
                                ? worker::DefaultMaxJobMemory()
                                : static_cast<std::uint64_t>(f.max_job_memory_mb * 1024 * 1024);
        spdlog::info("--max-job-memory {}", mo.max_job_memory ? worker::MiB(mo.max_job_memory) : "none");
        worker::JobManager jobs(store, mo,
                                [&](const v1::Job& job, v1::JobState from) { metrics.OnTransition(job, from); });
        server::ServiceLimits limits;
        limits.max_upload_bytes = static_cast<std::uint64_t>(f.max_upload_mb * 1024 * 1024);
        limits.max_points = f.max_points;
        limits.max_uploads = f.max_uploads;
        limits.max_upload_inflight_bytes = static_cast<std::uint64_t>(f.max_upload_inflight_mb * 1024 * 1024);
        if (limits.max_upload_inflight_bytes != 0 && limits.max_upload_inflight_bytes < limits.max_upload_bytes)
            spdlog::warn("--max-upload-inflight-mb {} is below --max-upload-mb {}: uploads larger than it are "
                         "always refused", f.max_upload_inflight_mb, f.max_upload_mb);
        // Declared before the service and the server: it outlives both, and runs its queue dry
        // while server->Shutdown waits for the upload calls its tasks finish.
        server::Executor ingest(f.ingest_threads, f.ingest_queue);
        // The same for the transfer threads; each upload or download queues one task at most.
        std::optional<server::Executor> transfers;
        if (f.transfer_threads > 0) transfers.emplace(f.transfer_threads, 4096);
        server::Operations ops(store, jobs, metrics, ingest, limits);
        ops.SetRetention(&retention);
        if (!f.auth_tokens.empty()) {
            server::TokenSet tokens = server::TokenSet::Load(f.auth_tokens);
            spdlog::info("auth: {} tenants from {}", tokens.size(), f.auth_tokens);
            ops.SetAuthenticator(server::Authenticator(std::move(tokens)));
        }
        server::SurfelService service(ops, transfers ? &*transfers : nullptr);
        const std::shared_ptr<grpc::ServerCredentials> credentials = GrpcCredentials(f);

        grpc::EnableDefaultHealthCheckService(true);
        grpc::reflection::InitProtoReflectionServerBuilderPlugin();
        grpc::ServerBuilder builder;
        int bound_port = 0;
        builder.AddListeningPort(f.host + ":" + std::to_string(f.port), credentials, &bound_port);
        builder.RegisterService(&service);
        builder.SetMaxReceiveMessageSize(4 << 20);
        if (f.upload_window_mib > 0) {
            // A fixed window instead of the adaptive one: on a fast link the adaptive window
            // lets the client run tens of MiB ahead of the server, buffered in fresh heap
            // memory on several gRPC threads (page faults cost the receive ~20 % of its CPU,
            // bench/README.md "Session 11 (upload helper)"). 8 MiB still fills a 1 Gbit/s link
            // at 64 ms round trip.
            builder.AddChannelArgument(GRPC_ARG_HTTP2_BDP_PROBE, 0);
            builder.AddChannelArgument(GRPC_ARG_HTTP2_STREAM_LOOKAHEAD_BYTES,
                                       static_cast<int>(f.upload_window_mib * (1 << 20)));
        }
        std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
        if (!server || bound_port == 0) {
            spdlog::error("cannot listen on {}:{}", f.host, f.port);
            return 1;
        }
        server->GetHealthCheckService()->SetServingStatus("surfel.v1.Surfel", true);

        std::unique_ptr<server::HttpFront> http;
        if (!f.http.empty()) {
            server::HttpOptions ho;
            const auto colon = f.http.rfind(':');
            if (colon == std::string::npos)
                throw Error(ErrorCode::kInvalidArgument, "--http: expected HOST:PORT, got " + f.http);
            ho.host = f.http.substr(0, colon);
            try {
                ho.port = std::stoi(f.http.substr(colon + 1));
            } catch (const std::exception&) {
                throw Error(ErrorCode::kInvalidArgument, "--http: bad port in " + f.http);
            }
            std::stringstream origins(f.http_cors_origins);
            for (std::string o; std::getline(origins, o, ',');)
                if (!o.empty()) ho.cors_origins.push_back(o);
            ho.web_root = f.web_root.empty() ? DefaultWebRoot() : f.web_root;
            ho.threads = f.http_threads;
            ho.sse_keepalive_ms = static_cast<int>(f.http_keepalive_s * 1000);
            ho.tls_cert = f.tls_cert;
            ho.tls_key = f.tls_key;
            ho.tls_client_ca = f.tls_client_ca;
            http = std::make_unique<server::HttpFront>(ops, ho);
            http->Start();
            const char* scheme = ho.tls_cert.empty() ? "http" : "https";
            spdlog::info("HTTP/JSON API and web page on {}://{}:{}/ (page from {})", scheme, ho.host, http->port(),
                         ho.web_root);
            std::printf("http on %s://%s:%d/\n", scheme, ho.host.c_str(), http->port());
            if (f.auth_tokens.empty() && !IsLoopback(ho.host))
                spdlog::warn("HTTP on {} (not loopback) without --auth-tokens: anyone who reaches it can "
                             "use every cloud and job", ho.host);
            if (!f.http_port_file.empty()) WritePortFile(f.http_port_file, http->port());
        }
        if (f.auth_tokens.empty() && !IsLoopback(f.host))
            spdlog::warn("gRPC on {} (not loopback) without --auth-tokens: anyone who reaches it can use "
                         "every cloud and job", f.host);
        if (f.tls_cert.empty() && !IsLoopback(f.host) && !f.auth_tokens.empty())
            spdlog::warn("tokens travel in plaintext on {}: add --tls-cert/--tls-key", f.host);
        LogImagePlugin();
        jobs.Start();
        spdlog::info("surfel-server listening on {}:{} (store {}, blobs {}, {} workers, {} ingest threads{}{})",
                     f.host, bound_port, f.store.empty() ? "sqlite in " + f.data_dir : worker::RedactDatabaseUrl(f.store),
                     store.blobs().Describe(), !mo.run_jobs ? 0u : mo.workers ? mo.workers : std::thread::hardware_concurrency(),
                     ingest.threads(),
                     f.metrics.empty() ? "" : ", metrics on http://", f.metrics.empty() ? "" : f.metrics + "/metrics");
        std::printf("listening on %s:%d\n", f.host.c_str(), bound_port);
        std::fflush(stdout);
        if (!f.port_file.empty()) WritePortFile(f.port_file, bound_port);

        // Queue depth and disk gauges, refreshed while serving; the time-to-live sweep.
        std::atomic<bool> done{false};
        std::thread gauge([&] {
            const auto sweep_every = std::chrono::milliseconds(static_cast<std::int64_t>(f.retention_sweep_s * 1000));
            auto next_sweep = std::chrono::steady_clock::now();
            while (!done) {
                metrics.SetQueueDepth(jobs.QueueDepth());
                if (std::chrono::steady_clock::now() >= next_sweep) {
                    try {
                        retention.Sweep(worker::NowUnixMs());
                        // Abandoned uploads' part files, each under its upload id's claim (an
                        // upload call holding it keeps it; at --max-uploads it waits a sweep).
                        retention.SweepUploads(
                            worker::NowUnixMs(),
                            [&](const std::string& id) {
                                try {
                                    return ops.ClaimUpload(id);
                                } catch (const Error&) {
                                    return false;
                                }
                            },
                            [&](const std::string& id) { ops.ReleaseUpload(id); });
                    } catch (const std::exception& e) {
                        spdlog::warn("retention sweep: {}", e.what());
                    }
                    next_sweep = std::chrono::steady_clock::now() + sweep_every;
                }
                metrics.SetDisk(retention.stored_bytes(), retention.reserved_bytes(), retention.max_bytes(),
                                ops.InflightBytes());
                std::this_thread::sleep_for(std::min(std::chrono::milliseconds(500), sweep_every));
            }
        });

        int sig = 0;
        sigwait(&signals, &sig);
        spdlog::info("{}: shutting down (grace {} s)", sig == SIGTERM ? "SIGTERM" : "SIGINT", f.grace_s);
        server->GetHealthCheckService()->SetServingStatus(false);
        if (http) http->Stop();
        jobs.Shutdown(static_cast<std::int64_t>(f.grace_s * 1000));
        server->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(2));
        if (transfers) transfers->Stop();  // the same for the transfer threads' last tasks
        ingest.Stop();  // its last tasks may still be returning from Finish; ops outlives them
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
