#pragma once
/// \file
/// One upload, free of any transport: bytes appended to <data>/uploads/<id>.part and hashed while
/// written, then (Finish) deduplicated by SHA-256, parsed and validated, moved into the cloud
/// store and recorded. The gRPC Upload reactor and the HTTP POST /v1/clouds handler both drive
/// one of these; neither knows how a cloud is stored.
///
/// Speed (issue 19.3, docs/service.md "Upload path"): the bytes are written with write(2) and
/// hashed as they arrive; when the blob store adopts the part file (the directory backend
/// renames it into place), writeback to disk is started every few MiB while the upload goes on
/// (sync_file_range), so that the fsync before the acknowledgement finds little left to do, and
/// Finish parses the file from a read-only mapping (no copy) while another thread fsyncs it.
/// The positions of a PLY (binary, or ascii with the vertices first) are checked while the chunks
/// are appended (PlyPositionScan, on the bytes just hashed): Finish then reads only the header and
/// what follows the vertex records.

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "operations.h"
#include "surfel/io/ply.h"
#include "surfel/worker/sha256.h"

namespace surfel::server {

/// Throws Error(kInvalidArgument) unless `id` matches [A-Za-z0-9_-]{1,128} (upload ids name files).
void CheckUploadId(const std::string& id);

/// Not thread-safe: one thread at a time (the caller hands it between threads).
class UploadSession {
  public:
    /// Checks and claims `upload_id` (kFailedPrecondition while another call holds it) and opens
    /// its part file for appending; bytes committed by an earlier call are kept (a resume).
    /// `filename` (its extension picks the parser for non-PLY content) defaults to the id.
    /// Upload ids are the caller's own (Operations::ScopedUploadId names the part file).
    UploadSession(Operations& ops, const Caller& caller, std::string upload_id,
                  const std::string& filename);
    /// Releases the claim. The part file stays for a resume unless Finish or Discard removed it.
    ~UploadSession();
    UploadSession(const UploadSession&) = delete;
    UploadSession& operator=(const UploadSession&) = delete;

    const std::string& id() const { return id_; }
    /// Bytes in the part file.
    std::uint64_t committed() const { return committed_; }
    /// False while the bytes of a resumed upload are not hashed yet (HashCommitted does it).
    bool hashed() const { return hashed_; }
    /// A hint for a client whose call broke off: where to resume.
    std::string ResumeHint() const;

    /// Throws kResourceExhausted, and discards the part file, when `more` bytes would take the
    /// upload past limits().max_upload_bytes.
    void CheckFits(std::uint64_t more);
    /// The client's word for the upload's whole size (UploadRequest.total_size, HTTP's
    /// Content-Length), before its first Append: refuses at once what could never be stored, and
    /// reserves the disk space of the bytes still to come, so that no blob is evicted for an
    /// upload refused later. kInvalidArgument: below the committed bytes, or another size than a
    /// call gave before. kResourceExhausted, the part file discarded (as Append's refusals): past
    /// limits().max_upload_bytes (CheckFits), past the whole in-flight cap, or past the disk
    /// quota when eviction cannot make room (nothing evicted then).
    void ExpectSize(std::uint64_t total);
    /// Reads and hashes the committed bytes of a resumed upload (slow: up to max_upload_bytes).
    void HashCommitted();
    /// Appends `data` to the part file (after CheckFits). Needs hashed(). The transport counted
    /// `data` in the in-flight total (Operations::ReserveInflight, kResourceExhausted past
    /// limits().max_upload_inflight_bytes) before it held the bytes in memory; the session takes
    /// that count over on entry, whatever happens, and releases it with the part file's when it
    /// goes (stored, or the call ended). kResourceExhausted:
    /// - past the disk quota when eviction cannot make room (Retention::Reserve), or the disk is
    ///   full (ENOSPC, EDQUOT): the part file is removed, freeing its space (upload again).
    /// A chunk is never half in the part file: a short write is truncated away.
    void Append(std::string_view data);
    /// Appends one chunk given in pieces (a gRPC message's slices), as Append of their
    /// concatenation: one writev, the same checks, never half in the part file.
    void Append(const std::vector<std::string_view>& pieces);
    /// The whole file is here: a cloud the caller stored before is returned at once
    /// (deduplicated); one only other tenants stored is parsed as if new (the same answer and
    /// about the same time as a new file; the bytes are kept once on disk); otherwise
    /// the bytes are parsed (kInvalidArgument naming line/element/field, kResourceExhausted over
    /// max_points), moved to the content-addressed store and recorded. Slow: run it off a
    /// transport's threads. The part file is gone afterwards, whatever the outcome.
    v1::Cloud Finish();
    /// Removes the part file.
    void Discard();

  private:
    Operations& ops_;
    Caller caller_;
    std::string id_, filename_, path_;
    bool claimed_ = false;
    bool hashed_ = false;  // hash_ covers the committed bytes
    bool adopt_ = false;   // the blob store renames the part file into place (early writeback pays)
    std::uint64_t committed_ = 0;
    std::uint64_t writeback_from_ = 0;  // bytes before this offset have had writeback started
    std::uint64_t inflight_ = 0;        // bytes this session counts in Operations' in-flight total
    std::uint64_t total_ = 0;           // ExpectSize's: the upload's whole size, 0 = not given
    std::uint64_t prereserved_ = 0;     // disk space reserved by ExpectSize for bytes not yet written
    int fd_ = -1;                       // the part file, open for appending
    worker::Sha256 hash_;
    // The upload check's positions folded in as the chunks are appended (a fresh upload only:
    // a resumed one's earlier bytes were not seen; Finish then reads them all, as before).
    std::unique_ptr<PlyPositionScan> scan_;

    void CloseFile();
    PlyReadOptions ReadLimits() const;  // the upload check's
};

}  // namespace surfel::server
