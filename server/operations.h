#pragma once
/// \file
/// The operations of surfel.v1, free of any transport: the gRPC front (SurfelService and its
/// reactors) and the HTTP/JSON front (HttpFront) translate their requests into these calls and
/// their answers back, and hold no logic of their own. Failures are thrown as surfel::Error with
/// a code (worker/status.h maps it to a gRPC status, the HTTP front to an HTTP status).

#include <cstdint>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "auth.h"
#include "executor.h"
#include "metrics.h"
#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/job_manager.h"
#include "surfel/worker/retention.h"
#include "surfel/worker/store.h"

namespace surfel::server {

/// Per-call limits of the service.
struct ServiceLimits {
    std::uint64_t max_upload_bytes = 2ull << 30;  ///< Larger uploads -> RESOURCE_EXHAUSTED.
    std::uint64_t max_points = 50'000'000;  ///< Clouds with more points -> RESOURCE_EXHAUSTED.
    std::size_t max_chunk_bytes = 1 << 20;  ///< One UploadRequest's data at most.
    std::size_t download_chunk_bytes = 256 << 10;  ///< Result chunks in Watch, Download and HTTP.
    std::size_t max_uploads = 64;  ///< Upload calls in progress at once; more -> RESOURCE_EXHAUSTED.
    /// Bytes received by upload calls in progress and not yet stored as clouds (their part files,
    /// which Finish reads whole into memory to parse, and the chunks the transports hold on the
    /// way there); a chunk past it -> RESOURCE_EXHAUSTED, the committed bytes kept for a resume.
    /// 0 = no limit.
    std::uint64_t max_upload_inflight_bytes = 4ull << 30;
};

/// A succeeded job's result file.
struct ResultFile {
    v1::Job job;
    /// Its blob in store().blobs() (ResultBlobKey); checked against job.result().sha256().
    std::string key;
    std::uint64_t size = 0;
    /// A file name for a download: "<type>-<first 12 of the job id><extension>".
    std::string filename;
};

/// The shared implementation of every operation. Every reference must outlive it; `ingest` must
/// also outlive the fronts that run it.
///
/// Every operation takes the Caller (auth.h). A scoped caller (auth on) sees only its tenant's
/// clouds and jobs: another tenant's id is kNotFound with the very message of an unknown id.
class Operations {
  public:
    Operations(worker::Store& store, worker::JobManager& jobs, Metrics& metrics, Executor& ingest,
               ServiceLimits limits);

    /// Bytes committed so far for an unfinished upload (0 when none). Checks the id.
    std::int64_t CommittedUploadBytes(const Caller& caller, const std::string& upload_id) const;
    /// kNotFound when unknown (or not the caller's).
    v1::Cloud GetCloud(const Caller& caller, const std::string& cloud_id) const;
    /// kNotFound when unknown (saying "evicted" when retention evicted it);
    /// kFailedPrecondition naming the job when a queued or running job of the caller needs the
    /// cloud (docs/retention.md). A scoped caller drops its own ownership; the bytes go with the
    /// last owner.
    void DeleteCloud(const Caller& caller, const std::string& cloud_id);

    /// kNotFound for an input cloud the caller does not own, then JobManager::Submit.
    v1::Job Submit(const Caller& caller, const v1::JobSpec& spec);
    /// kNotFound when unknown.
    v1::Job Cancel(const Caller& caller, const std::string& job_id);
    /// kNotFound when unknown.
    v1::Job GetJob(const Caller& caller, const std::string& job_id) const;
    /// Newest first; `limit` 0 = 100, at most 10000 (kInvalidArgument beyond).
    std::vector<v1::Job> ListJobs(const Caller& caller, std::uint32_t limit,
                                  v1::JobState state) const;
    /// kNotFound for an unknown job or a vanished file, kFailedPrecondition unless SUCCEEDED.
    ResultFile Result(const Caller& caller, const std::string& job_id) const;
    /// Why a SUCCEEDED job's result blob is missing, for the caller: "result of job <id> was
    /// evicted at …" when retention evicted it, else "result of job <id> is gone".
    std::string ResultGoneMessage(const Caller& caller, const std::string& job_id) const;
    /// The name of the part file (and of the claim) of a caller's upload id: the id itself for
    /// an unscoped caller, else prefixed by a digest of the tenant (ids are per tenant).
    static std::string ScopedUploadId(const Caller& caller, const std::string& upload_id);
    /// The events a watcher of an already final job gets: its state, then finished or failed.
    static std::vector<v1::JobEvent> FinalEvents(const v1::Job& job);

    /// Claims an upload id for one call at a time; false when another call holds it. Throws
    /// Error(kResourceExhausted) when limits().max_uploads calls hold one already.
    bool ClaimUpload(const std::string& id);
    void ReleaseUpload(const std::string& id);
    /// Counts `bytes` of upload `id` as in flight; Error(kResourceExhausted) when that would pass
    /// limits().max_upload_inflight_bytes (nothing counted then).
    void ReserveInflight(std::uint64_t bytes, const std::string& id);
    void ReleaseInflight(std::uint64_t bytes);
    /// Bytes of uploads in flight now.
    std::uint64_t InflightBytes() const;

    /// Disk quota and retention (worker/retention.h); null when not set.
    worker::Retention* retention() const { return retention_; }
    void SetRetention(worker::Retention* retention) { retention_ = retention; }

    worker::Store& store() { return store_; }
    worker::JobManager& jobs() { return jobs_; }
    Metrics& metrics() { return metrics_; }
    /// Where uploads are hashed (on resume) and parsed.
    Executor& ingest() { return ingest_; }
    const ServiceLimits& limits() const { return limits_; }
    /// Turns credentials into a Caller; off (everyone is Caller{}) unless set.
    const Authenticator& auth() const { return auth_; }
    void SetAuthenticator(Authenticator auth) { auth_ = std::move(auth); }
    /// Signs the browser's event-stream URLs (HTTP front).
    const UrlSigner& url_signer() const { return url_signer_; }

  private:
    worker::Store& store_;
    worker::JobManager& jobs_;
    Metrics& metrics_;
    Executor& ingest_;
    ServiceLimits limits_;
    Authenticator auth_;
    UrlSigner url_signer_;
    mutable std::mutex uploads_mutex_;
    std::set<std::string> active_uploads_;
    std::uint64_t inflight_bytes_ = 0;  ///< under uploads_mutex_
    worker::Retention* retention_ = nullptr;
    /// The "evicted" message of a blob the caller would see, if it was evicted.
    std::optional<std::string> Evicted(const Caller& caller, const std::string& key,
                                       const std::string& what) const;
};

}  // namespace surfel::server
