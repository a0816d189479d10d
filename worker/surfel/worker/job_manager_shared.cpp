// The JobManager over a shared store (PostgreSQL): claims with leases instead of an in-memory
// queue, hints across processes, watchers that follow jobs other processes run. The design is in
// docs/scale-out.md.
//
// Hints are one line "<kind> <origin> <job id> [<fraction> <stage>]", kind one of
//   n  a job was queued (claimers wake)        q  a job was queued again (claimers wake)
//   s  a job started                           p  progress (fraction, stage)
//   c  cancel requested (its leaseholder stops) d  a job reached a final state
// `origin` is the publishing process, so a process skips its own progress hints. A hint only
// says "look now": every receiver reads the table (or polls it every poll_ms without hints).
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <sstream>

#include "surfel/base/error.h"
#include "surfel/io/file_bytes.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/job_manager.h"
#include "surfel/worker/job_manager_detail.h"
#include "surfel/worker/job_state.h"
#include "surfel/worker/status.h"

namespace surfel::worker {
namespace {

using Clock = std::chrono::steady_clock;
using std::chrono::milliseconds;

/// How long a finished job's last write is retried while the database is down; past it the
/// lease expires and another worker runs the job again (the same bytes).
constexpr std::int64_t kFinishRetryMs = 120'000;

std::string DefaultWorkerName() {
    char host[256] = {0};
    if (::gethostname(host, sizeof host - 1) != 0) std::snprintf(host, sizeof host, "host");
    return std::string(host) + ":" + std::to_string(::getpid());
}

/// Logs a database outage once per `every`, not once per attempt.
class OutageLog {
  public:
    void Warn(const char* what, const std::exception& e) {
        const auto now = Clock::now();
        if (now - last_ < std::chrono::seconds(5)) return;
        last_ = now;
        spdlog::warn("{}: {} (retrying with backoff)", what, e.what());
    }

  private:
    Clock::time_point last_{};
};

}  // namespace

using detail::FailedEvent;
using detail::FinishedEvent;
using detail::NewJobId;

void JobManager::PublishHint(char kind, const std::string& id, const std::string& extra) {
    std::string payload(1, kind);
    payload += ' ';
    payload += origin_;
    payload += ' ';
    payload += id;
    if (!extra.empty()) payload += ' ' + extra;
    try {
        store_.Publish(payload);
    } catch (const std::exception& e) {  // a hint is an optimisation: the pollers see it later
        spdlog::debug("hint {} not sent: {}", payload, e.what());
    }
}

void JobManager::SharedStart() {
    origin_ = options_.worker_name.empty() ? DefaultWorkerName() : options_.worker_name;
    hints_ = store_.Listen([this](const std::string& payload) { OnHint(payload); });
    maintenance_ = std::thread([this] { MaintenanceLoop(); });
    if (options_.run_jobs)
        for (std::size_t i = 0; i < options_.workers; ++i)
            workers_.emplace_back([this, i] { ClaimLoop(i); });
    spdlog::info("shared queue: {} claiming threads as {} (lease {} ms, {} attempts)",
                 options_.run_jobs ? options_.workers : 0, origin_, options_.lease_ms,
                 options_.max_attempts);
}

// ---- hints from other processes (the listener's thread)

void JobManager::OnHint(const std::string& payload) {
    std::lock_guard lock(mutex_);
    if (payload.empty()) {  // reconnected: anything may have been missed
        ++claim_generation_;
        wake_.notify_all();
        follow_all_ = true;
        maintenance_wake_.notify_one();
        return;
    }
    std::istringstream in(payload);
    char kind = 0;
    std::string origin, id;
    in >> kind >> origin >> id;
    switch (kind) {
        case 'n':
        case 'q':
            ++claim_generation_;
            wake_.notify_all();
            break;
        case 'c':
            if (auto it = running_.find(id); it != running_.end()) {
                it->second->cancel = true;
                spdlog::info("job {}: cancel requested through another server", id);
            }
            break;
        case 'p': {
            if (origin == origin_ || running_.count(id) || !listeners_.count(id)) break;
            double fraction = 0;
            std::string stage;
            in >> fraction >> stage;
            v1::JobEvent e;
            e.set_job_id(id);
            e.mutable_running()->set_stage(stage);
            e.mutable_running()->set_fraction(fraction);
            Notify(id, e);
            followed_[id] = Followed{v1::RUNNING, fraction};
            return;
        }
        default:
            break;
    }
    if (listeners_.count(id) && !running_.count(id)) {
        follow_dirty_.push_back(id);
        maintenance_wake_.notify_one();
    }
}

// ---- watchers of jobs other processes run

void JobManager::FollowWatched(const std::vector<std::string>& ids) {
    for (const std::string& id : ids) {
        std::optional<v1::Job> job = store_.FindJob(id);  // no lock held while reading
        if (!job) continue;
        std::lock_guard lock(mutex_);
        if (!listeners_.count(id) || running_.count(id)) continue;  // gone, or ours now
        Followed& seen = followed_[id];
        v1::JobEvent e;
        e.set_job_id(id);
        if (IsFinal(job->state())) {
            Notify(id, job->state() == v1::SUCCEEDED ? FinishedEvent(*job) : FailedEvent(*job));
            listeners_.erase(id);
            followed_.erase(id);
            continue;
        }
        if (job->state() == v1::RUNNING &&
            (seen.state != v1::RUNNING || job->fraction() > seen.fraction)) {
            e.mutable_running()->set_stage(job->stage());
            e.mutable_running()->set_fraction(job->fraction());
            Notify(id, e);
        } else if (job->state() == v1::QUEUED && seen.state == v1::RUNNING) {
            *e.mutable_state() = *job;  // requeued after its worker was lost
            Notify(id, e);
        }
        seen = Followed{job->state(), std::max(seen.fraction, job->fraction())};
    }
}

// ---- the maintenance thread: follow, cancel flags, heartbeats, expired leases

void JobManager::MaintenanceLoop() {
    OutageLog outage;
    const auto heartbeat_every = milliseconds(std::max<std::int64_t>(options_.lease_ms / 3, 50));
    const auto sweep_every =
        milliseconds(std::clamp<std::int64_t>(options_.lease_ms / 4, 100, 2000));
    const auto poll_every = milliseconds(std::max<std::int64_t>(options_.poll_ms, 10));
    auto next_heartbeat = Clock::now() + heartbeat_every;
    auto next_sweep = Clock::now();
    auto next_poll = Clock::now() + poll_every;
    for (;;) {
        std::vector<std::string> follow;
        std::vector<std::pair<std::string, std::shared_ptr<RunState>>> runs;
        bool poll = false;
        {
            std::unique_lock lock(mutex_);
            maintenance_wake_.wait_until(
                lock, std::min({next_heartbeat, next_sweep, next_poll}),
                [&] { return maintenance_stop_ || follow_all_ || !follow_dirty_.empty(); });
            if (maintenance_stop_) return;
            poll = follow_all_ || Clock::now() >= next_poll;
            if (poll) {
                for (const auto& [id, l] : listeners_)
                    if (!running_.count(id)) follow.push_back(id);
                follow_all_ = false;
                next_poll = Clock::now() + poll_every;
            } else {
                follow.swap(follow_dirty_);
            }
            follow_dirty_.clear();
            for (const auto& r : running_) runs.push_back(r);
        }
        try {
            FollowWatched(follow);
            if (poll) {
                // The cancel flag, for a cancel whose hint never came.
                for (auto& [id, run] : runs)
                    if (!run->cancel && store_.CancelRequested(id)) {
                        spdlog::info("job {}: cancel request found in the table", id);
                        run->cancel = true;
                    }
            }
            if (Clock::now() >= next_heartbeat) {
                next_heartbeat = Clock::now() + heartbeat_every;
                for (auto& [id, run] : runs)
                    if (!store_.Heartbeat(id, run->owner, options_.lease_ms) && !run->lost) {
                        spdlog::warn(
                            "job {}: lease lost (expired and taken back); stopping it here", id);
                        run->lost = true;
                    }
            }
            if (Clock::now() >= next_sweep) {
                next_sweep = Clock::now() + sweep_every;
                for (const v1::Job& job :
                     store_.RequeueExpired(NowUnixMs(), options_.max_attempts)) {
                    if (job.state() == v1::QUEUED) {
                        spdlog::warn("job {}: its lease expired (worker gone); queued again",
                                     job.id());
                        PublishHint('q', job.id());
                    } else {
                        spdlog::warn("job {}: {}", job.id(), job.status_message());
                        if (hook_) hook_(job, v1::RUNNING);
                        PublishHint('d', job.id());
                    }
                }
            }
        } catch (const std::exception& e) {
            outage.Warn("shared queue maintenance", e);
            std::unique_lock lock(mutex_);
            maintenance_wake_.wait_for(lock, milliseconds(200), [&] { return maintenance_stop_; });
        }
    }
}

// ---- submit, cancel

v1::Job JobManager::SharedSubmit(const v1::JobSpec& spec, const std::string& tenant) {
    ValidateSpec(spec);
    const JobKind& kind = KindOf(spec);
    CheckOutputPoints(spec, options_.max_points);
    const std::uint64_t estimate = EstimateFromRecords(spec);
    const std::string key = TenantJobKey(spec, tenant);
    {
        std::lock_guard lock(mutex_);
        if (stopping_) throw Error(ErrorCode::kUnavailable, "the server is shutting down");
    }
    if (auto reused = store_.FindReusable(key); reused && detail::StillReusable(store_, *reused)) {
        reused->set_reused(true);
        spdlog::info("job {}: reused for an identical submission", reused->id());
        return *reused;
    }
    CheckJobMemory(spec, estimate, options_.max_job_memory, "--max-job-memory");
    const std::size_t queued = store_.CountQueued();
    if (queued >= options_.max_queued)
        throw Error(ErrorCode::kResourceExhausted,
                    "job queue is full (" + std::to_string(queued) + " jobs waiting); retry later");
    v1::Job job;
    job.set_id(NewJobId());
    job.set_type(std::string(kind.Name()));
    *job.mutable_spec() = spec;
    job.set_tenant(tenant);
    job.set_created_unix_ms(NowUnixMs());
    job.set_state(v1::QUEUED);
    store_.PutJob(job, key);  // persisted (committed) before it is acknowledged
    if (hook_) hook_(job, v1::JOB_STATE_UNSPECIFIED);
    PublishHint('n', job.id());
    {
        std::lock_guard lock(mutex_);  // a claimer of this process need not wait for the hint
        ++claim_generation_;
        wake_.notify_one();
    }
    spdlog::info("job {}: {} queued (shared)", job.id(), job.type());
    return job;
}

v1::Job JobManager::SharedCancel(const std::string& id) {
    {
        std::lock_guard lock(mutex_);
        if (auto it = running_.find(id); it != running_.end()) {
            it->second->cancel = true;
            spdlog::info("job {}: cancel requested while running here", id);
            return it->second->job;
        }
    }
    const std::optional<v1::Job> before = store_.FindJob(id);
    if (!before) throw Error(ErrorCode::kNotFound, "job " + id + " not found");
    std::optional<v1::Job> job = store_.RequestCancel(id);
    if (!job) throw Error(ErrorCode::kNotFound, "job " + id + " not found");
    if (job->state() == v1::CANCELLED && before->state() == v1::QUEUED) {
        spdlog::info("job {}: cancelled while queued", id);
        PublishHint('d', id);
        std::lock_guard lock(mutex_);
        if (hook_) hook_(*job, v1::QUEUED);
        Notify(id, FailedEvent(*job));
        listeners_.erase(id);
        followed_.erase(id);
    } else if (job->state() == v1::RUNNING) {
        spdlog::info("job {}: cancel requested; its worker stops it", id);
        PublishHint('c', id);
    }
    return *job;
}

// ---- claiming and running

void JobManager::ClaimLoop(std::size_t index) {
    detail::LowerJobThreadPriority(options_.job_nice);
    const std::string owner = origin_ + "/" + std::to_string(index);
    OutageLog outage;
    std::int64_t backoff_ms = 100;
    for (;;) {
        std::uint64_t generation;
        {
            std::lock_guard lock(mutex_);
            if (stopping_) return;
            generation = claim_generation_;
        }
        std::optional<LeasedJob> leased;
        try {
            leased = store_.ClaimNext(owner, options_.lease_ms);
            backoff_ms = 100;
        } catch (const std::exception& e) {
            outage.Warn("claiming a job", e);
            std::unique_lock lock(mutex_);
            wake_.wait_for(lock, milliseconds(backoff_ms), [&] { return stopping_; });
            backoff_ms = std::min<std::int64_t>(backoff_ms * 2, 2000);
            continue;
        }
        if (!leased) {
            std::unique_lock lock(mutex_);
            wake_.wait_for(lock, milliseconds(options_.poll_ms),
                           [&] { return stopping_ || claim_generation_ != generation; });
            continue;
        }
        ExecuteLeased(std::move(*leased));
    }
}

bool JobManager::FinishLeased(const v1::Job& job, const std::string& owner) {
    const auto until = Clock::now() + milliseconds(kFinishRetryMs);
    std::int64_t backoff_ms = 100;
    OutageLog outage;
    for (;;) {
        try {
            return store_.PutLeasedJob(job, owner);
        } catch (const Error& e) {
            if (e.code() != ErrorCode::kUnavailable || Clock::now() > until) throw;
            outage.Warn("writing a finished job", e);
            std::this_thread::sleep_for(milliseconds(backoff_ms));
            backoff_ms = std::min<std::int64_t>(backoff_ms * 2, 2000);
        }
    }
}

void JobManager::ExecuteLeased(LeasedJob leased) {
    auto run = std::make_shared<RunState>();
    const std::string id = leased.job.id();
    run->job = std::move(leased.job);
    run->owner = leased.owner;
    if (run->job.spec().timeout_ms() > 0)
        run->deadline = Clock::now() + milliseconds(run->job.spec().timeout_ms());
    run->job.set_stage("loading");
    {
        std::lock_guard lock(mutex_);
        running_[id] = run;
        if (hook_) hook_(run->job, v1::QUEUED);
        v1::JobEvent e;
        e.set_job_id(id);
        e.mutable_running()->set_stage("loading");
        Notify(id, e);
    }
    PublishHint('s', id);
    spdlog::info("job {}: {} running as {} (attempt {})", id, run->job.type(), run->owner,
                 leased.attempts + 1);
    const std::string stage(KindOf(run->job.spec()).Stage());
    const auto started = Clock::now();
    auto last_hint = Clock::time_point{};
    auto last_write = Clock::now();
    auto progress = [&](double fraction) {
        if (run->cancel || run->lost || Clock::now() > run->deadline) return false;
        v1::Job snapshot;
        {
            std::lock_guard lock(mutex_);
            run->job.set_stage(stage);
            run->job.set_fraction(fraction);
            v1::JobEvent e;
            e.set_job_id(id);
            e.mutable_running()->set_stage(stage);
            e.mutable_running()->set_fraction(fraction);
            Notify(id, e);
            snapshot = run->job;
        }
        const auto now = Clock::now();
        if (now - last_hint >= milliseconds(100)) {  // progress hints: at most 10 a second
            last_hint = now;
            char buf[32];
            std::snprintf(buf, sizeof buf, "%.4f", fraction);
            PublishHint('p', id, std::string(buf) + " " + stage);
        }
        if (now - last_write >= milliseconds(1000)) {  // the record: once a second
            last_write = now;
            try {
                if (!store_.PutLeasedJob(snapshot, run->owner)) run->lost = true;
            } catch (const std::exception&) {  // the database is down: keep computing
            }
        }
        return !run->lost;
    };
    v1::Job done;
    enum class End { kFinal, kRelease, kLost } end = End::kFinal;
    try {
        const JobOutput out = RunJob(
            run->job.spec(), [&](const std::string& cloud_id) { return LoadCloud(cloud_id); },
            progress, [&](std::uint64_t estimate) {
                CheckJobMemory(run->job.spec(), estimate, options_.max_job_memory,
                               "--max-job-memory of " + run->owner);
            });
        if (run->lost) throw Error(ErrorCode::kCancelled, "lease lost");
        // Durable and atomic (dir: temp + fsync + rename; large objects: one transaction):
        // complete before any record names it. A second run of the same
        // job writes the same bytes.
        const std::string sha = detail::StoreResult(store_, id, out.bytes, options_.retention);
        std::lock_guard lock(mutex_);
        done = run->job;
        detail::SetResult(done, out);
        done.mutable_result()->set_sha256(sha);
        done.set_state(v1::SUCCEEDED);
    } catch (...) {
        grpc::Status status = CurrentExceptionStatus();
        std::lock_guard lock(mutex_);
        done = run->job;
        if (run->lost) {
            end = End::kLost;
        } else if (status.error_code() == grpc::StatusCode::CANCELLED && run->requeue) {
            end = End::kRelease;
        } else if (status.error_code() == grpc::StatusCode::UNAVAILABLE) {
            end = End::kRelease;  // the database (or a cloud's bytes) went away: run it again
            spdlog::warn("job {}: {}; giving it back to the queue", id, status.error_message());
        } else {
            if (status.error_code() == grpc::StatusCode::CANCELLED) {
                if (!run->cancel && Clock::now() > run->deadline)
                    status = grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED,
                                          "job ran past its timeout of " +
                                              std::to_string(done.spec().timeout_ms()) + " ms (" +
                                              status.error_message() + ")");
                else
                    status = grpc::Status(grpc::StatusCode::CANCELLED,
                                          "cancelled by request (" + status.error_message() + ")");
            }
            done.set_status_code(status.error_code());
            done.set_status_message(status.error_message());
            done.set_state(status.error_code() == grpc::StatusCode::CANCELLED ? v1::CANCELLED
                                                                              : v1::FAILED);
        }
    }
    if (end == End::kRelease) {
        done.set_state(v1::QUEUED);
        done.set_stage("");
        done.set_fraction(0);
        done.set_started_unix_ms(0);
    } else if (end == End::kFinal) {
        done.set_finished_unix_ms(NowUnixMs());
    }
    bool written = false;
    if (end != End::kLost) {
        try {
            written = FinishLeased(done, run->owner);
        } catch (const std::exception& e) {
            spdlog::error(
                "job {}: its end could not be written ({}); the lease will expire and "
                "the job run again",
                id, e.what());
        }
    }
    {
        std::lock_guard lock(mutex_);
        if (written && end == End::kFinal) {
            if (hook_) hook_(done, v1::RUNNING);
            Notify(id, done.state() == v1::SUCCEEDED ? FinishedEvent(done) : FailedEvent(done));
            listeners_.erase(id);
            followed_.erase(id);
        }
        running_.erase(id);  // watchers of ours left now follow the table
        if (listeners_.count(id)) {
            follow_dirty_.push_back(id);
            maintenance_wake_.notify_one();
        }
    }
    if (written) PublishHint(end == End::kFinal ? 'd' : 'q', id);
    const double seconds = std::chrono::duration<double>(Clock::now() - started).count();
    if (end == End::kLost || (!written && end == End::kFinal))
        spdlog::warn(
            "job {}: lease lost after {:.3f} s; another worker runs it (its result is "
            "the same bytes)",
            id, seconds);
    else if (end == End::kRelease)
        spdlog::warn("job {}: released after {:.3f} s; queued again for any worker", id, seconds);
    else
        spdlog::info("job {}: {} in {:.3f} s{}{}", id, v1::JobState_Name(done.state()), seconds,
                     done.status_message().empty() ? "" : ": ", done.status_message());
}

// ---- shutdown

void JobManager::SharedShutdown(std::int64_t grace_ms) {
    {
        std::lock_guard lock(mutex_);
        if (shut_down_) return;
        shut_down_ = true;
        stopping_ = true;
    }
    wake_.notify_all();
    const auto until = Clock::now() + milliseconds(std::max<std::int64_t>(0, grace_ms));
    while (Clock::now() < until && Running() > 0) std::this_thread::sleep_for(milliseconds(10));
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
    {
        std::lock_guard lock(mutex_);
        maintenance_stop_ = true;
    }
    maintenance_wake_.notify_all();
    if (maintenance_.joinable()) maintenance_.join();
    hints_.reset();
}

}  // namespace surfel::worker
