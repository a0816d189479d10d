#pragma once
/// \file
/// Client library of the Surfel service: upload (resumable, skipped when the server already has
/// the bytes), submit, watch with progress and the result's bytes, cancel, list.

#include <grpcpp/grpcpp.h>

#include <functional>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "surfel/v1/surfel.grpc.pb.h"

namespace surfel::client {

/// A failed RPC: the status as the server sent it.
class RpcError : public std::runtime_error {
public:
    explicit RpcError(const grpc::Status& status, const std::string& what);
    const grpc::Status& status() const { return status_; }

private:
    grpc::Status status_;
};

/// Called with bytes done and total (total 0 when unknown).
using ByteProgress = std::function<void(std::uint64_t done, std::uint64_t total)>;

/// What Watch saw: the final job and, when asked for, the result's bytes.
struct WatchOutcome {
    v1::JobState state = v1::JOB_STATE_UNSPECIFIED;
    v1::JobResult result;   ///< SUCCEEDED
    int status_code = 0;    ///< FAILED / CANCELLED: a grpc::StatusCode
    std::string status_message;
    std::string bytes;      ///< include_result
};

/// How to reach a server that wants credentials (docs/security.md).
struct ConnectOptions {
    /// Sent as `authorization: Bearer <token>` on every call; empty = none.
    std::string token;
    /// TLS with the system's root certificates (or `ca_file`'s).
    bool tls = false;
    /// PEM file of the CA that signed the server's certificate; implies TLS.
    std::string ca_file;
    /// Mutual TLS: this client's certificate chain and key (PEM files); imply TLS.
    std::string cert_file, key_file;
};

class ServiceClient {
public:
    /// `target` is host:port. Connects lazily; `timeout_s` bounds unary calls. Throws
    /// std::runtime_error naming a PEM file of `options` that cannot be read.
    explicit ServiceClient(const std::string& target, double timeout_s = 30.0, const ConnectOptions& options = {});

    /// Uploads a file (chunks of `chunk` bytes). Sending starts at once, under an upload id
    /// that fingerprints the file (size, modification time, first and last MiB), so a broken
    /// upload of the unchanged file resumes where the server's committed size ends. The file's
    /// SHA-256 is computed on a second thread meanwhile: when the server already has that cloud
    /// and less than half of the file is sent, the upload is cancelled and the stored cloud
    /// returned (deduplicated; otherwise the server deduplicates it), and at the end the
    /// server's cloud id must equal it (std::runtime_error otherwise: the file changed).
    v1::Cloud UploadFile(const std::string& path, const ByteProgress& progress = {}, std::size_t chunk = 256 << 10);
    v1::Cloud GetCloud(const std::string& id);
    v1::Job Submit(const v1::JobSpec& spec);
    /// Follows a job to its end. `on_running` gets (stage, fraction); `on_queued` the position.
    WatchOutcome Watch(const std::string& job_id, bool include_result, bool cancel_on_disconnect,
                       const std::function<void(const std::string&, double)>& on_running = {},
                       const std::function<void(std::uint32_t)>& on_queued = {},
                       const ByteProgress& on_bytes = {});
    std::string Download(const std::string& job_id, const ByteProgress& progress = {});
    /// Downloads a job's result into the file `path`, each chunk written as it arrives (never
    /// the whole result in memory): into `path`.tmp-surfel, renamed to `path` once the call
    /// succeeded (the server checked the SHA-256), removed when it failed. Returns the size.
    std::uint64_t DownloadToFile(const std::string& job_id, const std::string& path,
                                 const ByteProgress& progress = {});
    v1::Job Cancel(const std::string& job_id);
    v1::Job GetJob(const std::string& job_id);
    std::vector<v1::Job> ListJobs(std::uint32_t limit = 100, v1::JobState state = v1::JOB_STATE_UNSPECIFIED);
    bool DeleteCloud(const std::string& id);

    const std::string& target() const { return target_; }

private:
    void Authorize(grpc::ClientContext& ctx) const;

    std::string target_;
    double timeout_s_;
    std::string token_;
    std::shared_ptr<grpc::Channel> channel_;
    std::unique_ptr<v1::Surfel::Stub> stub_;
};

}  // namespace surfel::client
