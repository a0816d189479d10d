#include "surfel/worker/store.h"

#include <chrono>
#include <filesystem>
#include <system_error>

#include "surfel/base/error.h"
#include "surfel/worker/status.h"
#include "surfel/worker/store_common.h"
#include "surfel/worker/store_migrations.h"
#include "surfel/worker/store_postgres.h"

namespace surfel::worker {
namespace fs = std::filesystem;

// ---- the interface's shared part: the blob directory

Store::Store(const std::string& data_dir) : data_dir_(data_dir) {
    if (data_dir.empty()) return;
    std::error_code ec;
    for (const char* sub : {"", "/uploads", "/clouds", "/results"}) {
        fs::create_directories(data_dir + sub, ec);
        if (ec)
            throw Error(ErrorCode::kInvalidArgument,
                        "data dir " + data_dir + sub + ": " + ec.message());
    }
    blobs_ = std::make_unique<DirBlobStore>(data_dir);
}

Store::~Store() = default;
Subscription::~Subscription() = default;

std::string Store::CloudPath(const std::string& id) const { return data_dir_ + "/clouds/" + id; }
std::string Store::ResultPath(const std::string& id) const { return data_dir_ + "/results/" + id; }
std::string Store::UploadPath(const std::string& id) const {
    return data_dir_ + "/uploads/" + id + ".part";
}

bool Store::DeleteCloud(const std::string& id) {
    const bool existed = DeleteCloudRecord(id);
    // An empty id would name the clouds folder itself, and removing it (when empty) made every
    // later upload fail (found by the API fuzzer).
    if (blobs_ && !id.empty()) blobs_->Remove(CloudBlobKey(id));
    return existed;
}

// ---- the factory

namespace {
std::unique_ptr<Store> OpenRecords(const std::string& url_or_dir, const std::string& data_dir) {
    if (url_or_dir.empty() || url_or_dir == "sqlite")
        return std::make_unique<SqliteStore>(data_dir);
    if (url_or_dir.starts_with("sqlite:"))
        return std::make_unique<SqliteStore>(url_or_dir.substr(7), data_dir);
    if (url_or_dir.starts_with("postgres://") || url_or_dir.starts_with("postgresql://"))
        return std::make_unique<PostgresStore>(url_or_dir, data_dir);
    if (url_or_dir.find("://") != std::string::npos)
        throw Error(
            ErrorCode::kInvalidArgument,
            "store " + url_or_dir +
                ": unknown scheme (use sqlite, sqlite:FILE, a directory or postgres://...)");
    const std::string blobs = data_dir.empty() ? url_or_dir : data_dir;
    return std::make_unique<SqliteStore>(url_or_dir + "/surfel.db", blobs);
}
}  // namespace

std::unique_ptr<Store> OpenStore(const std::string& url_or_dir, const std::string& data_dir,
                                 const std::string& blobs) {
    const bool large_objects = blobs == "postgres";
    const bool postgres =
        url_or_dir.starts_with("postgres://") || url_or_dir.starts_with("postgresql://");
    if (large_objects && !postgres)
        throw Error(ErrorCode::kInvalidArgument,
                    "--blobs postgres: needs --store postgres://... (the large objects live in "
                    "that database); got --store " +
                        (url_or_dir.empty() ? std::string("sqlite (the default)") : url_or_dir));
    std::unique_ptr<Store> store = OpenRecords(url_or_dir, data_dir);
    if (large_objects) store->SetBlobs(OpenLargeObjectBlobStore(url_or_dir));
    if (!store->has_blobs())
        throw Error(ErrorCode::kInvalidArgument,
                    "--blobs: none given (dir:PATH, or postgres with a PostgreSQL --store)");
    return store;
}

std::string BlobDirFromFlag(const std::string& blobs, const std::string& default_dir) {
    if (blobs.empty()) return default_dir;
    if (blobs.starts_with("dir:") && blobs.size() > 4) return blobs.substr(4);
    if (blobs == "postgres") return default_dir;
    throw Error(ErrorCode::kInvalidArgument,
                "--blobs " + blobs + ": expected dir:PATH or postgres");
}

std::int64_t NowUnixMs() {
    return std::chrono::duration_cast<std::chrono::milliseconds>(
               std::chrono::system_clock::now().time_since_epoch())
        .count();
}

std::string LeaseExhaustedMessage(int attempts, int max_attempts, const std::string& last_owner) {
    return "lease expired on attempt " + std::to_string(attempts) + " of " +
           std::to_string(max_attempts) + " (last owner " + last_owner + "); giving up";
}

// ---- shared by the backends

namespace store_detail {

v1::Job ClaimedRecord(v1::Job job, std::int64_t now_unix_ms) {
    job.set_state(v1::RUNNING);
    job.set_started_unix_ms(now_unix_ms);
    job.set_fraction(0);
    job.clear_stage();
    return job;
}

v1::Job ExpiredRecord(v1::Job job, int attempts, int max_attempts, const std::string& last_owner,
                      std::int64_t now_unix_ms) {
    job.set_fraction(0);
    job.clear_stage();
    if (attempts < max_attempts) {
        job.set_state(v1::QUEUED);
        job.set_started_unix_ms(0);
        return job;
    }
    job.set_state(v1::FAILED);
    job.set_finished_unix_ms(now_unix_ms);
    job.set_status_code(ToStatusCode(ErrorCode::kUnavailable));
    job.set_status_message(LeaseExhaustedMessage(attempts, max_attempts, last_owner));
    return job;
}

v1::Job CancelledWhileQueuedRecord(v1::Job job, std::int64_t now_unix_ms) {
    job.set_state(v1::CANCELLED);
    job.set_finished_unix_ms(now_unix_ms);
    job.set_status_code(ToStatusCode(ErrorCode::kCancelled));
    job.set_status_message("cancelled while queued");
    return job;
}

void CheckSchemaNotNewer(std::int64_t applied_version, const std::string& where) {
    const int known = Migrations().back().version;
    if (applied_version > known)
        throw Error(ErrorCode::kFailedPrecondition,
                    where + ": schema version " + std::to_string(applied_version) +
                        " is newer than this program's " + std::to_string(known) +
                        " (a newer release migrated it)");
}

void CheckLease(const std::string& owner, std::int64_t lease_ms) {
    if (owner.empty()) throw Error(ErrorCode::kInvalidArgument, "lease owner: must not be empty");
    if (lease_ms <= 0)
        throw Error(ErrorCode::kInvalidArgument,
                    "lease_ms: must be > 0, got " + std::to_string(lease_ms));
}

void CheckMaxAttempts(int max_attempts) {
    if (max_attempts < 1)
        throw Error(ErrorCode::kInvalidArgument,
                    "max_attempts: must be >= 1, got " + std::to_string(max_attempts));
}

}  // namespace store_detail
}  // namespace surfel::worker
