#pragma once
/// \file
/// Persistence of the service: an interface (`Store`) over a database of clouds' and jobs'
/// metadata, with two backends chosen by `OpenStore`:
///
///   sqlite      (the default) one process, SQLite in WAL mode: <data>/surfel.db
///   postgres    many servers and workers sharing one PostgreSQL database (libpq);
///               see store_postgres.h
///
/// Both keep one schema, created and upgraded at open by the versioned migrations of
/// store_migrations.h (table `schema_migrations`). Blobs are a BlobStore (blob_store.h): by
/// default a directory (a shared mount for several machines), or PostgreSQL large objects:
///
///   <data>/uploads/<id>.part    bytes of unfinished uploads (resumable; always local files)
///   <data>/clouds/<sha256>      uploaded files, content-addressed   (dir backend)
///   <data>/results/<job id>     job results                          (dir backend)
///
/// Every method is safe to call from several threads. Errors are surfel::Error: kUnavailable
/// when the database cannot be reached, kInternal for a record that does not parse or a
/// statement the database refuses.

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/blob_store.h"
#include "surfel/worker/sha256.h"

namespace surfel::worker {

/// A job claimed by one worker, held under a lease that the worker renews by Heartbeat.
struct LeasedJob {
    /// As stored by the claim: RUNNING, started_unix_ms set.
    v1::Job job;
    /// The claimer's name (unique per worker thread).
    std::string owner;
    /// Unix ms; after it RequeueExpired may take the job back.
    std::int64_t lease_expires_ms = 0;
    /// Earlier leases of this job that expired (0 on a first run).
    int attempts = 0;
};

/// A stored blob's entry in the retention table (migration 6).
struct BlobUsage {
    std::string key;               ///< CloudBlobKey or ResultBlobKey
    std::uint64_t size = 0;        ///< bytes
    std::int64_t last_used_ms = 0; ///< Unix ms of its last store, job read or download
};

/// The tombstone of a blob evicted for one tenant.
struct Eviction {
    std::string reason;          ///< e.g. "least recently used, to stay under --max-disk-gb 1"
    std::int64_t evicted_ms = 0; ///< Unix ms
};

/// A running delivery of cross-process hints (Store::Listen); destroying it stops the delivery.
class Subscription {
public:
    virtual ~Subscription();
};

/// Receives one hint's payload; "" after the delivery was interrupted (a reconnect), when any
/// hint may have been missed and the receiver should re-read what it follows.
using HintFn = std::function<void(const std::string& payload)>;

/// The store interface. The blob paths are shared by all backends; the records are the backend's.
class Store {
public:
    virtual ~Store();
    Store(const Store&) = delete;
    Store& operator=(const Store&) = delete;

    /// The blob directory (uploads, and clouds and results with the dir backend).
    const std::string& data_dir() const { return data_dir_; }
    /// Where clouds and results live (a DirBlobStore over data_dir() unless SetBlobs chose
    /// another). Keys: CloudBlobKey, ResultBlobKey.
    BlobStore& blobs() const { return *blobs_; }
    /// Replaces the blob store (OpenStore does it for `--blobs postgres`).
    void SetBlobs(std::unique_ptr<BlobStore> blobs) { blobs_ = std::move(blobs); }
    /// False for a store opened without a data dir whose blobs were not set yet.
    bool has_blobs() const { return blobs_ != nullptr; }
    std::string CloudPath(const std::string& cloud_id) const;
    std::string ResultPath(const std::string& job_id) const;
    std::string UploadPath(const std::string& upload_id) const;

    // ---- clouds
    virtual std::optional<v1::Cloud> FindCloud(const std::string& id) const = 0;
    /// Records a cloud whose bytes are already at CloudPath(id); no-op when it exists.
    virtual void PutCloud(const v1::Cloud& cloud) = 0;
    /// Removes the record and the bytes (and every tenant's ownership); false when unknown.
    bool DeleteCloud(const std::string& id);

    // ---- tenants' clouds (docs/security.md): the bytes and the record are shared, each tenant
    // owns its own entry in `cloud_owners`; "" is the default tenant (no auth).
    /// Whether `tenant` owns cloud `id`.
    virtual bool CloudOwned(const std::string& tenant, const std::string& id) const = 0;
    /// Records that `tenant` owns cloud `id` ; no-op when it does (PutCloud records none).
    virtual void AddCloudOwner(const std::string& tenant, const std::string& id) = 0;
    /// Removes `tenant`'s ownership of `id`; false when it had none. `*remaining` (if not null)
    /// gets how many owners are left (0: DeleteCloud may remove the bytes).
    virtual bool RemoveCloudOwner(const std::string& tenant, const std::string& id,
                                  std::size_t* remaining) = 0;

    // ---- jobs (stored as serialized surfel.v1.Job plus indexed columns)
    /// Insert or replace. On replace the key, creation time and order are kept (an empty key
    /// is how the job manager writes a transition).
    virtual void PutJob(const v1::Job& job, const std::string& key) = 0;
    virtual std::optional<v1::Job> FindJob(const std::string& id) const = 0;
    /// The newest job with this key that is queued, running or succeeded.
    virtual std::optional<v1::Job> FindReusable(const std::string& key) const = 0;
    /// The newest `limit` jobs, newest first; all states when `state` is JOB_STATE_UNSPECIFIED;
    /// only those of `*tenant` (Job.tenant) unless `tenant` is null.
    virtual std::vector<v1::Job> ListJobs(std::size_t limit, v1::JobState state,
                                          const std::string* tenant = nullptr) const = 0;
    /// Jobs left QUEUED or RUNNING (by a crash or a shutdown), oldest first.
    virtual std::vector<v1::Job> Unfinished() const = 0;

    /// Queued jobs (the depth of the shared queue).
    virtual std::size_t CountQueued() const = 0;
    /// How many QUEUED jobs come before this one (0 when it is next or not queued).
    virtual std::uint32_t QueuePosition(const std::string& job_id) const = 0;

    // ---- the shared queue: claim, lease, heartbeat, requeue, cancel. The JobManager uses it
    // when shared() is true; a single-node SQLite server keeps its in-memory queue.
    /// True when several processes share this store's jobs (PostgreSQL).
    virtual bool shared() const { return false; }
    /// Claims the oldest QUEUED job for `owner`: one short statement (PostgreSQL:
    /// `SELECT … FOR UPDATE SKIP LOCKED`, so concurrent claimers never get the same job and never
    /// wait for each other), which sets the job RUNNING with a lease of `lease_ms` from now.
    /// No row lock or transaction stays open after it returns. nullopt when nothing is queued.
    virtual std::optional<LeasedJob> ClaimNext(const std::string& owner, std::int64_t lease_ms) = 0;
    /// Extends the lease of a RUNNING job held by `owner` to `lease_ms` from now. False when the
    /// lease was lost (expired and requeued, claimed by another, or the job ended).
    virtual bool Heartbeat(const std::string& job_id, const std::string& owner,
                           std::int64_t lease_ms) = 0;
    /// Writes a job (a progress update or its end) only while `owner` holds its lease; a final
    /// state releases the lease, and so does QUEUED (a worker giving a job back, e.g. on
    /// SIGTERM, without counting an attempt). False, changing nothing, when the lease was lost.
    virtual bool PutLeasedJob(const v1::Job& job, const std::string& owner) = 0;
    /// Takes back every RUNNING job whose lease expired before `now_unix_ms`: attempts + 1, and
    /// QUEUED again, or FAILED (UNAVAILABLE, a message naming the attempts and the last owner)
    /// once attempts reaches `max_attempts` (>= 1). Returns those jobs as now stored.
    /// Jobs running without a lease (the single-node JobManager) are never touched.
    virtual std::vector<v1::Job> RequeueExpired(std::int64_t now_unix_ms, int max_attempts) = 0;
    /// Asks a job to stop, from any process: a QUEUED job becomes CANCELLED at once (status
    /// CANCELLED, "cancelled while queued"); a RUNNING one gets its cancel_requested flag, which
    /// its leaseholder reads (CancelRequested) and acts on. Returns the job as stored after it;
    /// nullopt when unknown. A final job is returned unchanged.
    virtual std::optional<v1::Job> RequestCancel(const std::string& job_id) = 0;
    /// Whether RequestCancel flagged this job.
    virtual bool CancelRequested(const std::string& job_id) const = 0;

    // ---- disk retention (retention.h, docs/retention.md; migration 6)
    /// Records a blob just stored: its size, last used now (`now_ms`); replaces an older entry
    /// and clears the key's eviction tombstones (the bytes are back).
    virtual void PutBlobUsage(const std::string& key, std::uint64_t size, std::int64_t now_ms) = 0;
    /// Sets a recorded blob's last use to `now_ms`; nothing when it has no entry.
    virtual void TouchBlobUsage(const std::string& key, std::int64_t now_ms) = 0;
    /// Every entry, least recently used first (ties by key).
    virtual std::vector<BlobUsage> ListBlobUsage() const = 0;
    /// Removes a blob's entry; false when it had none.
    virtual bool RemoveBlobUsage(const std::string& key) = 0;
    /// Records that `key` was evicted for `tenant` (replacing an older tombstone).
    virtual void PutEviction(const std::string& key, const std::string& tenant,
                             const Eviction& eviction) = 0;
    /// The tombstone of `key` for `tenant`, or for any tenant when `tenant` is null.
    virtual std::optional<Eviction> FindEviction(const std::string& key,
                                                 const std::string* tenant) const = 0;
    /// The tenants that own cloud `id`, sorted.
    virtual std::vector<std::string> CloudOwners(const std::string& id) const = 0;

    // ---- cross-process hints (PostgreSQL LISTEN/NOTIFY; nothing for SQLite). A hint is a
    // wake-up only: it may be lost (a reconnect, a crash before it was sent), so receivers also
    // poll the tables, which stay the state of record.
    /// Sends a small payload (< 8000 bytes: ids and fractions) to every Listen of every process
    /// on this database, at once (no transaction). Throws kUnavailable when the database is down.
    virtual void Publish(const std::string& /*payload*/) {}
    /// Delivers every hint published from now on to `fn`, on a thread of its own with its own
    /// connection, reconnecting with backoff (then `fn("")`). nullptr when the backend has no
    /// hints (SQLite: one process).
    virtual std::unique_ptr<Subscription> Listen(HintFn /*fn*/) { return nullptr; }

protected:
    /// Creates (when missing) the blob directories under `data_dir` and a DirBlobStore there;
    /// nothing when `data_dir` is empty (a surfel-worker on large-object blobs). Throws
    /// kInvalidArgument.
    explicit Store(const std::string& data_dir);

private:
    /// Removes the cloud's record; false when unknown.
    virtual bool DeleteCloudRecord(const std::string& id) = 0;

    std::string data_dir_;
    std::unique_ptr<BlobStore> blobs_;
};

/// The embedded default: SQLite (WAL) in one file, blobs in a directory.
class SqliteStore final : public Store {
public:
    /// Opens (creating when missing) `data_dir` and its database `<data_dir>/surfel.db`, and
    /// applies the migrations. Throws surfel::Error.
    explicit SqliteStore(const std::string& data_dir);
    /// Same, with the database at `database_file` and the blobs under `data_dir`.
    SqliteStore(const std::string& database_file, const std::string& data_dir);
    ~SqliteStore() override;

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

private:
    bool DeleteCloudRecord(const std::string& id) override;

    struct Impl;
    std::unique_ptr<Impl> impl_;
};

/// Opens the store named by `url_or_dir`, its blobs under `data_dir`:
///   ""  or "sqlite"                  SQLite at <data_dir>/surfel.db (today's default)
///   "sqlite:FILE"                    SQLite at FILE
///   "postgres://…", "postgresql://…" PostgreSQL (a libpq connection URI)
///   any other string without "://"   a directory: SQLite at <that dir>/surfel.db; the blobs
///                                    there too when `data_dir` is empty
/// `blobs` is the `--blobs` flag: "" or "dir:PATH" keep the blobs in `data_dir` (the caller
/// passes BlobDirFromFlag's answer there); "postgres" puts clouds and results into large objects
/// of the store's PostgreSQL database (kInvalidArgument with any other store).
/// Throws kInvalidArgument for another scheme, and whatever the backend's constructor throws.
std::unique_ptr<Store> OpenStore(const std::string& url_or_dir, const std::string& data_dir,
                                 const std::string& blobs = "");

/// The blob directory named by a `--blobs` flag: "dir:PATH" -> PATH; "" or "postgres" ->
/// `default_dir` (with large objects it holds only the local part files of uploads).
/// Throws kInvalidArgument for anything else.
std::string BlobDirFromFlag(const std::string& blobs, const std::string& default_dir);

/// Milliseconds since the Unix epoch.
std::int64_t NowUnixMs();

/// The status message of a job failed by RequeueExpired, e.g. "lease expired on attempt 3 of 3
/// (last owner worker-a); giving up".
std::string LeaseExhaustedMessage(int attempts, int max_attempts, const std::string& last_owner);

}  // namespace surfel::worker
