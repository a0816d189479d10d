// The SQLite backend of the store: one connection in WAL mode behind a mutex.
#include <SQLiteCpp/SQLiteCpp.h>
#include <sqlite3.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <mutex>
#include <string>
#include <thread>

#include "surfel/base/error.h"
#include "surfel/worker/job_state.h"
#include "surfel/worker/store.h"
#include "surfel/worker/store_common.h"
#include "surfel/worker/store_migrations.h"

namespace surfel::worker {
namespace {

v1::Job ParseJob(const SQLite::Column& blob) {
    v1::Job job;
    if (!job.ParseFromArray(blob.getBlob(), blob.getBytes()))
        throw Error(ErrorCode::kInternal, "store: a job record does not parse");
    return job;
}

/// Runs a write; a full disk (SQLITE_FULL) is kResourceExhausted naming `what`, not INTERNAL.
void ExecWrite(SQLite::Statement& q, const char* what) {
    try {
        q.exec();
    } catch (const SQLite::Exception& e) {
        if (e.getErrorCode() == SQLITE_FULL)
            throw Error(ErrorCode::kResourceExhausted, std::string("database: ") + what + ": " + e.what());
        throw;
    }
}

void BindRecord(SQLite::Statement& q, int index, const std::string& blob) {
    q.bind(index, blob.data(), static_cast<int>(blob.size()));
}

/// The busy timeout of every connection, ms.
constexpr int kBusyTimeoutMs = 5000;

/// Runs `fn` again while SQLite answers SQLITE_BUSY, up to kBusyTimeoutMs. SQLite returns BUSY at
/// once, without calling the busy handler, where waiting could deadlock: a connection whose read
/// snapshot is older than another connection's commit cannot upgrade it to a write (two openers
/// of a new file both running CREATE TABLE IF NOT EXISTS), and a switch to WAL meets another
/// opener. Every step `fn` runs must be idempotent (the opening's steps are).
template <typename Fn>
void RetryWhileBusy(Fn&& fn) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(kBusyTimeoutMs);
    for (int attempt = 0;; ++attempt) {
        try {
            fn();
            return;
        } catch (const SQLite::Exception& e) {
            if (e.getErrorCode() != SQLITE_BUSY || std::chrono::steady_clock::now() >= deadline) throw;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(1 << std::min(attempt, 5)));
    }
}

}  // namespace

struct SqliteStore::Impl {
    explicit Impl(const std::string& path)
        : db(path, SQLite::OPEN_READWRITE | SQLite::OPEN_CREATE | SQLite::OPEN_FULLMUTEX) {}
    mutable std::mutex mutex;
    SQLite::Database db;
};

SqliteStore::SqliteStore(const std::string& data_dir)
    : SqliteStore(data_dir + "/surfel.db", data_dir) {}

SqliteStore::SqliteStore(const std::string& database_file, const std::string& data_dir)
    : Store(data_dir) {
    std::error_code ec;
    const std::filesystem::path parent = std::filesystem::path(database_file).parent_path();
    if (!parent.empty()) std::filesystem::create_directories(parent, ec);
    if (ec)
        throw Error(ErrorCode::kInvalidArgument, "database " + database_file + ": " + ec.message());
    try {
        impl_ = std::make_unique<Impl>(database_file);
        auto& db = impl_->db;
        // First: another process may be opening it too.
        db.exec("PRAGMA busy_timeout=" + std::to_string(kBusyTimeoutMs));
        RetryWhileBusy([&] { db.exec("PRAGMA journal_mode=WAL"); });
        // FULL: the WAL is fsynced at every commit, so an acknowledged upload or job survives a
        // power failure too (NORMAL would lose the commits since the last checkpoint; ~1 ms per
        // commit here, docs/durability.md).
        db.exec("PRAGMA synchronous=FULL");
        // Migrations: each one with its record in one transaction, so a crash or a second
        // process opening at the same time never applies one twice. The table of them is
        // created in a write transaction taken at once (IMMEDIATE waits for the busy timeout).
        RetryWhileBusy([&] {
            SQLite::Transaction tx(db, SQLite::TransactionBehavior::IMMEDIATE);
            db.exec(kSchemaMigrationsTable);
            tx.commit();
        });
        for (const Migration& m : Migrations()) RetryWhileBusy([&] {
            SQLite::Transaction tx(db, SQLite::TransactionBehavior::IMMEDIATE);  // rolled back unless committed
            SQLite::Statement newest(db, "SELECT COALESCE(MAX(version), 0) FROM schema_migrations");
            newest.executeStep();
            const std::int64_t applied = newest.getColumn(0).getInt64();
            store_detail::CheckSchemaNotNewer(applied, "database " + database_file);
            if (applied >= m.version) return;
            db.exec(m.sqlite);
            SQLite::Statement rec(
                db, "INSERT INTO schema_migrations (version, name, applied_ms) VALUES (?, ?, ?)");
            rec.bind(1, m.version);
            rec.bind(2, m.name);
            rec.bind(3, static_cast<std::int64_t>(NowUnixMs()));
            rec.exec();
            tx.commit();
        });
    } catch (const SQLite::Exception& e) {
        throw Error(ErrorCode::kInternal, "database " + database_file + ": " + e.what());
    }
}

SqliteStore::~SqliteStore() = default;

// ---- clouds

std::optional<v1::Cloud> SqliteStore::FindCloud(const std::string& id) const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "SELECT record FROM clouds WHERE id = ?");
    q.bind(1, id);
    if (!q.executeStep()) return std::nullopt;
    v1::Cloud c;
    const SQLite::Column col = q.getColumn(0);
    if (!c.ParseFromArray(col.getBlob(), col.getBytes()))
        throw Error(ErrorCode::kInternal, "store: bad cloud record");
    return c;
}

void SqliteStore::PutCloud(const v1::Cloud& cloud) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db,
                        "INSERT OR IGNORE INTO clouds (id, record, created_ms) VALUES (?, ?, ?)");
    const std::string blob = cloud.SerializeAsString();
    q.bind(1, cloud.id());
    BindRecord(q, 2, blob);
    q.bind(3, static_cast<std::int64_t>(NowUnixMs()));
    ExecWrite(q, "recording a cloud");
}

bool SqliteStore::DeleteCloudRecord(const std::string& id) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Transaction tx(impl_->db);
    SQLite::Statement owners(impl_->db, "DELETE FROM cloud_owners WHERE cloud_id = ?");
    owners.bind(1, id);
    owners.exec();
    SQLite::Statement q(impl_->db, "DELETE FROM clouds WHERE id = ?");
    q.bind(1, id);
    const bool deleted = q.exec() > 0;
    tx.commit();
    return deleted;
}

bool SqliteStore::CloudOwned(const std::string& tenant, const std::string& id) const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "SELECT 1 FROM cloud_owners WHERE tenant = ? AND cloud_id = ?");
    q.bind(1, tenant);
    q.bind(2, id);
    return q.executeStep();
}

void SqliteStore::AddCloudOwner(const std::string& tenant, const std::string& id) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db,
                        "INSERT OR IGNORE INTO cloud_owners (tenant, cloud_id) VALUES (?, ?)");
    q.bind(1, tenant);
    q.bind(2, id);
    ExecWrite(q, "recording an owner");
}

bool SqliteStore::RemoveCloudOwner(const std::string& tenant, const std::string& id,
                                   std::size_t* remaining) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "DELETE FROM cloud_owners WHERE tenant = ? AND cloud_id = ?");
    q.bind(1, tenant);
    q.bind(2, id);
    const bool removed = q.exec() > 0;
    if (remaining) {
        SQLite::Statement n(impl_->db, "SELECT COUNT(*) FROM cloud_owners WHERE cloud_id = ?");
        n.bind(1, id);
        n.executeStep();
        *remaining = static_cast<std::size_t>(n.getColumn(0).getInt64());
    }
    return removed;
}

// ---- jobs

void SqliteStore::PutJob(const v1::Job& job, const std::string& key) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(
        impl_->db,
        "INSERT INTO jobs (id, key, state, created_ms, seq, record, tenant) VALUES (?, ?, ?, ?, "
        "(SELECT COALESCE(MAX(seq), 0) + 1 FROM jobs), ?, ?) ON CONFLICT(id) DO UPDATE SET "
        "state = excluded.state, record = excluded.record");
    const std::string blob = job.SerializeAsString();
    q.bind(1, job.id());
    q.bind(2, key);
    q.bind(3, static_cast<int>(job.state()));
    q.bind(4, static_cast<std::int64_t>(job.created_unix_ms()));
    BindRecord(q, 5, blob);
    q.bind(6, job.tenant());
    ExecWrite(q, "recording a job");
}

std::optional<v1::Job> SqliteStore::FindJob(const std::string& id) const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "SELECT record FROM jobs WHERE id = ?");
    q.bind(1, id);
    if (!q.executeStep()) return std::nullopt;
    return ParseJob(q.getColumn(0));
}

std::optional<v1::Job> SqliteStore::FindReusable(const std::string& key) const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(
        impl_->db,
        "SELECT record FROM jobs WHERE key = ? AND state IN (?, ?, ?) ORDER BY seq DESC LIMIT 1");
    q.bind(1, key);
    q.bind(2, static_cast<int>(v1::QUEUED));
    q.bind(3, static_cast<int>(v1::RUNNING));
    q.bind(4, static_cast<int>(v1::SUCCEEDED));
    if (!q.executeStep()) return std::nullopt;
    return ParseJob(q.getColumn(0));
}

std::vector<v1::Job> SqliteStore::ListJobs(std::size_t limit, v1::JobState state,
                                           const std::string* tenant) const {
    std::lock_guard lock(impl_->mutex);
    std::vector<v1::Job> out;
    const bool any_state = state == v1::JOB_STATE_UNSPECIFIED;
    std::string sql = "SELECT record FROM jobs";
    if (!any_state || tenant) sql += " WHERE ";
    if (!any_state) sql += "state = ?";
    if (!any_state && tenant) sql += " AND ";
    if (tenant) sql += "tenant = ?";
    sql += " ORDER BY seq DESC LIMIT ?";
    SQLite::Statement q(impl_->db, sql);
    int i = 1;
    if (!any_state) q.bind(i++, static_cast<int>(state));
    if (tenant) q.bind(i++, *tenant);
    q.bind(i, static_cast<std::int64_t>(limit));
    while (q.executeStep()) out.push_back(ParseJob(q.getColumn(0)));
    return out;
}

std::vector<v1::Job> SqliteStore::Unfinished() const {
    std::lock_guard lock(impl_->mutex);
    std::vector<v1::Job> out;
    SQLite::Statement q(impl_->db,
                        "SELECT record FROM jobs WHERE state IN (?, ?) ORDER BY seq ASC");
    q.bind(1, static_cast<int>(v1::QUEUED));
    q.bind(2, static_cast<int>(v1::RUNNING));
    while (q.executeStep()) out.push_back(ParseJob(q.getColumn(0)));
    return out;
}

// ---- the queue. One connection behind a mutex: a claim is the oldest QUEUED row turned
// RUNNING inside one short write transaction (BEGIN IMMEDIATE also serialises other processes
// on the same file).

std::optional<LeasedJob> SqliteStore::ClaimNext(const std::string& owner, std::int64_t lease_ms) {
    store_detail::CheckLease(owner, lease_ms);
    std::lock_guard lock(impl_->mutex);
    auto& db = impl_->db;
    SQLite::Transaction tx(db, SQLite::TransactionBehavior::IMMEDIATE);  // rolled back unless committed
    SQLite::Statement pick(
        db, "SELECT id, record, attempts FROM jobs WHERE state = ? ORDER BY seq ASC LIMIT 1");
    pick.bind(1, static_cast<int>(v1::QUEUED));
    if (!pick.executeStep()) return std::nullopt;
    const std::int64_t now = NowUnixMs();
    LeasedJob leased;
    leased.job = store_detail::ClaimedRecord(ParseJob(pick.getColumn(1)), now);
    leased.owner = owner;
    leased.lease_expires_ms = now + lease_ms;
    leased.attempts = pick.getColumn(2).getInt();
    const std::string id = pick.getColumn(0).getString();
    pick.reset();
    SQLite::Statement q(db,
                        "UPDATE jobs SET state = ?, lease_owner = ?, lease_expires_ms = ?, "
                        "record = ? WHERE id = ?");
    const std::string blob = leased.job.SerializeAsString();
    q.bind(1, static_cast<int>(v1::RUNNING));
    q.bind(2, owner);
    q.bind(3, static_cast<std::int64_t>(leased.lease_expires_ms));
    BindRecord(q, 4, blob);
    q.bind(5, id);
    q.exec();
    tx.commit();
    return leased;
}

bool SqliteStore::Heartbeat(const std::string& job_id, const std::string& owner,
                            std::int64_t lease_ms) {
    store_detail::CheckLease(owner, lease_ms);
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db,
                        "UPDATE jobs SET lease_expires_ms = ? WHERE id = ? AND lease_owner = ? AND "
                        "state = ?");
    q.bind(1, static_cast<std::int64_t>(NowUnixMs() + lease_ms));
    q.bind(2, job_id);
    q.bind(3, owner);
    q.bind(4, static_cast<int>(v1::RUNNING));
    return q.exec() > 0;
}

bool SqliteStore::PutLeasedJob(const v1::Job& job, const std::string& owner) {
    store_detail::CheckLease(owner, 1);
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db,
                        "UPDATE jobs SET state = ?, record = ?, "
                        "lease_owner = CASE WHEN ? THEN NULL ELSE lease_owner END, "
                        "lease_expires_ms = CASE WHEN ? THEN NULL ELSE lease_expires_ms END "
                        "WHERE id = ? AND lease_owner = ? AND state = ?");
    const std::string blob = job.SerializeAsString();
    const int ends = IsFinal(job.state()) || job.state() == v1::QUEUED ? 1 : 0;
    q.bind(1, static_cast<int>(job.state()));
    BindRecord(q, 2, blob);
    q.bind(3, ends);
    q.bind(4, ends);
    q.bind(5, job.id());
    q.bind(6, owner);
    q.bind(7, static_cast<int>(v1::RUNNING));
    return q.exec() > 0;
}

std::vector<v1::Job> SqliteStore::RequeueExpired(std::int64_t now_unix_ms, int max_attempts) {
    store_detail::CheckMaxAttempts(max_attempts);
    std::lock_guard lock(impl_->mutex);
    auto& db = impl_->db;
    SQLite::Transaction tx(db, SQLite::TransactionBehavior::IMMEDIATE);  // rolled back unless committed
    struct Expired {
        v1::Job job;
        int attempts;
    };
    std::vector<Expired> expired;
    {
        SQLite::Statement q(db,
                            "SELECT record, attempts, lease_owner FROM jobs WHERE state = ? AND "
                            "lease_expires_ms IS NOT NULL AND lease_expires_ms < ? ORDER BY seq");
        q.bind(1, static_cast<int>(v1::RUNNING));
        q.bind(2, static_cast<std::int64_t>(now_unix_ms));
        while (q.executeStep()) {
            const int attempts = q.getColumn(1).getInt() + 1;
            expired.push_back({store_detail::ExpiredRecord(ParseJob(q.getColumn(0)), attempts,
                                                           max_attempts, q.getColumn(2).getString(),
                                                           now_unix_ms),
                               attempts});
        }
    }
    std::vector<v1::Job> out;
    for (Expired& e : expired) {
        SQLite::Statement q(db,
                            "UPDATE jobs SET state = ?, attempts = ?, lease_owner = NULL, "
                            "lease_expires_ms = NULL, record = ? WHERE id = ?");
        const std::string blob = e.job.SerializeAsString();
        q.bind(1, static_cast<int>(e.job.state()));
        q.bind(2, e.attempts);
        BindRecord(q, 3, blob);
        q.bind(4, e.job.id());
        q.exec();
        out.push_back(std::move(e.job));
    }
    tx.commit();
    return out;
}

std::optional<v1::Job> SqliteStore::RequestCancel(const std::string& job_id) {
    std::lock_guard lock(impl_->mutex);
    auto& db = impl_->db;
    SQLite::Transaction tx(db, SQLite::TransactionBehavior::IMMEDIATE);  // rolled back unless committed
    SQLite::Statement pick(db, "SELECT record FROM jobs WHERE id = ?");
    pick.bind(1, job_id);
    if (!pick.executeStep()) return std::nullopt;
    v1::Job job = ParseJob(pick.getColumn(0));
    pick.reset();
    if (job.state() == v1::QUEUED) {
        job = store_detail::CancelledWhileQueuedRecord(std::move(job), NowUnixMs());
        SQLite::Statement q(db, "UPDATE jobs SET state = ?, record = ?, cancel_requested = 1 "
                                "WHERE id = ?");
        const std::string blob = job.SerializeAsString();
        q.bind(1, static_cast<int>(job.state()));
        BindRecord(q, 2, blob);
        q.bind(3, job_id);
        q.exec();
    } else if (job.state() == v1::RUNNING) {
        SQLite::Statement q(db, "UPDATE jobs SET cancel_requested = 1 WHERE id = ?");
        q.bind(1, job_id);
        q.exec();
    }
    tx.commit();
    return job;
}

bool SqliteStore::CancelRequested(const std::string& job_id) const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "SELECT cancel_requested FROM jobs WHERE id = ?");
    q.bind(1, job_id);
    return q.executeStep() && q.getColumn(0).getInt() != 0;
}

std::size_t SqliteStore::CountQueued() const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "SELECT COUNT(*) FROM jobs WHERE state = ?");
    q.bind(1, static_cast<int>(v1::QUEUED));
    q.executeStep();
    return static_cast<std::size_t>(q.getColumn(0).getInt64());
}

std::uint32_t SqliteStore::QueuePosition(const std::string& job_id) const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db,
                        "SELECT COUNT(*) FROM jobs WHERE state = ? AND seq < "
                        "(SELECT seq FROM jobs WHERE id = ? AND state = ?)");
    q.bind(1, static_cast<int>(v1::QUEUED));
    q.bind(2, job_id);
    q.bind(3, static_cast<int>(v1::QUEUED));
    q.executeStep();
    return static_cast<std::uint32_t>(q.getColumn(0).getInt64());
}

}  // namespace surfel::worker

// ---- disk retention (migration 6)

namespace surfel::worker {

void SqliteStore::PutBlobUsage(const std::string& key, std::uint64_t size, std::int64_t now_ms) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Transaction tx(impl_->db);
    SQLite::Statement q(impl_->db,
                        "INSERT INTO blob_usage (key, size, last_used_ms) VALUES (?, ?, ?) "
                        "ON CONFLICT(key) DO UPDATE SET size = excluded.size, "
                        "last_used_ms = excluded.last_used_ms");
    q.bind(1, key);
    q.bind(2, static_cast<std::int64_t>(size));
    q.bind(3, static_cast<std::int64_t>(now_ms));
    q.exec();
    SQLite::Statement e(impl_->db, "DELETE FROM evictions WHERE key = ?");
    e.bind(1, key);
    e.exec();
    tx.commit();
}

void SqliteStore::TouchBlobUsage(const std::string& key, std::int64_t now_ms) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "UPDATE blob_usage SET last_used_ms = ? WHERE key = ?");
    q.bind(1, static_cast<std::int64_t>(now_ms));
    q.bind(2, key);
    q.exec();
}

std::vector<BlobUsage> SqliteStore::ListBlobUsage() const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db,
                        "SELECT key, size, last_used_ms FROM blob_usage ORDER BY last_used_ms, key");
    std::vector<BlobUsage> out;
    while (q.executeStep())
        out.push_back({q.getColumn(0).getString(),
                       static_cast<std::uint64_t>(q.getColumn(1).getInt64()),
                       q.getColumn(2).getInt64()});
    return out;
}

bool SqliteStore::RemoveBlobUsage(const std::string& key) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "DELETE FROM blob_usage WHERE key = ?");
    q.bind(1, key);
    return q.exec() > 0;
}

void SqliteStore::PutEviction(const std::string& key, const std::string& tenant,
                              const Eviction& eviction) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db,
                        "INSERT OR REPLACE INTO evictions (key, tenant, reason, evicted_ms) "
                        "VALUES (?, ?, ?, ?)");
    q.bind(1, key);
    q.bind(2, tenant);
    q.bind(3, eviction.reason);
    q.bind(4, static_cast<std::int64_t>(eviction.evicted_ms));
    q.exec();
}

std::optional<Eviction> SqliteStore::FindEviction(const std::string& key,
                                                  const std::string* tenant) const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db,
                        tenant ? "SELECT reason, evicted_ms FROM evictions WHERE key = ? AND "
                                 "tenant = ?"
                               : "SELECT reason, evicted_ms FROM evictions WHERE key = ? "
                                 "ORDER BY evicted_ms DESC LIMIT 1");
    q.bind(1, key);
    if (tenant) q.bind(2, *tenant);
    if (!q.executeStep()) return std::nullopt;
    return Eviction{q.getColumn(0).getString(), q.getColumn(1).getInt64()};
}

std::vector<std::string> SqliteStore::CloudOwners(const std::string& id) const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db,
                        "SELECT tenant FROM cloud_owners WHERE cloud_id = ? ORDER BY tenant");
    q.bind(1, id);
    std::vector<std::string> out;
    while (q.executeStep()) out.push_back(q.getColumn(0).getString());
    return out;
}

}  // namespace surfel::worker
