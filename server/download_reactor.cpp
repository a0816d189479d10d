#include "download_reactor.h"

#include <string>

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
    DownloadReactor(SurfelService& service, const Caller& caller, const v1::DownloadRequest& request)
        : service_(service) {
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

grpc::ServerWriteReactor<v1::DataChunk>* NewDownloadReactor(SurfelService& service, const Caller& caller,
                                                            const v1::DownloadRequest& request) {
    return new DownloadReactor(service, caller, request);
}

}  // namespace surfel::server
