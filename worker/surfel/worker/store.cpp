#include "surfel/worker/store.h"

#include <SQLiteCpp/SQLiteCpp.h>

#include <chrono>
#include <cstdio>
#include <filesystem>

#include "surfel/base/error.h"

namespace surfel::worker {
namespace fs = std::filesystem;

struct Store::Impl {
    explicit Impl(const std::string& path)
        : db(path, SQLite::OPEN_READWRITE | SQLite::OPEN_CREATE | SQLite::OPEN_FULLMUTEX) {}
    mutable std::mutex mutex;
    SQLite::Database db;
};

namespace {

v1::Job ParseJob(const SQLite::Column& blob) {
    v1::Job job;
    if (!job.ParseFromArray(blob.getBlob(), blob.getBytes()))
        throw Error(ErrorCode::kInternal, "store: a job record does not parse");
    return job;
}

}  // namespace

Store::Store(const std::string& data_dir) : data_dir_(data_dir) {
    std::error_code ec;
    for (const char* sub : {"", "/uploads", "/clouds", "/results"}) {
        fs::create_directories(data_dir + sub, ec);
        if (ec) throw Error(ErrorCode::kInvalidArgument, "data dir " + data_dir + sub + ": " + ec.message());
    }
    try {
        impl_ = std::make_unique<Impl>(data_dir + "/surfel.db");
        auto& db = impl_->db;
        db.exec("PRAGMA journal_mode=WAL");
        db.exec("PRAGMA synchronous=NORMAL");  // durable across process crashes in WAL mode
        db.exec("PRAGMA busy_timeout=5000");
        db.exec(
            "CREATE TABLE IF NOT EXISTS clouds (id TEXT PRIMARY KEY, record BLOB NOT NULL, created_ms INTEGER NOT "
            "NULL)");
        db.exec(
            "CREATE TABLE IF NOT EXISTS jobs (id TEXT PRIMARY KEY, key TEXT NOT NULL, state INTEGER NOT NULL, "
            "created_ms INTEGER NOT NULL, seq INTEGER NOT NULL, record BLOB NOT NULL)");
        db.exec("CREATE INDEX IF NOT EXISTS jobs_key ON jobs(key)");
        db.exec("CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state)");
    } catch (const SQLite::Exception& e) {
        throw Error(ErrorCode::kInternal, "database " + data_dir + "/surfel.db: " + e.what());
    }
}

Store::~Store() = default;

std::string Store::CloudPath(const std::string& id) const { return data_dir_ + "/clouds/" + id; }
std::string Store::ResultPath(const std::string& id) const { return data_dir_ + "/results/" + id; }
std::string Store::UploadPath(const std::string& id) const { return data_dir_ + "/uploads/" + id + ".part"; }

std::optional<v1::Cloud> Store::FindCloud(const std::string& id) const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "SELECT record FROM clouds WHERE id = ?");
    q.bind(1, id);
    if (!q.executeStep()) return std::nullopt;
    v1::Cloud c;
    const SQLite::Column col = q.getColumn(0);
    if (!c.ParseFromArray(col.getBlob(), col.getBytes())) throw Error(ErrorCode::kInternal, "store: bad cloud record");
    return c;
}

void Store::PutCloud(const v1::Cloud& cloud) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "INSERT OR IGNORE INTO clouds (id, record, created_ms) VALUES (?, ?, ?)");
    const std::string blob = cloud.SerializeAsString();
    q.bind(1, cloud.id());
    q.bind(2, blob.data(), static_cast<int>(blob.size()));
    q.bind(3, static_cast<std::int64_t>(NowUnixMs()));
    q.exec();
}

bool Store::DeleteCloud(const std::string& id) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "DELETE FROM clouds WHERE id = ?");
    q.bind(1, id);
    const bool existed = q.exec() > 0;
    std::error_code ec;
    fs::remove(CloudPath(id), ec);
    return existed;
}

void Store::PutJob(const v1::Job& job, const std::string& key) {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db,
                        "INSERT INTO jobs (id, key, state, created_ms, seq, record) VALUES (?, ?, ?, ?, "
                        "(SELECT COALESCE(MAX(seq), 0) + 1 FROM jobs), ?) ON CONFLICT(id) DO UPDATE SET "
                        "state = excluded.state, record = excluded.record");
    const std::string blob = job.SerializeAsString();
    q.bind(1, job.id());
    q.bind(2, key);
    q.bind(3, static_cast<int>(job.state()));
    q.bind(4, static_cast<std::int64_t>(job.created_unix_ms()));
    q.bind(5, blob.data(), static_cast<int>(blob.size()));
    q.exec();
}

std::optional<v1::Job> Store::FindJob(const std::string& id) const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db, "SELECT record FROM jobs WHERE id = ?");
    q.bind(1, id);
    if (!q.executeStep()) return std::nullopt;
    return ParseJob(q.getColumn(0));
}

std::optional<v1::Job> Store::FindReusable(const std::string& key) const {
    std::lock_guard lock(impl_->mutex);
    SQLite::Statement q(impl_->db,
                        "SELECT record FROM jobs WHERE key = ? AND state IN (?, ?, ?) ORDER BY seq DESC LIMIT 1");
    q.bind(1, key);
    q.bind(2, static_cast<int>(v1::QUEUED));
    q.bind(3, static_cast<int>(v1::RUNNING));
    q.bind(4, static_cast<int>(v1::SUCCEEDED));
    if (!q.executeStep()) return std::nullopt;
    return ParseJob(q.getColumn(0));
}

std::vector<v1::Job> Store::ListJobs(std::size_t limit, v1::JobState state) const {
    std::lock_guard lock(impl_->mutex);
    std::vector<v1::Job> out;
    SQLite::Statement q(impl_->db, state == v1::JOB_STATE_UNSPECIFIED
                                       ? "SELECT record FROM jobs ORDER BY seq DESC LIMIT ?"
                                       : "SELECT record FROM jobs WHERE state = ? ORDER BY seq DESC LIMIT ?");
    int i = 1;
    if (state != v1::JOB_STATE_UNSPECIFIED) q.bind(i++, static_cast<int>(state));
    q.bind(i, static_cast<std::int64_t>(limit));
    while (q.executeStep()) out.push_back(ParseJob(q.getColumn(0)));
    return out;
}

std::vector<v1::Job> Store::Unfinished() const {
    std::lock_guard lock(impl_->mutex);
    std::vector<v1::Job> out;
    SQLite::Statement q(impl_->db, "SELECT record FROM jobs WHERE state IN (?, ?) ORDER BY seq ASC");
    q.bind(1, static_cast<int>(v1::QUEUED));
    q.bind(2, static_cast<int>(v1::RUNNING));
    while (q.executeStep()) out.push_back(ParseJob(q.getColumn(0)));
    return out;
}

std::int64_t NowUnixMs() {
    return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
        .count();
}

}  // namespace surfel::worker
