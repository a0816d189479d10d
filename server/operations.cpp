#include "operations.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <filesystem>

#include "surfel/base/error.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/sha256.h"
#include "upload_session.h"

namespace surfel::server {
namespace fs = std::filesystem;

Operations::Operations(worker::Store& store, worker::JobManager& jobs, Metrics& metrics,
                       Executor& ingest, ServiceLimits limits)
    : store_(store), jobs_(jobs), metrics_(metrics), ingest_(ingest), limits_(limits) {}

std::string Operations::ScopedUploadId(const Caller& caller, const std::string& upload_id) {
    if (!caller.scoped) return upload_id;
    std::string scoped = "t";
    scoped.append(worker::Sha256Hex("tenant\n" + caller.tenant), 0, 16);
    scoped.push_back('_');
    scoped.append(upload_id);
    return scoped;
}

std::int64_t Operations::CommittedUploadBytes(const Caller& caller,
                                              const std::string& upload_id) const {
    CheckUploadId(upload_id);
    const std::string path = store_.UploadPath(ScopedUploadId(caller, upload_id));
    std::error_code ec;
    return fs::exists(path, ec) ? static_cast<std::int64_t>(fs::file_size(path, ec)) : 0;
}

std::optional<std::string> Operations::Evicted(const Caller& caller, const std::string& key,
                                               const std::string& what) const {
    if (!retention_) return std::nullopt;
    return retention_->EvictedMessage(key, what, caller.scoped ? &caller.tenant : nullptr);
}

v1::Cloud Operations::GetCloud(const Caller& caller, const std::string& cloud_id) const {
    std::optional<v1::Cloud> c;
    if (!caller.scoped || store_.CloudOwned(caller.tenant, cloud_id)) c = store_.FindCloud(cloud_id);
    if (!c) {
        if (auto m = Evicted(caller, worker::CloudBlobKey(cloud_id), "cloud " + cloud_id))
            throw Error(ErrorCode::kNotFound, *m + "; upload it again");
        throw Error(ErrorCode::kNotFound, "cloud " + cloud_id + " not found");
    }
    return *c;
}

void Operations::DeleteCloud(const Caller& caller, const std::string& cloud_id) {
    const auto not_found = [&] {
        if (auto m = Evicted(caller, worker::CloudBlobKey(cloud_id), "cloud " + cloud_id))
            return Error(ErrorCode::kNotFound, *m);
        return Error(ErrorCode::kNotFound, "cloud " + cloud_id + " not found");
    };
    // Refused, not deferred, while a queued or running job of the caller needs it: the answer
    // names the job, and the caller cancels it or waits (docs/retention.md). Held against
    // evictions and submissions from the check to the deletion.
    std::unique_lock<std::recursive_mutex> hold;
    if (retention_) hold = retention_->Lock();
    if (!caller.scoped || store_.CloudOwned(caller.tenant, cloud_id)) {
        const auto in_use = worker::CloudsInUse(store_);
        if (auto it = in_use.find(cloud_id); it != in_use.end())
            for (const v1::Job& job : it->second)
                if (!caller.scoped || job.tenant() == caller.tenant)
                    throw Error(ErrorCode::kFailedPrecondition,
                                "cloud " + cloud_id + " is an input of job " + job.id() + " (" +
                                    v1::JobState_Name(job.state()) +
                                    "); cancel it or wait until it ends, then delete the cloud");
    }
    const auto removed = [&] {
        if (retention_) retention_->Removed(worker::CloudBlobKey(cloud_id));
    };
    if (!caller.scoped) {
        if (!store_.DeleteCloud(cloud_id)) throw not_found();
        removed();
        spdlog::info("cloud {} deleted", cloud_id);
        return;
    }
    std::size_t remaining = 0;
    if (!store_.RemoveCloudOwner(caller.tenant, cloud_id, &remaining)) throw not_found();
    if (remaining == 0) {
        store_.DeleteCloud(cloud_id);
        removed();
    }
    spdlog::info("cloud {} deleted by tenant {}{}", cloud_id, caller.tenant,
                 remaining ? " (other tenants keep it)" : "");
}

v1::Job Operations::Submit(const Caller& caller, const v1::JobSpec& spec) {
    // No eviction between the check that the clouds exist and the job's record (which pins them).
    std::unique_lock<std::recursive_mutex> hold;
    if (retention_) hold = retention_->Lock();
    if (caller.scoped || retention_) {
        // Validated first, as the manager does; then the same message as the manager's for a
        // cloud that does not exist at all, or one that says it was evicted.
        worker::ValidateSpec(spec);
        for (const worker::CloudInput& input : worker::KindOf(spec).Inputs(spec)) {
            const bool present = caller.scoped ? store_.CloudOwned(caller.tenant, input.id)
                                               : store_.FindCloud(input.id).has_value();
            if (present) continue;
            if (auto m = Evicted(caller, worker::CloudBlobKey(input.id), "cloud " + input.id))
                throw Error(ErrorCode::kNotFound, input.field + ": " + *m + "; upload it again");
            if (caller.scoped)
                throw Error(ErrorCode::kNotFound,
                            input.field + ": cloud " + input.id + " not found (upload it first)");
        }
    }
    v1::Job job = jobs_.Submit(spec, caller.tenant);
    metrics_.SetQueueDepth(jobs_.QueueDepth());
    return job;
}

v1::Job Operations::Cancel(const Caller& caller, const std::string& job_id) {
    if (caller.scoped) GetJob(caller, job_id);  // kNotFound for another tenant's job
    v1::Job job = jobs_.Cancel(job_id);
    metrics_.SetQueueDepth(jobs_.QueueDepth());
    return job;
}

v1::Job Operations::GetJob(const Caller& caller, const std::string& job_id) const {
    auto job = jobs_.Get(job_id);
    if (!job || (caller.scoped && job->tenant() != caller.tenant))
        throw Error(ErrorCode::kNotFound, "job " + job_id + " not found");
    return *job;
}

std::vector<v1::Job> Operations::ListJobs(const Caller& caller, std::uint32_t limit,
                                          v1::JobState state) const {
    if (limit > 10000) throw Error(ErrorCode::kInvalidArgument, "limit: at most 10000");
    return jobs_.List(limit, state, caller.scoped ? &caller.tenant : nullptr);
}

ResultFile Operations::Result(const Caller& caller, const std::string& job_id) const {
    ResultFile r;
    r.job = GetJob(caller, job_id);
    if (r.job.state() != v1::SUCCEEDED)
        throw Error(ErrorCode::kFailedPrecondition, "job " + job_id + " is " +
                                                        v1::JobState_Name(r.job.state()) +
                                                        "; results exist only for SUCCEEDED jobs");
    r.key = worker::ResultBlobKey(job_id);
    const std::optional<std::uint64_t> size = store_.blobs().Size(r.key);
    if (!size) throw Error(ErrorCode::kNotFound, ResultGoneMessage(caller, job_id));
    if (retention_) retention_->Touch(r.key);  // LRU: downloaded now
    r.size = *size;
    r.filename = (r.job.type().empty() ? std::string("result") : r.job.type()) + "-" +
                 job_id.substr(0, 12) + r.job.result().extension();
    return r;
}

std::string Operations::ResultGoneMessage(const Caller& caller, const std::string& job_id) const {
    if (auto m = Evicted(caller, worker::ResultBlobKey(job_id), "result of job " + job_id))
        return *m + "; submit the job again to recompute it";
    return "result of job " + job_id + " is gone";
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

void Operations::ReserveInflight(std::uint64_t bytes, const std::string& id) {
    std::lock_guard lock(uploads_mutex_);
    const std::uint64_t max = limits_.max_upload_inflight_bytes;
    if (max != 0 && inflight_bytes_ + bytes > max)
        throw Error(ErrorCode::kResourceExhausted,
                    "upload " + id + ": " + std::to_string(inflight_bytes_) +
                        " bytes of uploads in progress are received and not yet stored; " +
                        std::to_string(bytes) + " more would pass --max-upload-inflight-mb (" +
                        std::to_string(max) + " bytes); retry later");
    inflight_bytes_ += bytes;
}

void Operations::ReleaseInflight(std::uint64_t bytes) {
    std::lock_guard lock(uploads_mutex_);
    inflight_bytes_ -= std::min(bytes, inflight_bytes_);
}

std::uint64_t Operations::InflightBytes() const {
    std::lock_guard lock(uploads_mutex_);
    return inflight_bytes_;
}

}  // namespace surfel::server
