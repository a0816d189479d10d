#pragma once
/// \file
/// Job events numbered for Server-Sent Events: one log per watched job, filled by one JobManager
/// subscription, so that every HTTP event stream of that job sees the same `id:` for the same
/// event and a client that reconnects with Last-Event-ID gets exactly what it missed.

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/job_manager.h"

namespace surfel::server {

/// One numbered event.
struct NumberedEvent {
    std::uint64_t id = 0;  ///< 1, 2, ... in the order the job's events happened
    v1::JobEvent event;
};

/// The events of one job. Consecutive progress events (queued, running) are coalesced: a newer
/// one replaces the older under its own, larger id, so the log stays small while a job runs and
/// a reader that resumes gets the latest progress.
class JobEventLog {
  public:
    enum class Wait { kEvents, kTimeout, kStopped };

    /// Appends `event` (from the manager's listener: short, never blocks).
    void Append(const v1::JobEvent& event);
    /// Waits up to `timeout` for events with id > `after`; copies them into `out` in order.
    Wait WaitAfter(std::uint64_t after, std::chrono::milliseconds timeout,
                   std::vector<NumberedEvent>* out);
    /// The id of the last event (0 when none).
    std::uint64_t LastId() const;
    /// True once the job's final event (finished or failed) is in the log.
    bool Final() const;
    /// Wakes every waiter for good (the server is stopping).
    void Stop();

  private:
    mutable std::mutex mutex_;
    std::condition_variable changed_;
    std::vector<NumberedEvent> events_;
    std::uint64_t next_id_ = 1;
    bool final_ = false, stopped_ = false;
};

/// The logs of the jobs watched over HTTP. Final logs no stream reads are dropped beyond
/// `keep_final` (oldest first). Must be destroyed before the JobManager.
class JobEventLogs {
  public:
    explicit JobEventLogs(worker::JobManager& jobs, std::size_t keep_final = 256);
    ~JobEventLogs();
    JobEventLogs(const JobEventLogs&) = delete;
    JobEventLogs& operator=(const JobEventLogs&) = delete;

    /// The log of `job_id`, subscribing on first use; nullptr for an unknown job.
    std::shared_ptr<JobEventLog> Open(const std::string& job_id);
    /// Stops every log (their waiters return kStopped) and every later one.
    void Stop();

  private:
    struct Entry {
        std::shared_ptr<JobEventLog> log;
        std::uint64_t token = 0;
        bool subscribed = false;
        std::uint64_t opened = 0;  // order of first use, for dropping the oldest
    };
    void DropOldFinal();  // mutex_ held

    worker::JobManager& jobs_;
    const std::size_t keep_final_;
    std::mutex mutex_;
    std::map<std::string, Entry> logs_;
    std::uint64_t opened_ = 0;
    bool stopped_ = false;
};

}  // namespace surfel::server
