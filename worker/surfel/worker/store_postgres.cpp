// The PostgreSQL backend of the store: libpq, one connection behind a mutex, parameters sent
// as text (bytea records as binary) and results received in binary.
#include "surfel/worker/store_postgres.h"

#include <endian.h>
#include <libpq-fe.h>

#include <poll.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstring>
#include <mutex>
#include <thread>

#include "surfel/base/error.h"
#include "surfel/worker/job_state.h"
#include "surfel/worker/store_common.h"
#include "surfel/worker/store_migrations.h"

namespace surfel::worker {
namespace {

// The key of the advisory lock that serialises migrations between processes ("surfel" in
// ASCII).
constexpr const char* kMigrationLock = "SELECT pg_advisory_xact_lock(126879161019756)";

// OIDs of the built-in types read back (server/catalog/pg_type.dat).
constexpr Oid kInt2Oid = 21;
constexpr Oid kInt4Oid = 23;
constexpr Oid kInt8Oid = 20;

/// Owns a PGresult.
struct ResultDeleter {
    void operator()(PGresult* r) const { PQclear(r); }
};
using Result = std::unique_ptr<PGresult, ResultDeleter>;

/// The parameters of one statement: text values, and binary ones for bytea.
class Params {
public:
    Params& Text(std::string v) {
        values_.push_back(std::move(v));
        formats_.push_back(0);
        return *this;
    }
    Params& Int(std::int64_t v) { return Text(std::to_string(v)); }
    Params& Bytes(std::string v) {
        values_.push_back(std::move(v));
        formats_.push_back(1);
        return *this;
    }
    int size() const { return static_cast<int>(values_.size()); }
    /// Pointers and lengths for PQexecParams; valid while this object is unchanged.
    void Prepare(std::vector<const char*>& ptrs, std::vector<int>& lengths) const {
        for (const std::string& v : values_) {
            ptrs.push_back(v.data());
            lengths.push_back(static_cast<int>(v.size()));
        }
    }
    const int* formats() const { return formats_.data(); }

private:
    std::vector<std::string> values_;
    std::vector<int> formats_;
};

std::string_view Bytes(const PGresult* r, int row, int col) {
    return {PQgetvalue(r, row, col), static_cast<std::size_t>(PQgetlength(r, row, col))};
}

/// An integer column of a binary result (int2, int4 or int8).
std::int64_t Int(const PGresult* r, int row, int col) {
    const char* v = PQgetvalue(r, row, col);
    switch (PQftype(r, col)) {
        case kInt2Oid: {
            std::uint16_t x;
            std::memcpy(&x, v, sizeof x);
            return static_cast<std::int16_t>(be16toh(x));
        }
        case kInt4Oid: {
            std::uint32_t x;
            std::memcpy(&x, v, sizeof x);
            return static_cast<std::int32_t>(be32toh(x));
        }
        case kInt8Oid: {
            std::uint64_t x;
            std::memcpy(&x, v, sizeof x);
            return static_cast<std::int64_t>(be64toh(x));
        }
        default:
            throw Error(ErrorCode::kInternal, "postgres: column " + std::to_string(col) +
                                                  " is not an integer (type oid " +
                                                  std::to_string(PQftype(r, col)) + ")");
    }
}

v1::Job ParseJob(std::string_view bytes) {
    v1::Job job;
    if (!job.ParseFromArray(bytes.data(), static_cast<int>(bytes.size())))
        throw Error(ErrorCode::kInternal, "store: a job record does not parse");
    return job;
}

}  // namespace

std::string RedactDatabaseUrl(const std::string& url) {
    const std::size_t scheme = url.find("://");
    if (scheme == std::string::npos) return url;
    const std::size_t at = url.find('@', scheme + 3);
    if (at == std::string::npos) return url;
    const std::size_t colon = url.find(':', scheme + 3);
    if (colon == std::string::npos || colon > at) return url;
    return url.substr(0, colon + 1) + "***" + url.substr(at);
}

struct PostgresStore::Impl {
    std::string url;       ///< redacted, for messages
    std::string conninfo;  ///< as given
    mutable std::mutex mutex;
    mutable PGconn* conn = nullptr;

    ~Impl() {
        if (conn) PQfinish(conn);
    }

    /// A working connection: connects, or resets a broken one. Throws kUnavailable.
    PGconn* Connection() const {
        if (!conn) {
            conn = PQconnectdb(conninfo.c_str());
            if (conn) PQsetNoticeProcessor(conn, [](void*, const char*) {}, nullptr);
        } else if (PQstatus(conn) != CONNECTION_OK) {
            PQreset(conn);
        }
        if (!conn || PQstatus(conn) != CONNECTION_OK) {
            const std::string why = conn ? PQerrorMessage(conn) : "out of memory";
            throw Error(ErrorCode::kUnavailable, "postgres " + url + ": " + why);
        }
        return conn;
    }

    /// Runs one statement; throws unless its status is `expect`.
    Result Exec(const char* sql, const Params& params,
                ExecStatusType expect = PGRES_TUPLES_OK) const {
        PGconn* c = Connection();
        std::vector<const char*> ptrs;
        std::vector<int> lengths;
        params.Prepare(ptrs, lengths);
        Result r(PQexecParams(c, sql, params.size(), nullptr, ptrs.data(), lengths.data(),
                              params.formats(), /*resultFormat=*/1));
        Check(r, expect, sql);
        return r;
    }

    /// Runs a script of statements without parameters (DDL, BEGIN/COMMIT).
    void Script(const char* sql) const {
        Result r(PQexec(Connection(), sql));
        Check(r, PGRES_COMMAND_OK, sql);
    }

    void Check(const Result& r, ExecStatusType expect, const char* sql) const {
        if (r && PQresultStatus(r.get()) == expect) return;
        const bool lost = PQstatus(conn) != CONNECTION_OK;
        const std::string why = r ? PQresultErrorMessage(r.get()) : PQerrorMessage(conn);
        throw Error(lost ? ErrorCode::kUnavailable : ErrorCode::kInternal,
                    "postgres " + url + ": " + why + " (in: " + std::string(sql).substr(0, 80) +
                        ")");
    }

    /// BEGIN … COMMIT on this connection, rolled back when left by an exception.
    class Transaction {
    public:
        explicit Transaction(const Impl& db) : db_(db) { db_.Script("BEGIN"); }
        ~Transaction() {
            if (done_) return;
            try {
                db_.Script("ROLLBACK");
            } catch (const Error&) {  // the connection is gone; the server rolls back
            }
        }
        Transaction(const Transaction&) = delete;
        Transaction& operator=(const Transaction&) = delete;
        void Commit() {
            db_.Script("COMMIT");
            done_ = true;
        }

    private:
        const Impl& db_;
        bool done_ = false;
    };
};

PostgresStore::PostgresStore(const std::string& url, const std::string& data_dir)
    : Store(data_dir), impl_(std::make_unique<Impl>()) {
    impl_->url = RedactDatabaseUrl(url);
    impl_->conninfo = url;
    std::lock_guard lock(impl_->mutex);
    const Impl& db = *impl_;
    // Migrations: each one, with its row in schema_migrations, in one transaction under an
    // advisory lock, so servers and workers starting together apply each exactly once.
    {
        Impl::Transaction tx(db);
        db.Exec(kMigrationLock, Params{});
        db.Script(kSchemaMigrationsTable);
        tx.Commit();
    }
    for (const Migration& m : Migrations()) {
        Impl::Transaction tx(db);
        db.Exec(kMigrationLock, Params{});
        Result newest = db.Exec("SELECT COALESCE(MAX(version), 0)::bigint FROM schema_migrations",
                                Params{});
        const std::int64_t applied = Int(newest.get(), 0, 0);
        store_detail::CheckSchemaNotNewer(applied, "postgres " + impl_->url);
        if (applied >= m.version) continue;
        db.Script(m.postgres);
        db.Exec("INSERT INTO schema_migrations (version, name, applied_ms) VALUES ($1, $2, $3)",
                Params().Int(m.version).Text(m.name).Int(NowUnixMs()), PGRES_COMMAND_OK);
        tx.Commit();
    }
}

PostgresStore::~PostgresStore() = default;

// ---- clouds

std::optional<v1::Cloud> PostgresStore::FindCloud(const std::string& id) const {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec("SELECT record FROM clouds WHERE id = $1", Params().Text(id));
    if (PQntuples(r.get()) == 0) return std::nullopt;
    const std::string_view b = Bytes(r.get(), 0, 0);
    v1::Cloud c;
    if (!c.ParseFromArray(b.data(), static_cast<int>(b.size())))
        throw Error(ErrorCode::kInternal, "store: bad cloud record");
    return c;
}

void PostgresStore::PutCloud(const v1::Cloud& cloud) {
    std::lock_guard lock(impl_->mutex);
    impl_->Exec(
        "INSERT INTO clouds (id, record, created_ms) VALUES ($1, $2, $3) "
        "ON CONFLICT (id) DO NOTHING",
        Params().Text(cloud.id()).Bytes(cloud.SerializeAsString()).Int(NowUnixMs()),
        PGRES_COMMAND_OK);
}

bool PostgresStore::DeleteCloudRecord(const std::string& id) {
    std::lock_guard lock(impl_->mutex);
    impl_->Exec("DELETE FROM cloud_owners WHERE cloud_id = $1", Params().Text(id),
                PGRES_COMMAND_OK);
    Result r = impl_->Exec("DELETE FROM clouds WHERE id = $1 RETURNING id", Params().Text(id));
    return PQntuples(r.get()) > 0;
}

bool PostgresStore::CloudOwned(const std::string& tenant, const std::string& id) const {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec("SELECT 1 FROM cloud_owners WHERE tenant = $1 AND cloud_id = $2",
                           Params().Text(tenant).Text(id));
    return PQntuples(r.get()) > 0;
}

void PostgresStore::AddCloudOwner(const std::string& tenant, const std::string& id) {
    std::lock_guard lock(impl_->mutex);
    impl_->Exec(
        "INSERT INTO cloud_owners (tenant, cloud_id) VALUES ($1, $2) ON CONFLICT DO NOTHING",
        Params().Text(tenant).Text(id), PGRES_COMMAND_OK);
}

bool PostgresStore::RemoveCloudOwner(const std::string& tenant, const std::string& id,
                                     std::size_t* remaining) {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec(
        "DELETE FROM cloud_owners WHERE tenant = $1 AND cloud_id = $2 RETURNING cloud_id",
        Params().Text(tenant).Text(id));
    const bool removed = PQntuples(r.get()) > 0;
    if (remaining) {
        Result n = impl_->Exec("SELECT COUNT(*)::bigint FROM cloud_owners WHERE cloud_id = $1",
                               Params().Text(id));
        *remaining = static_cast<std::size_t>(Int(n.get(), 0, 0));
    }
    return removed;
}

// ---- jobs

void PostgresStore::PutJob(const v1::Job& job, const std::string& key) {
    std::lock_guard lock(impl_->mutex);
    impl_->Exec(
        "INSERT INTO jobs (id, key, state, created_ms, record, tenant) "
        "VALUES ($1, $2, $3, $4, $5, $6) "
        "ON CONFLICT (id) DO UPDATE SET state = excluded.state, record = excluded.record",
        Params()
            .Text(job.id())
            .Text(key)
            .Int(job.state())
            .Int(job.created_unix_ms())
            .Bytes(job.SerializeAsString())
            .Text(job.tenant()),
        PGRES_COMMAND_OK);
}

std::optional<v1::Job> PostgresStore::FindJob(const std::string& id) const {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec("SELECT record FROM jobs WHERE id = $1", Params().Text(id));
    if (PQntuples(r.get()) == 0) return std::nullopt;
    return ParseJob(Bytes(r.get(), 0, 0));
}

std::optional<v1::Job> PostgresStore::FindReusable(const std::string& key) const {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec(
        "SELECT record FROM jobs WHERE key = $1 AND state IN ($2, $3, $4) "
        "ORDER BY seq DESC LIMIT 1",
        Params().Text(key).Int(v1::QUEUED).Int(v1::RUNNING).Int(v1::SUCCEEDED));
    if (PQntuples(r.get()) == 0) return std::nullopt;
    return ParseJob(Bytes(r.get(), 0, 0));
}

std::vector<v1::Job> PostgresStore::ListJobs(std::size_t limit, v1::JobState state,
                                             const std::string* tenant) const {
    std::lock_guard lock(impl_->mutex);
    const bool any_state = state == v1::JOB_STATE_UNSPECIFIED;
    std::string sql = "SELECT record FROM jobs";
    Params params;
    int n = 0;
    if (!any_state || tenant) sql += " WHERE ";
    if (!any_state) {
        sql += "state = $" + std::to_string(++n);
        params.Int(state);
    }
    if (!any_state && tenant) sql += " AND ";
    if (tenant) {
        sql += "tenant = $" + std::to_string(++n);
        params.Text(*tenant);
    }
    sql += " ORDER BY seq DESC LIMIT $" + std::to_string(++n);
    params.Int(static_cast<std::int64_t>(limit));
    Result r = impl_->Exec(sql.c_str(), params);
    std::vector<v1::Job> out;
    for (int i = 0; i < PQntuples(r.get()); ++i) out.push_back(ParseJob(Bytes(r.get(), i, 0)));
    return out;
}

std::vector<v1::Job> PostgresStore::Unfinished() const {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec("SELECT record FROM jobs WHERE state IN ($1, $2) ORDER BY seq ASC",
                           Params().Int(v1::QUEUED).Int(v1::RUNNING));
    std::vector<v1::Job> out;
    for (int i = 0; i < PQntuples(r.get()); ++i) out.push_back(ParseJob(Bytes(r.get(), i, 0)));
    return out;
}

// ---- the queue

std::optional<LeasedJob> PostgresStore::ClaimNext(const std::string& owner,
                                                  std::int64_t lease_ms) {
    store_detail::CheckLease(owner, lease_ms);
    std::lock_guard lock(impl_->mutex);
    const Impl& db = *impl_;
    const std::int64_t now = NowUnixMs();
    // The claim is one statement: the oldest QUEUED row not locked by another claimer becomes
    // RUNNING under our lease. The record is rewritten in the same short transaction, so no
    // reader sees the columns and the record disagree.
    Impl::Transaction tx(db);
    Result r = db.Exec(
        "WITH next AS (SELECT id FROM jobs WHERE state = $1 ORDER BY seq LIMIT 1 "
        "FOR UPDATE SKIP LOCKED) "
        "UPDATE jobs SET state = $2, lease_owner = $3, lease_expires_ms = $4 FROM next "
        "WHERE jobs.id = next.id RETURNING jobs.record, jobs.attempts",
        Params().Int(v1::QUEUED).Int(v1::RUNNING).Text(owner).Int(now + lease_ms));
    if (PQntuples(r.get()) == 0) return std::nullopt;
    LeasedJob leased;
    leased.job = store_detail::ClaimedRecord(ParseJob(Bytes(r.get(), 0, 0)), now);
    leased.attempts = static_cast<int>(Int(r.get(), 0, 1));
    leased.owner = owner;
    leased.lease_expires_ms = now + lease_ms;
    db.Exec("UPDATE jobs SET record = $1 WHERE id = $2",
            Params().Bytes(leased.job.SerializeAsString()).Text(leased.job.id()),
            PGRES_COMMAND_OK);
    tx.Commit();
    return leased;
}

bool PostgresStore::Heartbeat(const std::string& job_id, const std::string& owner,
                              std::int64_t lease_ms) {
    store_detail::CheckLease(owner, lease_ms);
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec(
        "UPDATE jobs SET lease_expires_ms = $1 WHERE id = $2 AND lease_owner = $3 AND state = $4 "
        "RETURNING id",
        Params().Int(NowUnixMs() + lease_ms).Text(job_id).Text(owner).Int(v1::RUNNING));
    return PQntuples(r.get()) > 0;
}

bool PostgresStore::PutLeasedJob(const v1::Job& job, const std::string& owner) {
    store_detail::CheckLease(owner, 1);
    std::lock_guard lock(impl_->mutex);
    const bool ends = IsFinal(job.state()) || job.state() == v1::QUEUED;
    Result r = impl_->Exec(
        "UPDATE jobs SET state = $1, record = $2, "
        "lease_owner = CASE WHEN $3::boolean THEN NULL ELSE lease_owner END, "
        "lease_expires_ms = CASE WHEN $3::boolean THEN NULL ELSE lease_expires_ms END "
        "WHERE id = $4 AND lease_owner = $5 AND state = $6 RETURNING id",
        Params()
            .Int(job.state())
            .Bytes(job.SerializeAsString())
            .Text(ends ? "true" : "false")
            .Text(job.id())
            .Text(owner)
            .Int(v1::RUNNING));
    return PQntuples(r.get()) > 0;
}

std::vector<v1::Job> PostgresStore::RequeueExpired(std::int64_t now_unix_ms, int max_attempts) {
    store_detail::CheckMaxAttempts(max_attempts);
    std::lock_guard lock(impl_->mutex);
    const Impl& db = *impl_;
    // One short transaction over the expired rows; rows another sweeper holds are skipped (it
    // requeues them).
    Impl::Transaction tx(db);
    Result r = db.Exec(
        "SELECT record, attempts, lease_owner FROM jobs WHERE state = $1 AND "
        "lease_expires_ms IS NOT NULL AND lease_expires_ms < $2 ORDER BY seq "
        "FOR UPDATE SKIP LOCKED",
        Params().Int(v1::RUNNING).Int(now_unix_ms));
    std::vector<v1::Job> out;
    for (int i = 0; i < PQntuples(r.get()); ++i) {
        const int attempts = static_cast<int>(Int(r.get(), i, 1)) + 1;
        v1::Job job = store_detail::ExpiredRecord(ParseJob(Bytes(r.get(), i, 0)), attempts,
                                                  max_attempts,
                                                  std::string(Bytes(r.get(), i, 2)), now_unix_ms);
        db.Exec(
            "UPDATE jobs SET state = $1, attempts = $2, lease_owner = NULL, "
            "lease_expires_ms = NULL, record = $3 WHERE id = $4",
            Params().Int(job.state()).Int(attempts).Bytes(job.SerializeAsString()).Text(job.id()),
            PGRES_COMMAND_OK);
        out.push_back(std::move(job));
    }
    tx.Commit();
    return out;
}

std::optional<v1::Job> PostgresStore::RequestCancel(const std::string& job_id) {
    std::lock_guard lock(impl_->mutex);
    const Impl& db = *impl_;
    Impl::Transaction tx(db);
    Result r = db.Exec("SELECT record FROM jobs WHERE id = $1 FOR UPDATE", Params().Text(job_id));
    if (PQntuples(r.get()) == 0) return std::nullopt;
    v1::Job job = ParseJob(Bytes(r.get(), 0, 0));
    if (job.state() == v1::QUEUED) {
        job = store_detail::CancelledWhileQueuedRecord(std::move(job), NowUnixMs());
        db.Exec("UPDATE jobs SET state = $1, record = $2, cancel_requested = 1 WHERE id = $3",
                Params().Int(job.state()).Bytes(job.SerializeAsString()).Text(job_id),
                PGRES_COMMAND_OK);
    } else if (job.state() == v1::RUNNING) {
        db.Exec("UPDATE jobs SET cancel_requested = 1 WHERE id = $1", Params().Text(job_id),
                PGRES_COMMAND_OK);
    }
    tx.Commit();
    return job;
}

bool PostgresStore::CancelRequested(const std::string& job_id) const {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec("SELECT cancel_requested FROM jobs WHERE id = $1", Params().Text(job_id));
    return PQntuples(r.get()) > 0 && Int(r.get(), 0, 0) != 0;
}

std::size_t PostgresStore::CountQueued() const {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec("SELECT COUNT(*)::bigint FROM jobs WHERE state = $1",
                           Params().Int(v1::QUEUED));
    return static_cast<std::size_t>(Int(r.get(), 0, 0));
}

std::uint32_t PostgresStore::QueuePosition(const std::string& job_id) const {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec(
        "SELECT COUNT(*)::bigint FROM jobs WHERE state = $1 AND seq < "
        "(SELECT seq FROM jobs WHERE id = $2 AND state = $1)",
        Params().Int(v1::QUEUED).Text(job_id));
    return static_cast<std::uint32_t>(Int(r.get(), 0, 0));
}

// ---- hints: NOTIFY on the store's connection, LISTEN on a connection of the listener's own

namespace {
constexpr const char* kHintChannel = "surfel_hints";

/// A thread that holds `LISTEN surfel_hints` on its own connection and hands each payload to
/// the callback; it reconnects with backoff when the connection drops.
class HintListener final : public Subscription {
public:
    HintListener(std::string conninfo, std::string url, HintFn fn)
        : conninfo_(std::move(conninfo)), url_(std::move(url)), fn_(std::move(fn)) {
        thread_ = std::thread([this] { Loop(); });
    }
    ~HintListener() override {
        {
            std::lock_guard lock(mutex_);
            stop_ = true;
        }
        wake_.notify_all();
        thread_.join();
    }

private:
    /// Sleeps up to `ms` unless stopped; false when stopped.
    bool Sleep(int ms) {
        std::unique_lock lock(mutex_);
        return !wake_.wait_for(lock, std::chrono::milliseconds(ms), [&] { return stop_; });
    }
    bool stopped() {
        std::lock_guard lock(mutex_);
        return stop_;
    }

    void Loop() {
        int backoff_ms = 100;
        bool first = true;
        while (!stopped()) {
            PGconn* c = PQconnectdb(conninfo_.c_str());
            bool listening = false;
            if (c && PQstatus(c) == CONNECTION_OK) {
                PQsetNoticeProcessor(c, [](void*, const char*) {}, nullptr);
                PGresult* r = PQexec(c, (std::string("LISTEN ") + kHintChannel).c_str());
                listening = r && PQresultStatus(r) == PGRES_COMMAND_OK;
                PQclear(r);
            }
            if (!listening) {
                if (c) PQfinish(c);
                if (!Sleep(backoff_ms)) return;
                backoff_ms = std::min(backoff_ms * 2, 2000);
                continue;
            }
            backoff_ms = 100;
            if (!first) fn_("");  // hints may have been missed while disconnected
            first = false;
            while (!stopped()) {
                pollfd p{PQsocket(c), POLLIN, 0};
                if (::poll(&p, 1, 100) < 0) continue;
                if (PQconsumeInput(c) == 0 || PQstatus(c) != CONNECTION_OK) break;
                while (PGnotify* n = PQnotifies(c)) {
                    const std::string payload = n->extra ? n->extra : "";
                    PQfreemem(n);
                    try {
                        fn_(payload);
                    } catch (...) {  // a receiver's failure must not stop the delivery
                    }
                }
            }
            PQfinish(c);
        }
    }

    std::string conninfo_, url_;
    HintFn fn_;
    std::mutex mutex_;
    std::condition_variable wake_;
    bool stop_ = false;
    std::thread thread_;
};
}  // namespace

void PostgresStore::Publish(const std::string& payload) {
    std::lock_guard lock(impl_->mutex);
    impl_->Exec("SELECT pg_notify($1, $2)", Params().Text(kHintChannel).Text(payload));
}

std::unique_ptr<Subscription> PostgresStore::Listen(HintFn fn) {
    return std::make_unique<HintListener>(impl_->conninfo, impl_->url, std::move(fn));
}

}  // namespace surfel::worker

// ---- disk retention (migration 6)

namespace surfel::worker {

void PostgresStore::PutBlobUsage(const std::string& key, std::uint64_t size, std::int64_t now_ms) {
    std::lock_guard lock(impl_->mutex);
    Impl::Transaction tx(*impl_);
    impl_->Exec(
        "INSERT INTO blob_usage (key, size, last_used_ms) VALUES ($1, $2, $3) ON CONFLICT (key) "
        "DO UPDATE SET size = excluded.size, last_used_ms = excluded.last_used_ms",
        Params().Text(key).Int(static_cast<std::int64_t>(size)).Int(now_ms), PGRES_COMMAND_OK);
    impl_->Exec("DELETE FROM evictions WHERE key = $1", Params().Text(key), PGRES_COMMAND_OK);
    tx.Commit();
}

void PostgresStore::TouchBlobUsage(const std::string& key, std::int64_t now_ms) {
    std::lock_guard lock(impl_->mutex);
    impl_->Exec("UPDATE blob_usage SET last_used_ms = GREATEST(last_used_ms, $1) WHERE key = $2",
                Params().Int(now_ms).Text(key), PGRES_COMMAND_OK);
}

std::vector<BlobUsage> PostgresStore::ListBlobUsage() const {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec(
        "SELECT key, size, last_used_ms FROM blob_usage ORDER BY last_used_ms, key", Params());
    std::vector<BlobUsage> out;
    for (int i = 0; i < PQntuples(r.get()); ++i)
        out.push_back({std::string(Bytes(r.get(), i, 0)),
                       static_cast<std::uint64_t>(Int(r.get(), i, 1)), Int(r.get(), i, 2)});
    return out;
}

bool PostgresStore::RemoveBlobUsage(const std::string& key) {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec("DELETE FROM blob_usage WHERE key = $1 RETURNING key", Params().Text(key));
    return PQntuples(r.get()) > 0;
}

void PostgresStore::PutEviction(const std::string& key, const std::string& tenant,
                                const Eviction& eviction) {
    std::lock_guard lock(impl_->mutex);
    impl_->Exec(
        "INSERT INTO evictions (key, tenant, reason, evicted_ms) VALUES ($1, $2, $3, $4) "
        "ON CONFLICT (key, tenant) DO UPDATE SET reason = excluded.reason, "
        "evicted_ms = excluded.evicted_ms",
        Params().Text(key).Text(tenant).Text(eviction.reason).Int(eviction.evicted_ms),
        PGRES_COMMAND_OK);
}

std::optional<Eviction> PostgresStore::FindEviction(const std::string& key,
                                                    const std::string* tenant) const {
    std::lock_guard lock(impl_->mutex);
    Result r = tenant ? impl_->Exec(
                            "SELECT reason, evicted_ms FROM evictions WHERE key = $1 AND "
                            "tenant = $2",
                            Params().Text(key).Text(*tenant))
                      : impl_->Exec(
                            "SELECT reason, evicted_ms FROM evictions WHERE key = $1 ORDER BY "
                            "evicted_ms DESC LIMIT 1",
                            Params().Text(key));
    if (PQntuples(r.get()) == 0) return std::nullopt;
    return Eviction{std::string(Bytes(r.get(), 0, 0)), Int(r.get(), 0, 1)};
}

std::vector<std::string> PostgresStore::CloudOwners(const std::string& id) const {
    std::lock_guard lock(impl_->mutex);
    Result r = impl_->Exec("SELECT tenant FROM cloud_owners WHERE cloud_id = $1 ORDER BY tenant",
                           Params().Text(id));
    std::vector<std::string> out;
    for (int i = 0; i < PQntuples(r.get()); ++i) out.emplace_back(Bytes(r.get(), i, 0));
    return out;
}

}  // namespace surfel::worker
