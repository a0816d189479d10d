#pragma once
/// \file
/// surfel.v1.Surfel on gRPC's callback API: uploads (resumable, hashed while written,
/// validated by parsing), jobs through the JobManager, and streamed events and results.
///
/// One file per reactor (upload_reactor.cpp, watch_reactor.cpp, download_reactor.cpp), the unary
/// handlers in unary_handlers.cpp. No reaction blocks: parsing and hashing uploaded files run on
/// the ingest Executor. What stays on gRPC's threads is bounded and short: one chunk written or
/// read (at most max_chunk_bytes / download_chunk_bytes) and indexed SQLite lookups and updates.

#include "operations.h"
#include "surfel/v1/surfel.grpc.pb.h"

namespace surfel::server {

/// The gRPC front: each call translated into Operations (operations.h). `ops` must outlive it, and
/// its ingest Executor, like `transfers`, must also outlive the grpc::Server that runs it (their
/// tasks finish upload and download calls, and the server's Shutdown waits for those).
/// `transfers` (optional) appends and hashes the chunks of Upload calls while gRPC's threads
/// receive the next ones (upload_reactor.cpp), and reads and hashes the next chunk of a Download
/// while gRPC's threads send the last (download_reactor.cpp); without it, both in the reactions.
class SurfelService final
    : public v1::Surfel::WithRawCallbackMethod_Upload<v1::Surfel::CallbackService> {
  public:
    explicit SurfelService(Operations& ops, Executor* transfers = nullptr) : ops_(ops), transfers_(transfers) {}

    /// Upload reads gRPC's raw messages: the chunk's bytes stay in gRPC's receive slices, written
    /// and hashed from there (upload_reactor.cpp, ParseUploadMessage); the answer is a Cloud.
    grpc::ServerReadReactor<grpc::ByteBuffer>* Upload(grpc::CallbackServerContext* ctx,
                                                      grpc::ByteBuffer* response) override;
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
    Operations& ops() { return ops_; }
    worker::Store& store() { return ops_.store(); }
    worker::JobManager& jobs() { return ops_.jobs(); }
    Metrics& metrics() { return ops_.metrics(); }
    /// Where uploads are hashed (on resume) and parsed.
    Executor& ingest() { return ops_.ingest(); }
    /// Where Upload calls append and hash their chunks and Download calls read and hash theirs;
    /// null: in gRPC's reactions.
    Executor* transfers() { return transfers_; }
    const ServiceLimits& limits() const { return ops_.limits(); }
    /// The caller of a call: its `authorization: Bearer <token>` metadata through
    /// Operations::auth(). Throws Error(kUnauthenticated) when auth is on and it is missing or
    /// wrong. (grpc.health.v1 and reflection are other services: they stay open.)
    Caller Authenticate(const grpc::CallbackServerContext* ctx) const;

private:
    Operations& ops_;
    Executor* transfers_;
};

}  // namespace surfel::server
