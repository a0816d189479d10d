#include "download_reactor.h"

#include <optional>

#include "chunk_reader.h"
#include "surfel/worker/status.h"

namespace surfel::server {
namespace {

using worker::CurrentExceptionStatus;

// ---- Download reactor -------------------------------------------------------------------------
//
// One write in flight at a time; each reaction reads the next chunk (download_chunk_bytes, a
// bounded read, never the whole result) and starts its write, or finishes after the last.
class DownloadReactor final : public grpc::ServerWriteReactor<v1::DataChunk> {
public:
    DownloadReactor(SurfelService& service, const v1::DownloadRequest& request) : service_(service) {
        std::optional<v1::Job> job;
        try {
            job = service_.jobs().Get(request.job_id());
        } catch (...) {
            Finish(CurrentExceptionStatus());
            return;
        }
        if (!job) {
            Finish(grpc::Status(grpc::StatusCode::NOT_FOUND, "job " + request.job_id() + " not found"));
            return;
        }
        if (job->state() != v1::SUCCEEDED) {
            Finish(grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                                "job " + request.job_id() + " is " + v1::JobState_Name(job->state()) +
                                    "; results exist only for SUCCEEDED jobs"));
            return;
        }
        if (!reader_.Open(service_.store().ResultPath(job->id()))) {
            Finish(grpc::Status(grpc::StatusCode::NOT_FOUND, "result of job " + job->id() + " is gone"));
            return;
        }
        Next();
    }

    void OnWriteDone(bool ok) override {
        if (!ok) {
            Finish(grpc::Status(grpc::StatusCode::CANCELLED, "download stream broken"));
            return;
        }
        Next();
    }

    void OnDone() override { delete this; }

private:
    void Next() {
        bool more = false;
        try {
            more = reader_.Next(&chunk_, service_.limits().download_chunk_bytes);
        } catch (...) {
            Finish(CurrentExceptionStatus());
            return;
        }
        if (!more) {
            Finish(grpc::Status::OK);
            return;
        }
        service_.metrics().AddBytesOut(chunk_.data().size());
        StartWrite(&chunk_);
    }

    SurfelService& service_;
    ChunkReader reader_;
    v1::DataChunk chunk_;
};

}  // namespace

grpc::ServerWriteReactor<v1::DataChunk>* NewDownloadReactor(SurfelService& service,
                                                            const v1::DownloadRequest& request) {
    return new DownloadReactor(service, request);
}

}  // namespace surfel::server
