#pragma once
/// \file
/// The job queue and worker pool: jobs are persisted in the Store before Submit returns, run on
/// N worker threads through RunJob (job_kind.h), report progress to subscribers, and can be cancelled (the
/// core's progress hook returns false within one progress step).
///
/// Two modes, chosen by the store:
///  - single node (SQLite, Store::shared() false): an in-memory FIFO over the store; after a
///    restart, jobs left queued or running are queued again.
///  - shared queue (PostgreSQL): no in-memory queue. Worker threads claim with
///    Store::ClaimNext and hold a lease renewed by Heartbeat; every process sweeps expired
///    leases (RequeueExpired). Progress, cancel and "job finished" cross processes as hints
///    (Store::Publish/Listen) and are also polled every `poll_ms`, so a lost hint costs latency
///    only. Watchers of a job run elsewhere follow the table. See docs/scale-out.md.

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/store.h"

namespace surfel::worker {

class Retention;

struct ManagerOptions {
    std::size_t workers = 0;       ///< Worker threads; 0 = hardware concurrency.
    std::size_t max_queued = 256;  ///< Jobs waiting; more -> Error(kResourceExhausted).
    std::uint64_t max_points = 50'000'000;  ///< Parser limit when loading clouds.
    std::size_t cloud_cache = 8;   ///< Parsed clouds kept in memory.
    /// False: run no jobs here (an API node; a shared store only, where surfel-worker runs them).
    bool run_jobs = true;
    /// Shared queue: the lease of a claimed job (ms); renewed every lease_ms / 3.
    std::int64_t lease_ms = 30'000;
    /// Shared queue: leases that may expire before the job fails (>= 1).
    int max_attempts = 3;
    /// Shared queue: how often the tables are read when no hint arrived (ms): idle claims,
    /// cancel flags of running jobs, watched jobs run elsewhere.
    std::int64_t poll_ms = 250;
    /// Largest memory estimate (bytes, JobKind::EstimateMemory) a job may have; 0 = no limit.
    /// Single node: Submit refuses (kResourceExhausted) a job above it, or above what the
    /// running jobs' estimates leave of it; a queued job starts only when its estimate fits in
    /// what is left (docs/memory.md). Shared queue: Submit refuses above it, and a claimed job
    /// above the claiming process's limit fails with RESOURCE_EXHAUSTED before its work.
    std::uint64_t max_job_memory = 0;
    /// Niceness added to each job thread (and so to the TBB and Embree threads it starts, which
    /// inherit it): under load the API's calls, uploads and event streams keep their CPU share
    /// while jobs run on what is left (bench/results-load.md). 0 = as the process; 0..19.
    int job_nice = 10;
    /// Shared queue: the lease owner's prefix (default "<host>:<pid>"); thread i appends "/i".
    std::string worker_name;
    /// Disk quota and retention (retention.h): results are reserved there before they are
    /// written (kResourceExhausted when they cannot fit) and clouds marked used when loaded.
    /// Not owned; null = none.
    Retention* retention = nullptr;
};

/// Called for every event of one job (from worker threads or the caller of Submit/Cancel). Must
/// not block and must not call back into the manager.
using JobListener = std::function<void(const v1::JobEvent&)>;

/// Called after every state change (for metrics and logs); same rules as JobListener.
using TransitionHook = std::function<void(const v1::Job& job, v1::JobState from)>;

class JobManager {
public:
    JobManager(Store& store, ManagerOptions options, TransitionHook hook = {});
    ~JobManager();  ///< Shutdown(0) if still running.
    JobManager(const JobManager&) = delete;
    JobManager& operator=(const JobManager&) = delete;

    /// Queues again what the store holds unfinished, then starts the workers.
    void Start();

    /// Validates, checks the clouds exist (kNotFound), reuses an identical job of the same
    /// `tenant`, or persists and queues a new one owned by `tenant` (Job.tenant;
    /// kResourceExhausted when the queue is full). Whether the tenant owns the clouds is the
    /// caller's check (server/operations.cpp).
    v1::Job Submit(const v1::JobSpec& spec, const std::string& tenant = "");
    std::optional<v1::Job> Get(const std::string& id) const;
    /// Cancels a queued or running job (kNotFound when unknown); returns the job as it is then.
    v1::Job Cancel(const std::string& id);
    /// Newest first; only `*tenant`'s jobs unless `tenant` is null.
    std::vector<v1::Job> List(std::size_t limit, v1::JobState state,
                              const std::string* tenant = nullptr) const;

    /// Subscribes to a job's events; returns the job now (nullopt when unknown, then nothing is
    /// subscribed) and a token for Unsubscribe. Final jobs get no further events.
    std::optional<v1::Job> Subscribe(const std::string& id, JobListener listener, std::uint64_t* token);
    void Unsubscribe(const std::string& id, std::uint64_t token);

    std::size_t QueueDepth() const;
    std::size_t Running() const;
    /// Sum of the memory estimates of the jobs running here (bytes).
    std::uint64_t MemoryInUse() const;

    /// Stops taking jobs off the queue; running ones get `grace_ms` to finish, then are
    /// interrupted and left QUEUED in the store, to run again after a restart (shared queue:
    /// their leases are released, so another worker takes them at once).
    void Shutdown(std::int64_t grace_ms);

    /// Loads a stored cloud (cached). Throws kNotFound.
    std::shared_ptr<const PointCloud> LoadCloud(const std::string& id);

private:
    struct RunState;
    void WorkerLoop();
    void Execute(const std::string& id);
    void Transition(v1::Job& job, v1::JobState to);  ///< persists, notifies, calls the hook (lock held)
    void Notify(const std::string& id, const v1::JobEvent& event);  ///< lock held
    void NotifyQueuePositions();  ///< lock held
    std::optional<v1::Job> Current(const std::string& id) const;  ///< live copy or stored; lock held

    Store& store_;
    ManagerOptions options_;
    TransitionHook hook_;
    mutable std::mutex mutex_;
    std::condition_variable wake_;
    std::deque<std::string> queue_;
    std::map<std::string, std::shared_ptr<RunState>> running_;
    std::map<std::string, std::uint64_t> estimates_;  ///< queued and running jobs (single node)
    std::uint64_t memory_in_use_ = 0;                  ///< estimates of the running jobs
    /// The memory estimate of `spec` from its clouds' stored records (kNotFound naming the field).
    std::uint64_t EstimateFromRecords(const v1::JobSpec& spec) const;
    std::map<std::string, std::map<std::uint64_t, JobListener>> listeners_;
    std::uint64_t next_token_ = 1;
    bool stopping_ = false;
    std::vector<std::thread> workers_;

    // ---- the shared queue (job_manager_shared.cpp); used when store_.shared()
    struct Followed {
        v1::JobState state = v1::JOB_STATE_UNSPECIFIED;
        double fraction = -1;
    };
    void SharedStart();
    v1::Job SharedSubmit(const v1::JobSpec& spec, const std::string& tenant);
    v1::Job SharedCancel(const std::string& id);
    void SharedShutdown(std::int64_t grace_ms);
    void ClaimLoop(std::size_t index);
    void ExecuteLeased(LeasedJob leased);
    /// Writes a leased job's last record, retrying while the database is unreachable (up to
    /// `kFinishRetryMs`); false when the lease was lost.
    bool FinishLeased(const v1::Job& job, const std::string& owner);
    void MaintenanceLoop();
    void OnHint(const std::string& payload);
    void PublishHint(char kind, const std::string& id, const std::string& extra = "");
    /// Reads watched jobs run by other processes and sends their changes to the watchers.
    void FollowWatched(const std::vector<std::string>& ids);

    bool shared_ = false;
    std::string origin_;  ///< this process in hints (lease owner prefix)
    std::unique_ptr<Subscription> hints_;
    std::thread maintenance_;
    std::condition_variable maintenance_wake_;
    bool maintenance_stop_ = false;
    bool follow_all_ = false;
    std::vector<std::string> follow_dirty_;
    std::map<std::string, Followed> followed_;
    std::uint64_t claim_generation_ = 0;  ///< bumped by "new job" hints
    bool shut_down_ = false;

    std::mutex cache_mutex_;
    std::deque<std::pair<std::string, std::shared_ptr<const PointCloud>>> cache_;
};

/// The key that makes two jobs identical: SHA-256 of the spec without its timeout.
std::string JobKey(const v1::JobSpec& spec);
/// The reuse key of a tenant's job: JobKey for the default tenant "", else SHA-256 of the
/// tenant and JobKey, so that FindReusable never returns another tenant's job.
std::string TenantJobKey(const v1::JobSpec& spec, const std::string& tenant);

}  // namespace surfel::worker
