#include "download_reactor.h"

#include <mutex>
#include <string>
#include <utility>

#include "chunk_reader.h"
#include "surfel/worker/status.h"

namespace surfel::server {
namespace {

using worker::CurrentExceptionStatus;

// ---- Download reactor -------------------------------------------------------------------------
//
// One write in flight at a time, and beside it the next chunk read and hashed (ChunkReader: a
// bounded read of download_chunk_bytes, never the whole result) by a task on the service's
// transfer Executor (on this thread without one), so that reading and hashing chunk k+1 overlap
// sending chunk k (issue 19.3). Whichever of the two ends second (OnWriteDone, the read task)
// takes the turn: it starts the next write and the next read, or finishes the call after the
// last chunk, on an error (the read's: a vanished blob, DATA_LOSS, which holds the last chunk
// back) or when the stream broke. `mu_` guards the flags between them; the call ends with exactly
// one Finish, the last thing that touches `this` (OnDone deletes the reactor).
class DownloadReactor final : public grpc::ServerWriteReactor<v1::DataChunk> {
public:
    DownloadReactor(SurfelService& service, const Caller& caller, const v1::DownloadRequest& request)
        : service_(service), readers_(service.transfers()) {
        bool open = false;
        try {
            const ResultFile r = service_.ops().Result(caller, request.job_id());
            open = reader_.Open(service_.store().blobs(), r.job);
        } catch (...) {
            Finish(CurrentExceptionStatus());
            return;
        }
        if (!open) {
            Finish(grpc::Status(grpc::StatusCode::NOT_FOUND, "result of job " + request.job_id() + " is gone"));
            return;
        }
        reading_ = true;
        Read();  // the first chunk, here; then its write and the second read
    }

    void OnWriteDone(bool ok) override {
        {
            std::lock_guard lock(mu_);
            writing_ = false;
            if (!ok) broken_ = true;
            if (reading_) return;  // the read task takes the turn when it ends
        }
        Advance();
    }

    void OnDone() override { delete this; }

private:
    enum class Got { kChunk, kEnd, kError };

    // Reads (and hashes) the next chunk into next_; then takes the turn unless a write is still
    // in flight.
    void Read() {
        Got got = Got::kEnd;
        grpc::Status error;
        try {
            got = reader_.Next(&next_, service_.limits().download_chunk_bytes) ? Got::kChunk : Got::kEnd;
        } catch (...) {
            got = Got::kError;
            error = CurrentExceptionStatus();
        }
        {
            std::lock_guard lock(mu_);
            reading_ = false;
            got_ = got;
            if (got == Got::kError) error_ = std::move(error);
            if (writing_) return;  // OnWriteDone takes the turn
        }
        Advance();
    }

    // Both the last write and the last read are done: the next write and read, or the end.
    void Advance() {
        if (broken_) {
            Finish(grpc::Status(grpc::StatusCode::CANCELLED, "download stream broken"));
            return;
        }
        if (got_ == Got::kError) {
            Finish(error_);
            return;
        }
        if (got_ == Got::kEnd) {
            Finish(grpc::Status::OK);
            return;
        }
        chunk_.Swap(&next_);
        {
            std::lock_guard lock(mu_);
            writing_ = reading_ = true;
        }
        service_.metrics().AddBytesOut(chunk_.data().size());
        // The read task first: gRPC sends the chunk on the thread that starts its write (this
        // one), so a read queued after StartWrite would wait for the send.
        const bool queued = readers_ && readers_->TrySubmit([this] { Read(); });
        StartWrite(&chunk_);
        if (!queued) Read();
    }

    SurfelService& service_;
    Executor* const readers_;  // null: the next chunk is read on this thread
    ChunkReader reader_;
    v1::DataChunk chunk_;  // being written
    v1::DataChunk next_;   // being read, then waiting for the write before it to end

    std::mutex mu_;  // guards the flags between the write's reaction and the read task
    bool writing_ = false, reading_ = false, broken_ = false;
    Got got_ = Got::kEnd;
    grpc::Status error_;
};

}  // namespace

grpc::ServerWriteReactor<v1::DataChunk>* NewDownloadReactor(SurfelService& service, const Caller& caller,
                                                            const v1::DownloadRequest& request) {
    return new DownloadReactor(service, caller, request);
}

}  // namespace surfel::server
