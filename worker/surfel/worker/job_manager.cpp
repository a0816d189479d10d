#include "surfel/worker/job_manager.h"

#include <google/protobuf/io/coded_stream.h>
#include <google/protobuf/io/zero_copy_stream_impl_lite.h>
#include <spdlog/spdlog.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <random>

#include "surfel/base/error.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/file_bytes.h"
#include "surfel/worker/job_manager_detail.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/job_state.h"
#include "surfel/worker/status.h"

namespace surfel::worker {
namespace {
using Clock = std::chrono::steady_clock;
}  // namespace

namespace detail {

std::string NewJobId() {
    static std::mutex mutex;
    static std::mt19937_64 rng(std::random_device{}() ^ static_cast<std::uint64_t>(NowUnixMs()));
    std::lock_guard lock(mutex);
    char buf[20];
    std::snprintf(buf, sizeof buf, "j%016llx", static_cast<unsigned long long>(rng()));
    return buf;
}

v1::JobEvent FailedEvent(const v1::Job& job) {
    v1::JobEvent e;
    e.set_job_id(job.id());
    e.mutable_failed()->set_code(job.status_code());
    e.mutable_failed()->set_message(job.status_message());
    return e;
}

v1::JobEvent FinishedEvent(const v1::Job& job) {
    v1::JobEvent e;
    e.set_job_id(job.id());
    *e.mutable_finished() = job.result();
    return e;
}

std::string StoreResult(Store& store, const std::string& job_id, std::string_view bytes,
                        Retention* retention) {
    const std::string sha = Sha256Hex(bytes);
    const std::string key = ResultBlobKey(job_id);
    if (retention) retention->Reserve(bytes.size(), "result of job " + job_id);
    try {
        store.blobs().PutBytes(key, bytes, sha);
    } catch (...) {
        if (retention) retention->Release(bytes.size());
        throw;
    }
    if (retention) retention->Stored(key, bytes.size(), bytes.size());
    return sha;
}

bool StillReusable(const Store& store, const v1::Job& job) {
    return job.state() != v1::SUCCEEDED || store.blobs().Exists(ResultBlobKey(job.id()));
}

void SetResult(v1::Job& job, const JobOutput& out) {
    v1::JobResult* r = job.mutable_result();
    r->set_media_type(out.media_type);
    r->set_extension(out.extension);
    r->set_size_bytes(out.bytes.size());
    r->set_report_json(out.report.dump());
    r->set_points(out.points);
    r->set_time_ms(out.time_ms);
    job.set_fraction(1.0);
    job.set_stage("done");
}

void LowerJobThreadPriority(int nice) {
    if (nice <= 0) return;
    const auto tid = static_cast<id_t>(::syscall(SYS_gettid));
    errno = 0;
    const int now = ::getpriority(PRIO_PROCESS, tid);
    if (now == -1 && errno != 0) return;
    if (::setpriority(PRIO_PROCESS, tid, std::min(19, now + std::min(nice, 19))) != 0)
        spdlog::warn("job thread: cannot lower its priority by {}: {}", nice, std::strerror(errno));
}

}  // namespace detail

using detail::FailedEvent;
using detail::FinishedEvent;
using detail::NewJobId;

std::string JobKey(const v1::JobSpec& spec) {
    v1::JobSpec copy = spec;
    copy.clear_timeout_ms();
    std::string bytes;
    {
        google::protobuf::io::StringOutputStream raw(&bytes);
        google::protobuf::io::CodedOutputStream out(&raw);
        out.SetSerializationDeterministic(true);
        copy.SerializeToCodedStream(&out);
    }
    return Sha256Hex(bytes);
}

std::string TenantJobKey(const v1::JobSpec& spec, const std::string& tenant) {
    const std::string key = JobKey(spec);
    return tenant.empty() ? key : Sha256Hex("tenant\n" + tenant + "\n" + key);
}

JobManager::JobManager(Store& store, ManagerOptions options, TransitionHook hook)
    : store_(store), options_(options), hook_(std::move(hook)), shared_(store.shared()) {
    if (options_.workers == 0) options_.workers = std::max(1u, std::thread::hardware_concurrency());
    if (!options_.run_jobs && !shared_)
        throw Error(ErrorCode::kInvalidArgument,
                    "workers: 0 (an API node) needs a shared store (--store postgres://...); "
                    "with SQLite no other process would run the jobs");
}

JobManager::~JobManager() { Shutdown(0); }

void JobManager::Start() {
    if (shared_) return SharedStart();
    {
        std::lock_guard lock(mutex_);
        for (v1::Job& job : store_.Unfinished()) {
            if (job.state() == v1::RUNNING) {
                spdlog::info("job {}: was running when the server stopped; queued again", job.id());
                job.set_stage("");
                job.set_fraction(0);
                Transition(job, v1::QUEUED);
            }
            queue_.push_back(job.id());
            try {
                estimates_[job.id()] = EstimateFromRecords(job.spec());
            } catch (const std::exception& e) {  // its cloud is gone: the run fails and says so
                estimates_[job.id()] = 0;
            }
        }
        if (!queue_.empty()) spdlog::info("{} unfinished jobs queued again", queue_.size());
    }
    for (std::size_t i = 0; i < options_.workers; ++i) workers_.emplace_back([this] { WorkerLoop(); });
}

void JobManager::Transition(v1::Job& job, v1::JobState to) {
    const v1::JobState from = job.state();
    job.set_state(to);
    const std::int64_t now = NowUnixMs();
    if (to == v1::RUNNING) job.set_started_unix_ms(now);
    if (IsFinal(to)) job.set_finished_unix_ms(now);
    try {
        store_.PutJob(job, "");
    } catch (const std::exception& e) {
        // A worker thread must not die of it (a full disk under SQLite, docs/retention.md): the
        // change is kept in memory and its watchers told; the store keeps the previous state,
        // so after a restart an unfinished job runs again.
        spdlog::error("job {}: cannot record {} in the store: {}", job.id(), v1::JobState_Name(to),
                      e.what());
    }
    if (hook_) hook_(job, from);
}

void JobManager::Notify(const std::string& id, const v1::JobEvent& event) {
    auto it = listeners_.find(id);
    if (it == listeners_.end()) return;
    for (auto& [token, listener] : it->second) listener(event);
}

void JobManager::NotifyQueuePositions() {
    std::uint32_t position = 0;
    for (const std::string& id : queue_) {
        if (listeners_.count(id)) {
            v1::JobEvent e;
            e.set_job_id(id);
            e.mutable_queued()->set_position(position);
            Notify(id, e);
        }
        ++position;
    }
}

std::uint64_t JobManager::EstimateFromRecords(const v1::JobSpec& spec) const {
    std::vector<CloudFacts> facts;
    for (const CloudInput& input : KindOf(spec).Inputs(spec)) {
        const std::optional<v1::Cloud> cloud = store_.FindCloud(input.id);
        if (!cloud)
            throw Error(ErrorCode::kNotFound, input.field + ": cloud " + input.id + " not found (upload it first)");
        facts.push_back(FactsOf(*cloud));
    }
    return EstimateJobMemory(spec, facts);
}

std::uint64_t JobManager::MemoryInUse() const {
    std::lock_guard lock(mutex_);
    return memory_in_use_;
}

v1::Job JobManager::Submit(const v1::JobSpec& spec, const std::string& tenant) {
    if (shared_) return SharedSubmit(spec, tenant);
    ValidateSpec(spec);
    const JobKind& kind = KindOf(spec);
    CheckOutputPoints(spec, options_.max_points);
    const std::uint64_t estimate = EstimateFromRecords(spec);
    const std::string key = TenantJobKey(spec, tenant);
    std::lock_guard lock(mutex_);
    if (stopping_) throw Error(ErrorCode::kUnavailable, "the server is shutting down");
    if (auto reused = store_.FindReusable(key); reused && detail::StillReusable(store_, *reused)) {
        if (auto it = running_.find(reused->id()); it != running_.end()) *reused = it->second->job;
        reused->set_reused(true);
        spdlog::info("job {}: reused for an identical submission", reused->id());
        return *reused;
    }
    CheckJobMemory(spec, estimate, options_.max_job_memory, "--max-job-memory", memory_in_use_);
    if (queue_.size() >= options_.max_queued)
        throw Error(ErrorCode::kResourceExhausted,
                    "job queue is full (" + std::to_string(queue_.size()) + " jobs waiting); retry later");
    v1::Job job;
    job.set_id(NewJobId());
    job.set_type(std::string(kind.Name()));
    *job.mutable_spec() = spec;
    job.set_tenant(tenant);
    job.set_created_unix_ms(NowUnixMs());
    job.set_state(v1::QUEUED);
    store_.PutJob(job, key);  // persisted before it is acknowledged
    if (hook_) hook_(job, v1::JOB_STATE_UNSPECIFIED);
    queue_.push_back(job.id());
    estimates_[job.id()] = estimate;
    spdlog::info("job {}: {} queued at position {} (memory estimate {})", job.id(), job.type(), queue_.size() - 1,
                 MiB(estimate));
    wake_.notify_one();
    return job;
}

std::optional<v1::Job> JobManager::Current(const std::string& id) const {
    if (auto it = running_.find(id); it != running_.end()) return it->second->job;
    return store_.FindJob(id);
}

std::optional<v1::Job> JobManager::Get(const std::string& id) const {
    std::lock_guard lock(mutex_);
    return Current(id);
}

std::vector<v1::Job> JobManager::List(std::size_t limit, v1::JobState state,
                                      const std::string* tenant) const {
    std::vector<v1::Job> jobs = store_.ListJobs(limit ? limit : 100, state, tenant);
    std::lock_guard lock(mutex_);
    for (v1::Job& j : jobs)
        if (auto it = running_.find(j.id()); it != running_.end()) j = it->second->job;  // live progress
    return jobs;
}

v1::Job JobManager::Cancel(const std::string& id) {
    if (shared_) return SharedCancel(id);
    std::lock_guard lock(mutex_);
    if (auto it = running_.find(id); it != running_.end()) {
        it->second->cancel = true;
        spdlog::info("job {}: cancel requested while running", id);
        return it->second->job;
    }
    auto job = store_.FindJob(id);
    if (!job) throw Error(ErrorCode::kNotFound, "job " + id + " not found");
    if (job->state() == v1::QUEUED) {
        queue_.erase(std::remove(queue_.begin(), queue_.end(), id), queue_.end());
        estimates_.erase(id);
        wake_.notify_all();  // the next job may fit now
        job->set_status_code(grpc::StatusCode::CANCELLED);
        job->set_status_message("cancelled while queued");
        Transition(*job, v1::CANCELLED);
        spdlog::info("job {}: cancelled while queued", id);
        Notify(id, FailedEvent(*job));
        listeners_.erase(id);
        NotifyQueuePositions();
    }
    return *job;
}

std::optional<v1::Job> JobManager::Subscribe(const std::string& id, JobListener listener, std::uint64_t* token) {
    std::lock_guard lock(mutex_);
    std::optional<v1::Job> job = Current(id);
    if (!job) return std::nullopt;
    if (IsFinal(job->state())) return job;
    *token = next_token_++;
    v1::JobEvent first;
    first.set_job_id(id);
    *first.mutable_state() = *job;
    listener(first);
    if (shared_) followed_[id] = Followed{job->state(), job->fraction()};
    if (job->state() == v1::QUEUED) {
        const auto pos = shared_ ? store_.QueuePosition(id)
                                 : std::find(queue_.begin(), queue_.end(), id) - queue_.begin();
        v1::JobEvent q;
        q.set_job_id(id);
        q.mutable_queued()->set_position(static_cast<std::uint32_t>(pos));
        listener(q);
    }
    listeners_[id][*token] = std::move(listener);
    return job;
}

void JobManager::Unsubscribe(const std::string& id, std::uint64_t token) {
    std::lock_guard lock(mutex_);
    auto it = listeners_.find(id);
    if (it == listeners_.end()) return;
    it->second.erase(token);
    if (it->second.empty()) {
        listeners_.erase(it);
        followed_.erase(id);
    }
}

std::size_t JobManager::QueueDepth() const {
    if (shared_) {
        try {
            return store_.CountQueued();
        } catch (const Error&) {  // the database is unreachable: nothing known
            return 0;
        }
    }
    std::lock_guard lock(mutex_);
    return queue_.size();
}

std::size_t JobManager::Running() const {
    std::lock_guard lock(mutex_);
    return running_.size();
}

void JobManager::WorkerLoop() {
    detail::LowerJobThreadPriority(options_.job_nice);
    // The queue's head starts when its estimate fits in what the running jobs leave of
    // max_job_memory (or nothing runs): FIFO, so a large job is not starved by small ones.
    auto fits = [&] {
        if (queue_.empty()) return false;
        if (options_.max_job_memory == 0 || memory_in_use_ == 0) return true;
        const std::uint64_t estimate = estimates_[queue_.front()];
        return memory_in_use_ + estimate <= options_.max_job_memory;
    };
    for (;;) {
        std::string id;
        std::uint64_t estimate = 0;
        {
            std::unique_lock lock(mutex_);
            wake_.wait(lock, [&] { return stopping_ || fits(); });
            if (stopping_) return;
            id = queue_.front();
            queue_.pop_front();
            estimate = estimates_[id];
            memory_in_use_ += estimate;
            NotifyQueuePositions();
        }
        Execute(id);
        {
            std::lock_guard lock(mutex_);
            memory_in_use_ -= estimate;
            estimates_.erase(id);
        }
        wake_.notify_all();
    }
}

std::shared_ptr<const PointCloud> JobManager::LoadCloud(const std::string& id) {
    if (options_.retention) options_.retention->Touch(CloudBlobKey(id));  // LRU: used now
    {
        std::lock_guard lock(cache_mutex_);
        for (auto& [cid, cloud] : cache_)
            if (cid == id) return cloud;
    }
    if (!store_.FindCloud(id)) {
        if (options_.retention)
            if (auto m = options_.retention->EvictedMessage(CloudBlobKey(id), "cloud " + id, nullptr))
                throw Error(ErrorCode::kNotFound, *m);
        throw Error(ErrorCode::kNotFound, "cloud " + id + " not found");
    }
    PlyReadOptions limits;
    limits.max_points = options_.max_points;
    // Hashed while read (one pass over the bytes): a cloud's id is its SHA-256, so a flipped
    // byte on disk fails the job with DATA_LOSS instead of giving a wrong result.
    const std::string bytes = ReadVerified(store_.blobs(), CloudBlobKey(id), id, "cloud " + id);
    auto cloud = std::make_shared<const PointCloud>(ParsePointCloud(bytes, "cloud " + id, limits));
    std::lock_guard lock(cache_mutex_);
    cache_.emplace_front(id, cloud);
    while (cache_.size() > options_.cloud_cache) cache_.pop_back();
    return cloud;
}

void JobManager::Execute(const std::string& id) {
    auto run = std::make_shared<RunState>();
    {
        std::lock_guard lock(mutex_);
        auto job = store_.FindJob(id);
        if (!job || job->state() != v1::QUEUED) return;  // cancelled meanwhile
        run->job = *job;
        if (job->spec().timeout_ms() > 0)
            run->deadline = Clock::now() + std::chrono::milliseconds(job->spec().timeout_ms());
        run->job.set_stage("loading");
        Transition(run->job, v1::RUNNING);
        running_[id] = run;
        v1::JobEvent e;
        e.set_job_id(id);
        e.mutable_running()->set_stage("loading");
        Notify(id, e);
    }
    spdlog::info("job {}: {} running", id, run->job.type());
    const std::string stage(KindOf(run->job.spec()).Stage());
    const auto started = Clock::now();
    auto progress = [&](double fraction) {
        if (run->cancel || Clock::now() > run->deadline) return false;
        std::lock_guard lock(mutex_);
        run->job.set_stage(stage);
        run->job.set_fraction(fraction);
        v1::JobEvent e;
        e.set_job_id(id);
        e.mutable_running()->set_stage(stage);
        e.mutable_running()->set_fraction(fraction);
        Notify(id, e);
        return true;
    };
    v1::Job done;
    bool requeued = false;
    try {
        const JobOutput out =
            RunJob(run->job.spec(), [&](const std::string& cloud_id) { return LoadCloud(cloud_id); }, progress);
        const std::string sha = detail::StoreResult(store_, id, out.bytes, options_.retention);  // durable first
        std::lock_guard lock(mutex_);
        done = run->job;
        detail::SetResult(done, out);
        done.mutable_result()->set_sha256(sha);
        Transition(done, v1::SUCCEEDED);
        Notify(id, FinishedEvent(done));
        running_.erase(id);  // in the same critical section: Get never sees a stale RUNNING
        listeners_.erase(id);
    } catch (...) {
        grpc::Status status = CurrentExceptionStatus();
        std::lock_guard lock(mutex_);
        done = run->job;
        if (status.error_code() == grpc::StatusCode::CANCELLED) {
            if (run->requeue) {
                requeued = true;
            } else if (!run->cancel && Clock::now() > run->deadline) {
                status = grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED,
                                      "job ran past its timeout of " + std::to_string(done.spec().timeout_ms()) +
                                          " ms (" + status.error_message() + ")");
            } else {
                status = grpc::Status(grpc::StatusCode::CANCELLED, "cancelled by request (" +
                                                                       status.error_message() + ")");
            }
        }
        if (requeued) {
            done.set_stage("");
            done.set_fraction(0);
            Transition(done, v1::QUEUED);
        } else {
            done.set_status_code(status.error_code());
            done.set_status_message(status.error_message());
            Transition(done, status.error_code() == grpc::StatusCode::CANCELLED ? v1::CANCELLED : v1::FAILED);
            Notify(id, FailedEvent(done));
            listeners_.erase(id);
        }
        running_.erase(id);
    }
    const double seconds = std::chrono::duration<double>(Clock::now() - started).count();
    if (requeued)
        spdlog::warn("job {}: interrupted by shutdown after {:.3f} s; will run again after a restart", id, seconds);
    else
        spdlog::info("job {}: {} in {:.3f} s{}{}", id, v1::JobState_Name(done.state()), seconds,
                     done.status_message().empty() ? "" : ": ", done.status_message());
}

void JobManager::Shutdown(std::int64_t grace_ms) {
    if (shared_) return SharedShutdown(grace_ms);
    {
        std::lock_guard lock(mutex_);
        if (stopping_ && workers_.empty()) return;
        stopping_ = true;
    }
    wake_.notify_all();
    const auto until = Clock::now() + std::chrono::milliseconds(std::max<std::int64_t>(0, grace_ms));
    while (Clock::now() < until && Running() > 0) std::this_thread::sleep_for(std::chrono::milliseconds(10));
    {
        std::lock_guard lock(mutex_);
        for (auto& [id, run] : running_) {
            run->requeue = true;
            run->cancel = true;
        }
    }
    for (auto& t : workers_)
        if (t.joinable()) t.join();
    workers_.clear();
}

}  // namespace surfel::worker
