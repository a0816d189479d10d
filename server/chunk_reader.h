#pragma once
/// \file
/// A job's result blob sent as DataChunks, by Watch (include_result) and Download, checked
/// against the SHA-256 recorded for it.

#include <cstdint>
#include <memory>
#include <string>

#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/blob_store.h"

namespace surfel::server {

/// Reads a blob one chunk at a time, so that a reaction reads at most one chunk (a bounded read,
/// never the whole result), hashing what it sends: the last chunk is held back and
/// Error(kDataLoss) thrown instead when the bytes do not hash to the recorded SHA-256.
class ChunkReader {
public:
    /// Opens the result of `job` (its blob ResultBlobKey(job.id()), checked against
    /// job.result().sha256(); results recorded before checks existed are not checked).
    /// False when the blob is gone.
    bool Open(const worker::BlobStore& blobs, const v1::Job& job);
    /// Same, from a `finished` event's result.
    bool Open(const worker::BlobStore& blobs, const std::string& job_id,
              const v1::JobResult& result);
    /// Fills the next chunk of at most `size` bytes (offset, total_size, data); false after the
    /// last. An empty blob is one empty chunk. Throws Error(kInternal) when the blob got
    /// shorter, Error(kDataLoss) when it does not match its SHA-256.
    bool Next(v1::DataChunk* chunk, std::size_t size);

private:
    std::string what_;
    std::unique_ptr<worker::BlobReader> in_;
    std::int64_t total_ = 0, offset_ = 0;
    bool sent_any_ = false;
};

}  // namespace surfel::server
