#pragma once
/// \file
/// The job queue and worker pool: jobs are persisted in the Store before Submit returns, run on
/// N worker threads through RunJob (job_kind.h), report progress to subscribers, and can be cancelled (the
/// core's progress hook returns false within one progress step). After a restart, jobs left
/// queued or running are queued again.

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

struct ManagerOptions {
    std::size_t workers = 0;       ///< Worker threads; 0 = hardware concurrency.
    std::size_t max_queued = 256;  ///< Jobs waiting; more -> Error(kResourceExhausted).
    std::uint64_t max_points = 50'000'000;  ///< Parser limit when loading clouds.
    std::size_t cloud_cache = 8;   ///< Parsed clouds kept in memory.
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

    /// Validates, checks the clouds exist (kNotFound), reuses an identical job, or persists and
    /// queues a new one (kResourceExhausted when the queue is full).
    v1::Job Submit(const v1::JobSpec& spec);
    std::optional<v1::Job> Get(const std::string& id) const;
    /// Cancels a queued or running job (kNotFound when unknown); returns the job as it is then.
    v1::Job Cancel(const std::string& id);
    std::vector<v1::Job> List(std::size_t limit, v1::JobState state) const;

    /// Subscribes to a job's events; returns the job now (nullopt when unknown, then nothing is
    /// subscribed) and a token for Unsubscribe. Final jobs get no further events.
    std::optional<v1::Job> Subscribe(const std::string& id, JobListener listener, std::uint64_t* token);
    void Unsubscribe(const std::string& id, std::uint64_t token);

    std::size_t QueueDepth() const;
    std::size_t Running() const;

    /// Stops taking jobs off the queue; running ones get `grace_ms` to finish, then are
    /// interrupted and left QUEUED in the store, to run again after a restart.
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
    std::map<std::string, std::map<std::uint64_t, JobListener>> listeners_;
    std::uint64_t next_token_ = 1;
    bool stopping_ = false;
    std::vector<std::thread> workers_;

    std::mutex cache_mutex_;
    std::deque<std::pair<std::string, std::shared_ptr<const PointCloud>>> cache_;
};

/// The key that makes two jobs identical: SHA-256 of the spec without its timeout.
std::string JobKey(const v1::JobSpec& spec);

}  // namespace surfel::worker
