// The large-object backend of the blob store ("--blobs postgres"): libpq's large objects in the
// store's database, indexed by table `blobs` (key, oid, size, sha256; migration 5).
//
// A put is one transaction: lo_creat, lo_open, lo_write in chunks (1 MiB), lo_tell64 to check
// the size, then the row (an advisory lock on the key serialises two puts of one key, and the
// large object it replaces is unlinked in the same transaction). Nothing is visible before the
// COMMIT, and a COMMIT is durable under PostgreSQL's own settings (synchronous_commit = on, the
// default). A read is one read-only transaction holding the large object open: lo_lseek64 /
// lo_tell64 (64-bit: large objects over 2 GiB), lo_read in chunks.
#include <libpq-fe.h>
#include <libpq/libpq-fs.h>

#include <fstream>
#include <mutex>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/worker/blob_store.h"
#include "surfel/worker/store.h"
#include "surfel/worker/store_postgres.h"

namespace surfel::worker {
namespace {

/// Owns a PGresult.
struct ResultDeleter {
    void operator()(PGresult* r) const { PQclear(r); }
};
using Result = std::unique_ptr<PGresult, ResultDeleter>;

/// A pool of connections to one database: a caller takes one for a transaction and gives it
/// back; broken connections are dropped.
class Pool {
public:
    explicit Pool(std::string conninfo)
        : conninfo_(std::move(conninfo)), url_(RedactDatabaseUrl(conninfo_)) {}
    ~Pool() {
        for (PGconn* c : idle_) PQfinish(c);
    }
    const std::string& url() const { return url_; }

    PGconn* Take() {
        {
            std::lock_guard lock(mutex_);
            while (!idle_.empty()) {
                PGconn* c = idle_.back();
                idle_.pop_back();
                if (PQstatus(c) == CONNECTION_OK) return c;
                PQfinish(c);
            }
        }
        PGconn* c = PQconnectdb(conninfo_.c_str());
        if (!c || PQstatus(c) != CONNECTION_OK) {
            const std::string why = c ? PQerrorMessage(c) : "out of memory";
            if (c) PQfinish(c);
            throw Error(ErrorCode::kUnavailable, "blobs: postgres " + url_ + ": " + why);
        }
        PQsetNoticeProcessor(c, [](void*, const char*) {}, nullptr);
        return c;
    }
    void Give(PGconn* c) {
        if (!c) return;
        std::lock_guard lock(mutex_);
        if (PQstatus(c) != CONNECTION_OK || PQtransactionStatus(c) != PQTRANS_IDLE ||
            idle_.size() >= kMaxIdle) {
            PQfinish(c);
            return;
        }
        idle_.push_back(c);
    }

private:
    static constexpr std::size_t kMaxIdle = 8;
    std::string conninfo_, url_;
    std::mutex mutex_;
    std::vector<PGconn*> idle_;
};

/// The error of a failed libpq call on `c`: kUnavailable when the connection is gone.
[[noreturn]] void Fail(PGconn* c, const std::string& what) {
    const bool lost = PQstatus(c) != CONNECTION_OK;
    std::string why = PQerrorMessage(c);
    while (!why.empty() && (why.back() == '\n' || why.back() == ' ')) why.pop_back();
    throw Error(lost ? ErrorCode::kUnavailable : ErrorCode::kInternal,
                "blobs: " + what + ": " + why);
}

/// Runs one statement with text parameters; throws unless its status is `expect`.
Result Exec(PGconn* c, const char* sql, std::initializer_list<std::string> params,
            ExecStatusType expect) {
    std::vector<const char*> values;
    for (const std::string& p : params) values.push_back(p.c_str());
    Result r(PQexecParams(c, sql, static_cast<int>(values.size()), nullptr, values.data(),
                          nullptr, nullptr, 0));
    if (!r || PQresultStatus(r.get()) != expect) {
        const bool lost = PQstatus(c) != CONNECTION_OK;
        std::string why = r ? PQresultErrorMessage(r.get()) : PQerrorMessage(c);
        while (!why.empty() && (why.back() == '\n' || why.back() == ' ')) why.pop_back();
        throw Error(lost ? ErrorCode::kUnavailable : ErrorCode::kInternal,
                    "blobs: " + why + " (in: " + std::string(sql).substr(0, 60) + ")");
    }
    return r;
}

/// A connection from the pool with a transaction on it: BEGIN at construction, ROLLBACK unless
/// committed, the connection given back at the end.
class Tx {
public:
    Tx(Pool& pool, const char* begin = "BEGIN") : pool_(pool), c_(pool.Take()) {
        try {
            Exec(c_, begin, {}, PGRES_COMMAND_OK);
        } catch (...) {
            PQfinish(c_);
            throw;
        }
    }
    ~Tx() {
        if (!done_) {
            Result r(PQexec(c_, "ROLLBACK"));
        }
        pool_.Give(c_);
    }
    Tx(const Tx&) = delete;
    Tx& operator=(const Tx&) = delete;
    PGconn* conn() const { return c_; }
    void Commit() {
        Exec(c_, "COMMIT", {}, PGRES_COMMAND_OK);
        done_ = true;
    }

private:
    Pool& pool_;
    PGconn* c_;
    bool done_ = false;
};

/// A large object open for reading inside its own read-only transaction.
class LargeObjectReader final : public BlobReader {
public:
    LargeObjectReader(std::unique_ptr<Tx> tx, int fd, std::uint64_t size, std::string key)
        : tx_(std::move(tx)), fd_(fd), size_(size), key_(std::move(key)) {}
    ~LargeObjectReader() override {
        lo_close(tx_->conn(), fd_);
        try {
            tx_->Commit();
        } catch (const Error&) {  // read-only: a failed COMMIT loses nothing
        }
    }
    std::uint64_t size() const override { return size_; }
    std::size_t Read(char* buf, std::size_t n) override {
        const int got = lo_read(tx_->conn(), fd_, buf, std::min<std::size_t>(n, 1 << 30));
        if (got < 0) Fail(tx_->conn(), "lo_read of blob " + key_);
        return static_cast<std::size_t>(got);
    }
    void Seek(std::uint64_t offset) override {
        if (lo_lseek64(tx_->conn(), fd_, static_cast<pg_int64>(offset), SEEK_SET) < 0)
            Fail(tx_->conn(), "lo_lseek64 of blob " + key_);
    }

private:
    std::unique_ptr<Tx> tx_;
    int fd_;
    std::uint64_t size_;
    std::string key_;
};

class LargeObjectBlobStore final : public BlobStore {
public:
    LargeObjectBlobStore(const std::string& url, std::size_t chunk_bytes)
        : pool_(url), chunk_(chunk_bytes) {
        if (chunk_ == 0 || chunk_ > (1u << 30))
            throw Error(ErrorCode::kInvalidArgument, "blobs: chunk_bytes must be in 1..2^30");
        Tx tx(pool_);  // reachable, and migration 5 applied
        Exec(tx.conn(), "SELECT 1 FROM blobs LIMIT 1", {}, PGRES_TUPLES_OK);
        tx.Commit();
    }

    std::string Describe() const override {
        return "postgres large objects (" + pool_.url() + ")";
    }

    void PutFile(const std::string& key, const std::string& path,
                 const std::string& sha256) override {
        std::ifstream in(path, std::ios::binary);
        if (!in) throw Error(ErrorCode::kInternal, "storing blob " + key + ": cannot open " + path);
        std::string buf(chunk_, '\0');
        Put(key, sha256, [&]() -> std::string_view {
            in.read(buf.data(), static_cast<std::streamsize>(buf.size()));
            if (in.bad())
                throw Error(ErrorCode::kInternal, "storing blob " + key + ": reading " + path);
            return {buf.data(), static_cast<std::size_t>(in.gcount())};
        });
        in.close();
        std::remove(path.c_str());
    }

    void PutBytes(const std::string& key, std::string_view bytes,
                  const std::string& sha256) override {
        std::size_t at = 0;
        Put(key, sha256, [&]() -> std::string_view {
            const std::size_t n = std::min(chunk_, bytes.size() - at);
            const std::string_view piece = bytes.substr(at, n);
            at += n;
            return piece;
        });
    }

    std::unique_ptr<BlobReader> Open(const std::string& key) const override {
        auto tx = std::make_unique<Tx>(pool_, "BEGIN ISOLATION LEVEL REPEATABLE READ READ ONLY");
        PGconn* c = tx->conn();
        Result row = Exec(c, "SELECT oid, size FROM blobs WHERE key = $1", {key}, PGRES_TUPLES_OK);
        if (PQntuples(row.get()) == 0) return nullptr;
        const Oid oid = static_cast<Oid>(std::stoul(PQgetvalue(row.get(), 0, 0)));
        const std::uint64_t size = std::stoull(PQgetvalue(row.get(), 0, 1));
        const int fd = lo_open(c, oid, INV_READ);
        if (fd < 0) Fail(c, "lo_open of blob " + key + " (oid " + std::to_string(oid) + ")");
        // The object's real length (64-bit calls: objects over 2 GiB) against the recorded one.
        const pg_int64 end = lo_lseek64(c, fd, 0, SEEK_END);
        const pg_int64 told = lo_tell64(c, fd);
        if (end < 0 || told < 0) Fail(c, "lo_lseek64 of blob " + key);
        if (static_cast<std::uint64_t>(told) != size)
            throw Error(ErrorCode::kDataLoss, "blob " + key + " is corrupt: large object " +
                                                  std::to_string(oid) + " has " +
                                                  std::to_string(told) + " bytes, recorded " +
                                                  std::to_string(size));
        if (lo_lseek64(c, fd, 0, SEEK_SET) < 0) Fail(c, "lo_lseek64 of blob " + key);
        return std::make_unique<LargeObjectReader>(std::move(tx), fd, size, key);
    }

    std::optional<std::uint64_t> Size(const std::string& key) const override {
        Tx tx(pool_);
        Result row =
            Exec(tx.conn(), "SELECT size FROM blobs WHERE key = $1", {key}, PGRES_TUPLES_OK);
        tx.Commit();
        if (PQntuples(row.get()) == 0) return std::nullopt;
        return std::stoull(PQgetvalue(row.get(), 0, 0));
    }

    std::vector<std::pair<std::string, std::uint64_t>> List() const override {
        Tx tx(pool_);
        Result rows = Exec(tx.conn(), "SELECT key, size FROM blobs ORDER BY key", {},
                           PGRES_TUPLES_OK);
        tx.Commit();
        std::vector<std::pair<std::string, std::uint64_t>> out;
        for (int i = 0; i < PQntuples(rows.get()); ++i)
            out.emplace_back(PQgetvalue(rows.get(), i, 0),
                             std::stoull(PQgetvalue(rows.get(), i, 1)));
        return out;
    }

    bool Remove(const std::string& key) override {
        Tx tx(pool_);
        PGconn* c = tx.conn();
        Exec(c, "SELECT pg_advisory_xact_lock(hashtext($1))", {key}, PGRES_TUPLES_OK);
        Result row = Exec(c, "DELETE FROM blobs WHERE key = $1 RETURNING oid", {key},
                          PGRES_TUPLES_OK);
        if (PQntuples(row.get()) == 0) return false;
        const Oid oid = static_cast<Oid>(std::stoul(PQgetvalue(row.get(), 0, 0)));
        if (lo_unlink(c, oid) < 0) Fail(c, "lo_unlink of blob " + key);
        tx.Commit();
        return true;
    }

private:
    /// One transaction: a new large object filled from `next` (pieces until an empty one),
    /// hashed while written; the row replaces the key's old object, which is unlinked.
    template <class Next>
    void Put(const std::string& key, const std::string& sha256, Next next) {
        Tx tx(pool_);
        PGconn* c = tx.conn();
        const Oid oid = lo_creat(c, INV_READ | INV_WRITE);
        if (oid == InvalidOid) Fail(c, "lo_creat for blob " + key);
        const int fd = lo_open(c, oid, INV_WRITE);
        if (fd < 0) Fail(c, "lo_open for blob " + key);
        Sha256 hash;
        std::uint64_t written = 0;
        for (std::string_view piece = next(); !piece.empty(); piece = next()) {
            hash.Update(piece);
            const int n = lo_write(c, fd, piece.data(), piece.size());
            if (n < 0 || static_cast<std::size_t>(n) != piece.size())
                Fail(c, "lo_write of blob " + key + " at byte " + std::to_string(written));
            written += piece.size();
        }
        const pg_int64 told = lo_tell64(c, fd);
        if (told < 0) Fail(c, "lo_tell64 of blob " + key);
        if (static_cast<std::uint64_t>(told) != written)
            throw Error(ErrorCode::kInternal, "blob " + key + ": wrote " +
                                                  std::to_string(written) + " bytes, lo_tell64 " +
                                                  std::to_string(told));
        if (lo_close(c, fd) < 0) Fail(c, "lo_close of blob " + key);
        const std::string actual = hash.FinishHex();
        if (actual != sha256)
            throw Error(ErrorCode::kDataLoss,
                        CorruptBlobMessage(sha256, actual, "while storing " + key));
        Exec(c, "SELECT pg_advisory_xact_lock(hashtext($1))", {key}, PGRES_TUPLES_OK);
        Result old = Exec(c, "SELECT oid FROM blobs WHERE key = $1", {key}, PGRES_TUPLES_OK);
        if (PQntuples(old.get()) > 0) {
            const Oid old_oid = static_cast<Oid>(std::stoul(PQgetvalue(old.get(), 0, 0)));
            if (lo_unlink(c, old_oid) < 0) Fail(c, "lo_unlink of the old blob " + key);
            Exec(c, "UPDATE blobs SET oid = $2, size = $3, sha256 = $4, created_ms = $5 WHERE key = $1",
                 {key, std::to_string(oid), std::to_string(written), sha256,
                  std::to_string(NowUnixMs())},
                 PGRES_COMMAND_OK);
        } else {
            Exec(c,
                 "INSERT INTO blobs (key, oid, size, sha256, created_ms) VALUES ($1, $2, $3, $4, "
                 "$5)",
                 {key, std::to_string(oid), std::to_string(written), sha256,
                  std::to_string(NowUnixMs())},
                 PGRES_COMMAND_OK);
        }
        tx.Commit();
    }

    mutable Pool pool_;
    std::size_t chunk_;
};

}  // namespace

std::unique_ptr<BlobStore> OpenLargeObjectBlobStore(const std::string& url,
                                                    std::size_t chunk_bytes) {
    return std::make_unique<LargeObjectBlobStore>(url, chunk_bytes);
}

}  // namespace surfel::worker
