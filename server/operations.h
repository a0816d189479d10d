#pragma once
/// \file
/// The operations of surfel.v1, free of any transport: the gRPC front (SurfelService and its
/// reactors) and the HTTP/JSON front (HttpFront) translate their requests into these calls and
/// their answers back, and hold no logic of their own. Failures are thrown as surfel::Error with
/// a code (worker/status.h maps it to a gRPC status, the HTTP front to an HTTP status).

#include <cstdint>
#include <mutex>
#include <set>
#include <string>
#include <vector>

#include "executor.h"
#include "metrics.h"
#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/job_manager.h"
#include "surfel/worker/store.h"

namespace surfel::server {

/// Per-call limits of the service.
struct ServiceLimits {
    std::uint64_t max_upload_bytes = 2ull << 30;  ///< Larger uploads -> RESOURCE_EXHAUSTED.
    std::uint64_t max_points = 50'000'000;  ///< Clouds with more points -> RESOURCE_EXHAUSTED.
    std::size_t max_chunk_bytes = 1 << 20;  ///< One UploadRequest's data at most.
    std::size_t download_chunk_bytes = 256 << 10;  ///< Result chunks in Watch, Download and HTTP.
    std::size_t max_uploads = 64;  ///< Upload calls in progress at once; more -> RESOURCE_EXHAUSTED.
};

/// A succeeded job's result file.
struct ResultFile {
    v1::Job job;
    std::string path;
    std::uint64_t size = 0;
    /// A file name for a download: "<type>-<first 12 of the job id><extension>".
    std::string filename;
};

/// The shared implementation of every operation. Every reference must outlive it; `ingest` must
/// also outlive the fronts that run it.
class Operations {
  public:
    Operations(worker::Store& store, worker::JobManager& jobs, Metrics& metrics, Executor& ingest,
               ServiceLimits limits);

    /// Bytes committed so far for an unfinished upload (0 when none). Checks the id.
    std::int64_t CommittedUploadBytes(const std::string& upload_id) const;
    /// kNotFound when unknown.
    v1::Cloud GetCloud(const std::string& cloud_id) const;
    /// kNotFound when unknown.
    void DeleteCloud(const std::string& cloud_id);

    v1::Job Submit(const v1::JobSpec& spec);
    /// kNotFound when unknown.
    v1::Job Cancel(const std::string& job_id);
    /// kNotFound when unknown.
    v1::Job GetJob(const std::string& job_id) const;
    /// Newest first; `limit` 0 = 100, at most 10000 (kInvalidArgument beyond).
    std::vector<v1::Job> ListJobs(std::uint32_t limit, v1::JobState state) const;
    /// kNotFound for an unknown job or a vanished file, kFailedPrecondition unless SUCCEEDED.
    ResultFile Result(const std::string& job_id) const;
    /// The events a watcher of an already final job gets: its state, then finished or failed.
    static std::vector<v1::JobEvent> FinalEvents(const v1::Job& job);

    /// Claims an upload id for one call at a time; false when another call holds it. Throws
    /// Error(kResourceExhausted) when limits().max_uploads calls hold one already.
    bool ClaimUpload(const std::string& id);
    void ReleaseUpload(const std::string& id);

    worker::Store& store() { return store_; }
    worker::JobManager& jobs() { return jobs_; }
    Metrics& metrics() { return metrics_; }
    /// Where uploads are hashed (on resume) and parsed.
    Executor& ingest() { return ingest_; }
    const ServiceLimits& limits() const { return limits_; }

  private:
    worker::Store& store_;
    worker::JobManager& jobs_;
    Metrics& metrics_;
    Executor& ingest_;
    ServiceLimits limits_;
    std::mutex uploads_mutex_;
    std::set<std::string> active_uploads_;
};

}  // namespace surfel::server
