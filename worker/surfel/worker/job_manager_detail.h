#pragma once
/// \file
/// Pieces the two modes of the JobManager share (job_manager.cpp, job_manager_shared.cpp).
/// Internal to worker/.

#include <atomic>
#include <chrono>
#include <string>

#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/job_manager.h"
#include "surfel/worker/retention.h"

namespace surfel::worker {

/// A job running in this process.
struct JobManager::RunState {
    v1::Job job;  ///< live copy: stage and fraction
    std::atomic<bool> cancel{false};
    std::atomic<bool> requeue{false};
    std::chrono::steady_clock::time_point deadline = std::chrono::steady_clock::time_point::max();
    // shared queue only
    std::string owner;              ///< the lease holder's name
    std::atomic<bool> lost{false};  ///< the lease was lost: stop, write nothing
};

}  // namespace surfel::worker

namespace surfel::worker::detail {

/// A new job id: "j" and 16 random hex digits.
std::string NewJobId();
/// The `failed` event of a FAILED or CANCELLED job (its status code and message).
v1::JobEvent FailedEvent(const v1::Job& job);
/// The `finished` event of a SUCCEEDED job (its result).
v1::JobEvent FinishedEvent(const v1::Job& job);
/// Stores a job's result bytes as its blob (ResultBlobKey), durable before it returns, and
/// returns their SHA-256 for JobResult.sha256. With `retention`, the bytes are reserved first
/// (evicting least recently used blobs; kResourceExhausted when they cannot fit) and recorded
/// after. A full disk is kResourceExhausted; no partial blob is left behind.
std::string StoreResult(Store& store, const std::string& job_id, std::string_view bytes,
                        Retention* retention);
/// Whether a job FindReusable returned may answer an identical submission: not a SUCCEEDED job
/// whose result blob is gone (evicted), which must run again.
bool StillReusable(const Store& store, const v1::Job& job);
/// Fills `job`'s result from what RunJob gave (media type, extension, size, report, points,
/// time) and marks it done (fraction 1, stage "done"); the state is the caller's to set.
void SetResult(v1::Job& job, const JobOutput& out);

/// Adds `nice` (0..19) to the calling thread's niceness (Linux: per thread). Best effort: a
/// failure is logged, never fatal.
void LowerJobThreadPriority(int nice);

}  // namespace surfel::worker::detail
