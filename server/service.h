#pragma once
/// \file
/// surfel.v1.Surfel on gRPC's callback API: uploads (resumable, hashed while written,
/// validated by parsing), jobs through the JobManager, and streamed events and results.
///
/// One file per reactor (upload_reactor.cpp, watch_reactor.cpp, download_reactor.cpp), the unary
/// handlers in unary_handlers.cpp. No reaction blocks: parsing and hashing uploaded files run on
/// the ingest Executor. What stays on gRPC's threads is bounded and short: one chunk written or
/// read (at most max_chunk_bytes / download_chunk_bytes) and indexed SQLite lookups and updates.

#include <cstdint>
#include <mutex>
#include <set>
#include <string>

#include "executor.h"
#include "metrics.h"
#include "surfel/v1/surfel.grpc.pb.h"
#include "surfel/worker/job_manager.h"
#include "surfel/worker/store.h"

namespace surfel::server {

/// Per-call limits of the service.
struct ServiceLimits {
    std::uint64_t max_upload_bytes = 2ull << 30;  ///< Larger uploads -> RESOURCE_EXHAUSTED.
    std::uint64_t max_points = 50'000'000;        ///< Clouds with more points -> RESOURCE_EXHAUSTED.
    std::size_t max_chunk_bytes = 1 << 20;        ///< One UploadRequest's data at most.
    std::size_t download_chunk_bytes = 256 << 10; ///< Result chunks in Watch and Download.
};

/// The service. Every reference must outlive it; `ingest` must also outlive the grpc::Server that
/// runs it (its tasks finish upload calls, and the server's Shutdown waits for those).
class SurfelService final : public v1::Surfel::CallbackService {
public:
    SurfelService(worker::Store& store, worker::JobManager& jobs, Metrics& metrics, Executor& ingest,
                  ServiceLimits limits);

    grpc::ServerReadReactor<v1::UploadRequest>* Upload(grpc::CallbackServerContext* ctx, v1::Cloud* response) override;
    grpc::ServerUnaryReactor* QueryUpload(grpc::CallbackServerContext* ctx, const v1::QueryUploadRequest* req,
                                          v1::QueryUploadResponse* resp) override;
    grpc::ServerUnaryReactor* GetCloud(grpc::CallbackServerContext* ctx, const v1::GetCloudRequest* req,
                                       v1::Cloud* resp) override;
    grpc::ServerUnaryReactor* DeleteCloud(grpc::CallbackServerContext* ctx, const v1::DeleteCloudRequest* req,
                                          v1::DeleteCloudResponse* resp) override;
    grpc::ServerUnaryReactor* Submit(grpc::CallbackServerContext* ctx, const v1::SubmitRequest* req,
                                     v1::Job* resp) override;
    grpc::ServerWriteReactor<v1::JobEvent>* Watch(grpc::CallbackServerContext* ctx,
                                                   const v1::WatchRequest* req) override;
    grpc::ServerWriteReactor<v1::DataChunk>* Download(grpc::CallbackServerContext* ctx,
                                                       const v1::DownloadRequest* req) override;
    grpc::ServerUnaryReactor* Cancel(grpc::CallbackServerContext* ctx, const v1::CancelRequest* req,
                                     v1::Job* resp) override;
    grpc::ServerUnaryReactor* GetJob(grpc::CallbackServerContext* ctx, const v1::GetJobRequest* req,
                                     v1::Job* resp) override;
    grpc::ServerUnaryReactor* ListJobs(grpc::CallbackServerContext* ctx, const v1::ListJobsRequest* req,
                                       v1::ListJobsResponse* resp) override;

    /// Used by the reactors.
    worker::Store& store() { return store_; }
    worker::JobManager& jobs() { return jobs_; }
    Metrics& metrics() { return metrics_; }
    /// Where uploads are hashed (on resume) and parsed.
    Executor& ingest() { return ingest_; }
    const ServiceLimits& limits() const { return limits_; }
    /// Claims an upload id for one call at a time; false when another call holds it.
    bool ClaimUpload(const std::string& id);
    void ReleaseUpload(const std::string& id);

private:
    worker::Store& store_;
    worker::JobManager& jobs_;
    Metrics& metrics_;
    Executor& ingest_;
    ServiceLimits limits_;
    std::mutex uploads_mutex_;
    std::set<std::string> active_uploads_;
};

}  // namespace surfel::server
