// The unary calls of SurfelService. Each translates and calls the Store or the JobManager: indexed
// SQLite lookups and updates, short enough to run in the reaction (no file is read here).
#include <spdlog/spdlog.h>

#include <filesystem>

#include "service.h"
#include "surfel/base/error.h"
#include "surfel/worker/status.h"
#include "upload_reactor.h"

namespace surfel::server {
namespace fs = std::filesystem;

namespace {

// Runs `fn` and finishes a unary call with OK or the mapped status of what it threw.
template <typename Fn>
grpc::ServerUnaryReactor* Unary(grpc::CallbackServerContext* ctx, Fn&& fn) {
    auto* reactor = ctx->DefaultReactor();
    grpc::Status status;
    try {
        fn();
    } catch (...) {
        status = worker::CurrentExceptionStatus();
    }
    reactor->Finish(status);
    return reactor;
}

}  // namespace

grpc::ServerUnaryReactor* SurfelService::QueryUpload(grpc::CallbackServerContext* ctx, const v1::QueryUploadRequest* req,
                                                     v1::QueryUploadResponse* resp) {
    return Unary(ctx, [&] {
        CheckUploadId(req->upload_id());
        const std::string path = store_.UploadPath(req->upload_id());
        std::error_code ec;
        resp->set_committed_size(fs::exists(path, ec) ? static_cast<std::int64_t>(fs::file_size(path, ec)) : 0);
    });
}

grpc::ServerUnaryReactor* SurfelService::GetCloud(grpc::CallbackServerContext* ctx, const v1::GetCloudRequest* req,
                                                  v1::Cloud* resp) {
    return Unary(ctx, [&] {
        auto c = store_.FindCloud(req->cloud_id());
        if (!c) throw Error(ErrorCode::kNotFound, "cloud " + req->cloud_id() + " not found");
        *resp = *c;
    });
}

grpc::ServerUnaryReactor* SurfelService::DeleteCloud(grpc::CallbackServerContext* ctx, const v1::DeleteCloudRequest* req,
                                                     v1::DeleteCloudResponse* resp) {
    return Unary(ctx, [&] {
        if (!store_.DeleteCloud(req->cloud_id()))
            throw Error(ErrorCode::kNotFound, "cloud " + req->cloud_id() + " not found");
        resp->set_deleted(true);
        spdlog::info("cloud {} deleted", req->cloud_id());
    });
}

grpc::ServerUnaryReactor* SurfelService::Submit(grpc::CallbackServerContext* ctx, const v1::SubmitRequest* req,
                                                v1::Job* resp) {
    return Unary(ctx, [&] {
        *resp = jobs_.Submit(req->spec());
        metrics_.SetQueueDepth(jobs_.QueueDepth());
    });
}

grpc::ServerUnaryReactor* SurfelService::Cancel(grpc::CallbackServerContext* ctx, const v1::CancelRequest* req,
                                                v1::Job* resp) {
    return Unary(ctx, [&] {
        *resp = jobs_.Cancel(req->job_id());
        metrics_.SetQueueDepth(jobs_.QueueDepth());
    });
}

grpc::ServerUnaryReactor* SurfelService::GetJob(grpc::CallbackServerContext* ctx, const v1::GetJobRequest* req,
                                                v1::Job* resp) {
    return Unary(ctx, [&] {
        auto job = jobs_.Get(req->job_id());
        if (!job) throw Error(ErrorCode::kNotFound, "job " + req->job_id() + " not found");
        *resp = *job;
    });
}

grpc::ServerUnaryReactor* SurfelService::ListJobs(grpc::CallbackServerContext* ctx, const v1::ListJobsRequest* req,
                                                  v1::ListJobsResponse* resp) {
    return Unary(ctx, [&] {
        if (req->limit() > 10000) throw Error(ErrorCode::kInvalidArgument, "limit: at most 10000");
        for (v1::Job& j : jobs_.List(req->limit(), req->state())) *resp->add_jobs() = std::move(j);
    });
}

}  // namespace surfel::server
