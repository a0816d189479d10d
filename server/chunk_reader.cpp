#include "chunk_reader.h"

#include <algorithm>
#include <utility>

#include "surfel/base/error.h"

namespace surfel::server {

bool ChunkReader::Open(const worker::BlobStore& blobs, const v1::Job& job) {
    return Open(blobs, job.id(), job.result());
}

bool ChunkReader::Open(const worker::BlobStore& blobs, const std::string& job_id,
                       const v1::JobResult& result) {
    what_ = "result of job " + job_id;
    std::unique_ptr<worker::BlobReader> raw = blobs.Open(worker::ResultBlobKey(job_id));
    if (!raw) return false;
    total_ = static_cast<std::int64_t>(raw->size());
    in_ = std::make_unique<worker::VerifyingReader>(std::move(raw), result.sha256(), what_);
    return true;
}

bool ChunkReader::Next(v1::DataChunk* chunk, std::size_t size) {
    if (sent_any_ && offset_ >= total_) return false;
    // Read straight into the message's bytes: a chunk reused for every write (DownloadReactor)
    // keeps its buffer, so no allocation and no zero fill per chunk, and nothing is copied again.
    std::string& data = *chunk->mutable_data();
    data.resize(static_cast<std::size_t>(std::min<std::int64_t>(static_cast<std::int64_t>(size), total_ - offset_)));
    std::size_t at = 0;
    while (at < data.size()) {
        const std::size_t got = in_->Read(data.data() + at, data.size() - at);
        if (got == 0)
            throw Error(ErrorCode::kInternal, "reading the " + what_ + ": short read at offset " +
                                                  std::to_string(offset_ + static_cast<std::int64_t>(at)) +
                                                  " of " + std::to_string(total_) + " bytes");
        at += got;
    }
    if (total_ == 0) {
        char probe;
        in_->Read(&probe, 1);  // an empty blob: the check runs at its end
    }
    chunk->set_offset(offset_);
    chunk->set_total_size(total_);
    offset_ += static_cast<std::int64_t>(data.size());
    sent_any_ = true;
    return true;
}

}  // namespace surfel::server
