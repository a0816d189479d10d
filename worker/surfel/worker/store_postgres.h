#pragma once
/// \file
/// The PostgreSQL backend of the store (libpq), for many servers and workers on separate
/// machines sharing one database; the blobs stay in a directory (a shared mount) for now.
/// Cross-process hints are LISTEN/NOTIFY on the channel `surfel_hints`.
///
/// Each PostgresStore holds one connection, used by one thread at a time (a mutex), so a
/// process that wants parallel claims opens one store per claiming thread. A lost connection is
/// reported as kUnavailable and re-established on the next call. Leases are compared with the
/// callers' clocks (Unix ms), which must agree to well within a lease (NTP).

#include <memory>
#include <string>

#include "surfel/worker/store.h"

namespace surfel::worker {

class PostgresStore final : public Store {
public:
    /// Connects to `url` (a libpq connection URI, "postgres://user@host:port/db?…"), applies
    /// the migrations (serialised between processes by an advisory lock) and keeps the blobs
    /// under `data_dir`. Throws kUnavailable when the database cannot be reached.
    PostgresStore(const std::string& url, const std::string& data_dir);
    ~PostgresStore() override;

    std::optional<v1::Cloud> FindCloud(const std::string& id) const override;
    void PutCloud(const v1::Cloud& cloud) override;
    bool CloudOwned(const std::string& tenant, const std::string& id) const override;
    void AddCloudOwner(const std::string& tenant, const std::string& id) override;
    bool RemoveCloudOwner(const std::string& tenant, const std::string& id,
                          std::size_t* remaining) override;
    void PutJob(const v1::Job& job, const std::string& key) override;
    std::optional<v1::Job> FindJob(const std::string& id) const override;
    std::optional<v1::Job> FindReusable(const std::string& key) const override;
    std::vector<v1::Job> ListJobs(std::size_t limit, v1::JobState state,
                                  const std::string* tenant = nullptr) const override;
    std::vector<v1::Job> Unfinished() const override;
    std::optional<LeasedJob> ClaimNext(const std::string& owner, std::int64_t lease_ms) override;
    bool Heartbeat(const std::string& job_id, const std::string& owner,
                   std::int64_t lease_ms) override;
    bool PutLeasedJob(const v1::Job& job, const std::string& owner) override;
    std::vector<v1::Job> RequeueExpired(std::int64_t now_unix_ms, int max_attempts) override;
    std::optional<v1::Job> RequestCancel(const std::string& job_id) override;
    bool CancelRequested(const std::string& job_id) const override;
    std::size_t CountQueued() const override;
    std::uint32_t QueuePosition(const std::string& job_id) const override;
    void PutBlobUsage(const std::string& key, std::uint64_t size, std::int64_t now_ms) override;
    void TouchBlobUsage(const std::string& key, std::int64_t now_ms) override;
    std::vector<BlobUsage> ListBlobUsage() const override;
    bool RemoveBlobUsage(const std::string& key) override;
    void PutEviction(const std::string& key, const std::string& tenant,
                     const Eviction& eviction) override;
    std::optional<Eviction> FindEviction(const std::string& key,
                                         const std::string* tenant) const override;
    std::vector<std::string> CloudOwners(const std::string& id) const override;
    bool shared() const override { return true; }
    /// `SELECT pg_notify('surfel_hints', payload)`.
    void Publish(const std::string& payload) override;
    /// `LISTEN surfel_hints` on a connection of its own, polled by a thread; a lost connection is
    /// re-established with backoff (100 ms doubling to 2 s), then `fn("")`.
    std::unique_ptr<Subscription> Listen(HintFn fn) override;

private:
    bool DeleteCloudRecord(const std::string& id) override;

    struct Impl;
    std::unique_ptr<Impl> impl_;
};

/// `url` with its password, if any, replaced by "***" (for messages and logs).
std::string RedactDatabaseUrl(const std::string& url);

}  // namespace surfel::worker
