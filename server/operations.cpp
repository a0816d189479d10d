#include "operations.h"

#include <spdlog/spdlog.h>

#include <filesystem>

#include "surfel/base/error.h"
#include "upload_session.h"

namespace surfel::server {
namespace fs = std::filesystem;

Operations::Operations(worker::Store& store, worker::JobManager& jobs, Metrics& metrics,
                       Executor& ingest, ServiceLimits limits)
    : store_(store), jobs_(jobs), metrics_(metrics), ingest_(ingest), limits_(limits) {}

std::int64_t Operations::CommittedUploadBytes(const std::string& upload_id) const {
    CheckUploadId(upload_id);
    const std::string path = store_.UploadPath(upload_id);
    std::error_code ec;
    return fs::exists(path, ec) ? static_cast<std::int64_t>(fs::file_size(path, ec)) : 0;
}

v1::Cloud Operations::GetCloud(const std::string& cloud_id) const {
    auto c = store_.FindCloud(cloud_id);
    if (!c) throw Error(ErrorCode::kNotFound, "cloud " + cloud_id + " not found");
    return *c;
}

void Operations::DeleteCloud(const std::string& cloud_id) {
    if (!store_.DeleteCloud(cloud_id))
        throw Error(ErrorCode::kNotFound, "cloud " + cloud_id + " not found");
    spdlog::info("cloud {} deleted", cloud_id);
}

v1::Job Operations::Submit(const v1::JobSpec& spec) {
    v1::Job job = jobs_.Submit(spec);
    metrics_.SetQueueDepth(jobs_.QueueDepth());
    return job;
}

v1::Job Operations::Cancel(const std::string& job_id) {
    v1::Job job = jobs_.Cancel(job_id);
    metrics_.SetQueueDepth(jobs_.QueueDepth());
    return job;
}

v1::Job Operations::GetJob(const std::string& job_id) const {
    auto job = jobs_.Get(job_id);
    if (!job) throw Error(ErrorCode::kNotFound, "job " + job_id + " not found");
    return *job;
}

std::vector<v1::Job> Operations::ListJobs(std::uint32_t limit, v1::JobState state) const {
    if (limit > 10000) throw Error(ErrorCode::kInvalidArgument, "limit: at most 10000");
    return jobs_.List(limit, state);
}

ResultFile Operations::Result(const std::string& job_id) const {
    ResultFile r;
    r.job = GetJob(job_id);
    if (r.job.state() != v1::SUCCEEDED)
        throw Error(ErrorCode::kFailedPrecondition, "job " + job_id + " is " +
                                                        v1::JobState_Name(r.job.state()) +
                                                        "; results exist only for SUCCEEDED jobs");
    r.path = store_.ResultPath(job_id);
    std::error_code ec;
    r.size = fs::file_size(r.path, ec);
    if (ec) throw Error(ErrorCode::kNotFound, "result of job " + job_id + " is gone");
    r.filename = (r.job.type().empty() ? std::string("result") : r.job.type()) + "-" +
                 job_id.substr(0, 12) + r.job.result().extension();
    return r;
}

std::vector<v1::JobEvent> Operations::FinalEvents(const v1::Job& job) {
    std::vector<v1::JobEvent> events(2);
    events[0].set_job_id(job.id());
    *events[0].mutable_state() = job;
    events[1].set_job_id(job.id());
    if (job.state() == v1::SUCCEEDED) {
        *events[1].mutable_finished() = job.result();
    } else {
        events[1].mutable_failed()->set_code(job.status_code());
        events[1].mutable_failed()->set_message(job.status_message());
    }
    return events;
}

bool Operations::ClaimUpload(const std::string& id) {
    std::lock_guard lock(uploads_mutex_);
    if (active_uploads_.count(id)) return false;
    if (active_uploads_.size() >= limits_.max_uploads)
        throw Error(ErrorCode::kResourceExhausted,
                    "upload " + id + ": " + std::to_string(active_uploads_.size()) +
                        " uploads are in progress, the most --max-uploads allows; retry later");
    active_uploads_.insert(id);
    return true;
}

void Operations::ReleaseUpload(const std::string& id) {
    std::lock_guard lock(uploads_mutex_);
    active_uploads_.erase(id);
}

}  // namespace surfel::server
