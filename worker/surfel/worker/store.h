#pragma once
/// \file
/// Persistence of the service: SQLite (WAL) for clouds and jobs, a blob directory for uploads,
/// clouds and results, all under one data directory.
///
///   <data>/surfel.db            tables `clouds` and `jobs`
///   <data>/uploads/<id>.part    bytes of unfinished uploads (resumable)
///   <data>/clouds/<sha256>      uploaded files, content-addressed
///   <data>/results/<job id>     job results

#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/sha256.h"

namespace surfel::worker {

class Store {
public:
    /// Opens (creating when missing) the data directory and its database. Throws surfel::Error.
    explicit Store(const std::string& data_dir);
    ~Store();
    Store(const Store&) = delete;
    Store& operator=(const Store&) = delete;

    const std::string& data_dir() const { return data_dir_; }
    std::string CloudPath(const std::string& cloud_id) const;
    std::string ResultPath(const std::string& job_id) const;
    std::string UploadPath(const std::string& upload_id) const;

    // ---- clouds
    std::optional<v1::Cloud> FindCloud(const std::string& id) const;
    /// Records a cloud whose bytes are already at CloudPath(id); no-op when it exists.
    void PutCloud(const v1::Cloud& cloud);
    /// Removes the record and the bytes; false when unknown.
    bool DeleteCloud(const std::string& id);

    // ---- jobs (stored as serialized surfel.v1.Job plus indexed columns)
    void PutJob(const v1::Job& job, const std::string& key);  ///< insert or replace
    std::optional<v1::Job> FindJob(const std::string& id) const;
    /// The newest job with this key that is queued, running or succeeded.
    std::optional<v1::Job> FindReusable(const std::string& key) const;
    std::vector<v1::Job> ListJobs(std::size_t limit, v1::JobState state) const;
    /// Jobs left QUEUED or RUNNING (by a crash or a shutdown), oldest first.
    std::vector<v1::Job> Unfinished() const;

private:
    struct Impl;
    std::string data_dir_;
    std::unique_ptr<Impl> impl_;
};

/// Milliseconds since the Unix epoch.
std::int64_t NowUnixMs();

}  // namespace surfel::worker
