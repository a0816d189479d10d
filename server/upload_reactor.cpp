#include "upload_reactor.h"

#include <spdlog/spdlog.h>

#include <atomic>
#include <memory>

#include "surfel/base/error.h"
#include "surfel/worker/status.h"
#include "upload_session.h"

namespace surfel::server {
namespace {

using worker::CurrentExceptionStatus;

// ---- Upload reactor ---------------------------------------------------------------------------
//
// Threads. Reactions (OnReadDone, OnCancel) run on gRPC's threads and do only bounded work: one
// chunk of at most max_chunk_bytes appended and flushed. The slow steps run as one task on the
// service's ingest executor, while no read is outstanding:
//   - after the first message of a resumed upload, hashing the bytes already committed (up to
//     max_upload_bytes), then that message's chunk, then the next read is started from there;
//   - after the final message (finish_write), the session's Finish (parse, validate, store).
// So one thread at a time touches the state below; only `cancelled_` is shared (OnCancel may run
// at any time). The call ends with exactly one Finish, in Done, which is the last thing that
// touches `this`: OnDone deletes the reactor, possibly at once on another thread.
//
// Cancellation (the client went away, its deadline passed, or the server is shutting down): a
// pending read then fails and ends the call; a queued task sees `cancelled_` and ends it at once,
// keeping the committed bytes for a resume. Parsing has no cancel hook: a parse already running
// completes and stores the cloud (the client's next attempt then finds it by its hash).
class UploadReactor final : public grpc::ServerReadReactor<v1::UploadRequest> {
  public:
    UploadReactor(SurfelService& service, const Caller& caller, v1::Cloud* response)
        : service_(service), caller_(caller), response_(response) {
        StartRead(&request_);
    }

    void OnReadDone(bool ok) override {
        if (!ok) {  // the client closed (or broke) the stream without finish_write
            Done(grpc::Status(
                grpc::StatusCode::FAILED_PRECONDITION,
                "upload " + Id() + " incomplete: " + (session_ ? session_->ResumeHint() : "")));
            return;
        }
        try {
            if (!session_)
                session_ = std::make_unique<UploadSession>(service_.ops(), caller_, request_.upload_id(),
                                                           request_.filename());
            CheckChunk();
        } catch (...) {
            Done(CurrentExceptionStatus());
            return;
        }
        if (!session_->hashed()) {  // resuming: hash what is committed, off this thread, before
                                    // this chunk
            Offload(&UploadReactor::ResumeTask);
            return;
        }
        Accept(false);
    }

    void OnCancel() override { cancelled_.store(true); }

    void OnDone() override { delete this; }

  private:
    using Task = void (UploadReactor::*)();

    std::string Id() const { return session_ ? session_->id() : request_.upload_id(); }

    // Checks request_ against the upload's state (cheap: a refused resume is answered before
    // anything is hashed).
    void CheckChunk() {
        if (!request_.upload_id().empty() && request_.upload_id() != session_->id())
            throw Error(ErrorCode::kInvalidArgument, "upload_id: changed within one call");
        if (request_.write_offset() != static_cast<std::int64_t>(session_->committed()))
            throw Error(ErrorCode::kFailedPrecondition,
                        "write_offset " + std::to_string(request_.write_offset()) +
                            " does not match the committed size " +
                            std::to_string(session_->committed()) + " of upload " + session_->id() +
                            " (QueryUpload tells)");
        const std::size_t max_chunk = service_.limits().max_chunk_bytes;
        if (request_.data().size() > max_chunk)
            throw Error(ErrorCode::kInvalidArgument,
                        "data: a chunk holds at most " + std::to_string(max_chunk) + " bytes");
        session_->CheckFits(request_.data().size());
    }

    // Appends request_'s chunk (a bounded write: the page cache absorbs it), then reads the next
    // message or, after the final one, ingests.
    void Accept(bool on_executor) {
        try {
            session_->Append(request_.data());
        } catch (...) {
            Done(CurrentExceptionStatus());
            return;
        }
        if (!request_.finish_write())
            StartRead(&request_);
        else if (on_executor)
            IngestTask();
        else
            Offload(&UploadReactor::IngestTask);
    }

    // Hands the rest of the call to the ingest executor; a full queue ends the call, the
    // committed bytes kept.
    void Offload(Task task) {
        if (service_.ingest().TrySubmit([this, task] { (this->*task)(); })) return;
        Done(grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                          "upload " + Id() +
                              ": the server is busy ingesting other uploads, "
                              "try again; " +
                              session_->ResumeHint()));
    }

    // ---- tasks on the executor
    void ResumeTask() {
        if (cancelled_.load()) {
            Done(grpc::Status(grpc::StatusCode::CANCELLED,
                              "upload " + Id() + " cancelled; " + session_->ResumeHint()));
            return;
        }
        try {
            session_->HashCommitted();
        } catch (...) {
            Done(CurrentExceptionStatus());
            return;
        }
        Accept(true);
    }

    void IngestTask() {
        if (cancelled_.load()) {
            Done(grpc::Status(
                grpc::StatusCode::CANCELLED,
                "upload " + Id() + " cancelled before parsing; " + session_->ResumeHint()));
            return;
        }
        grpc::Status status;
        try {
            *response_ = session_->Finish();
        } catch (...) {
            status = CurrentExceptionStatus();
        }
        if (status.ok() && cancelled_.load())
            spdlog::info("upload {}: the caller went away; cloud {} is stored anyway", Id(),
                         response_->id());
        Done(status);
    }

    // Ends the call: once, and nothing may touch `this` after Finish.
    void Done(const grpc::Status& status) {
        const std::string id = Id();
        session_.reset();  // releases the claim
        if (!status.ok()) {
            const std::string& message = status.error_message();
            if (!id.empty() && message.find(id) != std::string::npos)
                spdlog::info("{}", message);
            else
                spdlog::info("upload {}: {}", id.empty() ? "?" : id, message);
        }
        Finish(status);
    }

    SurfelService& service_;
    Caller caller_;
    v1::Cloud* response_;
    v1::UploadRequest request_;
    std::atomic<bool> cancelled_{false};
    std::unique_ptr<UploadSession> session_;
};

}  // namespace

grpc::ServerReadReactor<v1::UploadRequest>* NewUploadReactor(SurfelService& service,
                                                             const Caller& caller,
                                                             v1::Cloud* response) {
    return new UploadReactor(service, caller, response);
}

}  // namespace surfel::server
