// The unary calls of SurfelService. Each translates and calls Operations (the same calls the HTTP
// front makes): indexed SQLite lookups and updates, short enough to run in the reaction (no file
// is read here).
#include "service.h"
#include "surfel/worker/status.h"

namespace surfel::server {

namespace {

// Runs `fn` and finishes a unary call with OK or the mapped status of what it threw.
// The caller is authenticated first (UNAUTHENTICATED with auth on and no valid token).
template <typename Fn>
grpc::ServerUnaryReactor* Unary(const SurfelService& service, grpc::CallbackServerContext* ctx, Fn&& fn) {
    auto* reactor = ctx->DefaultReactor();
    grpc::Status status;
    try {
        fn(service.Authenticate(ctx));
    } catch (...) {
        status = worker::CurrentExceptionStatus();
    }
    reactor->Finish(status);
    return reactor;
}

}  // namespace

grpc::ServerUnaryReactor* SurfelService::QueryUpload(grpc::CallbackServerContext* ctx, const v1::QueryUploadRequest* req,
                                                     v1::QueryUploadResponse* resp) {
    return Unary(*this, ctx, [&](const Caller& caller) { resp->set_committed_size(ops_.CommittedUploadBytes(caller, req->upload_id())); });
}

grpc::ServerUnaryReactor* SurfelService::GetCloud(grpc::CallbackServerContext* ctx, const v1::GetCloudRequest* req,
                                                  v1::Cloud* resp) {
    return Unary(*this, ctx, [&](const Caller& caller) { *resp = ops_.GetCloud(caller, req->cloud_id()); });
}

grpc::ServerUnaryReactor* SurfelService::DeleteCloud(grpc::CallbackServerContext* ctx, const v1::DeleteCloudRequest* req,
                                                     v1::DeleteCloudResponse* resp) {
    return Unary(*this, ctx, [&](const Caller& caller) {
        ops_.DeleteCloud(caller, req->cloud_id());
        resp->set_deleted(true);
    });
}

grpc::ServerUnaryReactor* SurfelService::Submit(grpc::CallbackServerContext* ctx, const v1::SubmitRequest* req,
                                                v1::Job* resp) {
    return Unary(*this, ctx, [&](const Caller& caller) { *resp = ops_.Submit(caller, req->spec()); });
}

grpc::ServerUnaryReactor* SurfelService::Cancel(grpc::CallbackServerContext* ctx, const v1::CancelRequest* req,
                                                v1::Job* resp) {
    return Unary(*this, ctx, [&](const Caller& caller) { *resp = ops_.Cancel(caller, req->job_id()); });
}

grpc::ServerUnaryReactor* SurfelService::GetJob(grpc::CallbackServerContext* ctx, const v1::GetJobRequest* req,
                                                v1::Job* resp) {
    return Unary(*this, ctx, [&](const Caller& caller) { *resp = ops_.GetJob(caller, req->job_id()); });
}

grpc::ServerUnaryReactor* SurfelService::ListJobs(grpc::CallbackServerContext* ctx, const v1::ListJobsRequest* req,
                                                  v1::ListJobsResponse* resp) {
    return Unary(*this, ctx, [&](const Caller& caller) {
        for (v1::Job& j : ops_.ListJobs(caller, req->limit(), req->state())) *resp->add_jobs() = std::move(j);
    });
}

}  // namespace surfel::server
