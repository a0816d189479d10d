#pragma once
/// \file
/// Blobs (uploaded clouds, job results) behind one interface, with two backends chosen by the
/// `--blobs` flag (OpenStore in store.h):
///
///   dir:PATH    a directory, local disk or a shared mount (NFS, CephFS, a Kubernetes
///               ReadWriteMany volume): PATH/clouds/<sha256>, PATH/results/<job id>. Written
///               into a temp file, fsynced, renamed into place, and the directory fsynced before
///               Put returns (docs/durability.md).
///   postgres    PostgreSQL large objects in the store's database (blob_store_postgres.cpp):
///               table `blobs` maps a key to its large object's oid, size and SHA-256; written
///               and read in 1 MiB chunks with the 64-bit lo_lseek64/lo_tell64, so blobs over
///               2 GiB work and no blob is ever held whole in memory by the store.
///
/// Keys are "clouds/<sha256>" (CloudBlobKey) and "results/<job id>" (ResultBlobKey). Blobs are
/// content-checked: a reader gets the SHA-256 recorded for the blob (a cloud's id is its
/// SHA-256; a result's is in JobResult.sha256) and VerifyingReader / ReadVerified fail with
/// kDataLoss when the bytes read do not hash to it — a flipped byte on disk never becomes a
/// wrong result.
///
/// Every method is safe to call from several threads. Errors are surfel::Error: kUnavailable
/// when the database or the mount cannot be reached, kDataLoss for bytes that do not match
/// their SHA-256, kInternal for anything else the backend refuses.

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "surfel/worker/sha256.h"

namespace surfel::worker {

/// One blob, read front to back in chunks (Seek for a ranged read). One thread at a time.
class BlobReader {
public:
    virtual ~BlobReader();
    /// The blob's size in bytes.
    virtual std::uint64_t size() const = 0;
    /// Reads up to `n` bytes into `buf`; returns how many, 0 only at the end. Throws
    /// kUnavailable / kInternal.
    virtual std::size_t Read(char* buf, std::size_t n) = 0;
    /// Moves to byte `offset` (<= size()); the next Read starts there.
    virtual void Seek(std::uint64_t offset) = 0;
};

/// The blob store interface.
class BlobStore {
public:
    virtual ~BlobStore();
    /// For logs: "dir:/var/lib/surfel" or "postgres large objects (postgres://…)".
    virtual std::string Describe() const = 0;
    /// Stores the file at `path` under `key`, replacing any blob there; `sha256` is the file's
    /// SHA-256 (hex), recorded with it. The file is consumed (moved or copied, then removed).
    /// Durable (fsynced, or committed) before it returns. kDataLoss when a backend that copies
    /// the bytes finds they do not hash to `sha256` (the file changed after it was hashed).
    virtual void PutFile(const std::string& key, const std::string& path,
                         const std::string& sha256) = 0;
    /// Stores `bytes` under `key` (replacing), `sha256` being their SHA-256; durable on return.
    virtual void PutBytes(const std::string& key, std::string_view bytes,
                          const std::string& sha256) = 0;
    /// Opens a blob for reading; nullptr when there is none under `key`.
    virtual std::unique_ptr<BlobReader> Open(const std::string& key) const = 0;
    /// The blob's size; nullopt when there is none.
    virtual std::optional<std::uint64_t> Size(const std::string& key) const = 0;
    bool Exists(const std::string& key) const { return Size(key).has_value(); }
    /// Removes a blob; false when there was none.
    virtual bool Remove(const std::string& key) = 0;
    /// True when PutFile moves the file itself into the store (a rename) rather than copying
    /// its bytes: syncing the file to disk early (while an upload is received and validated)
    /// then shortens PutFile. The directory backend; not the large objects.
    virtual bool AdoptsFiles() const { return false; }
    /// Every stored blob (key, size in bytes), sorted by key; never a temp file of a put in
    /// progress. For retention's accounting at start (retention.h).
    virtual std::vector<std::pair<std::string, std::uint64_t>> List() const = 0;
};

/// "clouds/<id>": the key of an uploaded cloud (its id is the SHA-256 of its bytes).
std::string CloudBlobKey(const std::string& cloud_id);
/// "results/<job id>": the key of a job's result.
std::string ResultBlobKey(const std::string& job_id);

/// The message of a blob that failed its check: "blob <expected> (<what>) is corrupt: sha256
/// <actual> != <expected>", `what` naming its owner ("cloud <id>", "result of job <id>").
std::string CorruptBlobMessage(const std::string& expected, const std::string& actual,
                               const std::string& what);

/// Wraps a reader and hashes every byte that passes; when the last byte has been read, the
/// SHA-256 must equal `expected` or Read throws kDataLoss (CorruptBlobMessage). An empty
/// `expected` checks nothing (results recorded before checks existed). A Seek away from the
/// sequential position turns the check off (a ranged read cannot be checked).
class VerifyingReader final : public BlobReader {
public:
    VerifyingReader(std::unique_ptr<BlobReader> inner, std::string expected, std::string what);
    std::uint64_t size() const override { return inner_->size(); }
    std::size_t Read(char* buf, std::size_t n) override;
    void Seek(std::uint64_t offset) override;
    /// True once every byte was read and hashed to `expected`.
    bool verified() const { return verified_; }

private:
    std::unique_ptr<BlobReader> inner_;
    std::string expected_, what_;
    Sha256 hash_;
    std::uint64_t position_ = 0;
    bool checking_ = true;
    bool verified_ = false;
};

/// Reads a whole blob into memory (what a parser needs), hashing while reading: one pass over
/// the bytes. Throws kNotFound (naming `what`) when there is no blob under `key`, kDataLoss when
/// its SHA-256 is not `expected` (CorruptBlobMessage), kInternal when it is shorter than its size.
std::string ReadVerified(const BlobStore& store, const std::string& key,
                         const std::string& expected, const std::string& what);

/// The directory backend ("dir:PATH").
class DirBlobStore final : public BlobStore {
public:
    /// Creates `dir`, dir/clouds and dir/results when missing. Throws kInvalidArgument.
    explicit DirBlobStore(std::string dir);
    std::string Describe() const override { return "dir:" + dir_; }
    /// fsync(path), rename to dir/key, fsync(dir/key's directory).
    void PutFile(const std::string& key, const std::string& path,
                 const std::string& sha256) override;
    /// A temp file beside dir/key, written, fsynced, renamed, directory fsynced.
    void PutBytes(const std::string& key, std::string_view bytes,
                  const std::string& sha256) override;
    std::unique_ptr<BlobReader> Open(const std::string& key) const override;
    std::optional<std::uint64_t> Size(const std::string& key) const override;
    bool Remove(const std::string& key) override;
    bool AdoptsFiles() const override { return true; }
    std::vector<std::pair<std::string, std::uint64_t>> List() const override;
    /// The file that holds `key`.
    std::string PathOf(const std::string& key) const { return dir_ + "/" + key; }

private:
    std::string dir_;
};

/// The large-object backend ("postgres") on the database at `url` (a libpq URI), whose schema
/// the store's migrations made (table `blobs`, migration 5). Connections are pooled; a reader
/// holds one connection and one read-only transaction until it is destroyed.
/// `chunk_bytes` is the size of each lo_write / lo_read (default 1 MiB).
std::unique_ptr<BlobStore> OpenLargeObjectBlobStore(const std::string& url,
                                                    std::size_t chunk_bytes = 1 << 20);

/// True for the errno values of a full disk or quota (ENOSPC, EDQUOT): such failures are
/// kResourceExhausted, not kInternal.
bool IsDiskFull(int err);

/// Writes all of `bytes` to `fd`, retrying short writes and EINTR. Returns 0, or the errno of
/// the write that failed (the file then holds the first *written bytes).
int WriteAll(int fd, std::string_view bytes, std::size_t* written = nullptr);

/// fsync of a file's data and metadata (kInternal naming the path on failure; kResourceExhausted
/// when the filesystem reports it full, as NFS may at fsync).
void SyncFile(const std::string& path);
/// fsync of a directory, so that a rename or a new entry in it survives a power failure.
void SyncDirectory(const std::string& dir);

}  // namespace surfel::worker
