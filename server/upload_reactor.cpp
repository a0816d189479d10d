#include "upload_reactor.h"

#include <spdlog/spdlog.h>

#include <atomic>
#include <deque>
#include <exception>
#include <memory>
#include <mutex>
#include <optional>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/worker/status.h"
#include "upload_session.h"

namespace surfel::server {
namespace {

using worker::CurrentExceptionStatus;

// ---- Upload reactor ---------------------------------------------------------------------------
//
// Two stages (issue 19.3). The reader, OnReadDone on gRPC's threads, only queues each received
// message and starts the next read at once; the writer, a task on the service's transfer
// Executor, takes the queued messages in order and does the rest: checks the message against
// the upload's state, appends its chunk to the part file and hashes it (UploadSession::Append).
// So receiving the next chunk overlaps writing and hashing this one. The reader runs ahead by at
// most kAheadBytes (and kAheadMessages) of messages received and not yet appended; then it
// pauses, and the writer starts the next read when it has caught up. Every received chunk is
// counted in the upload bytes in flight (Operations::ReserveInflight, --max-upload-inflight-mb)
// when the reader takes it, before it is queued and before the next read: the reader's lead is in
// the total, and UploadSession::Append takes each chunk's count over. A chunk that would pass the
// limit is queued as refused and no more is read; the writer appends the chunks before it and
// then ends the call with RESOURCE_EXHAUSTED, the committed bytes kept, as a one-stage reactor
// refuses that chunk's Append. The chunks never appended are released when the call ends.
// Without a writer Executor (--transfer-threads 0) the writer runs inline in OnReadDone and
// nothing is read ahead: one chunk appended, then the next read, as before the two stages.
//
// The writer owns the UploadSession and is the only one to end the call: an error of the message
// it takes (a wrong write_offset, a limit, a full disk) ends the call, and the messages the reader
// took after it are dropped, never appended: the committed size is exactly what a one-stage
// reactor would have committed. A failed read (the client closed or broke the stream, the call
// was cancelled) is queued too, after the messages before it, so the writer appends those first
// and then ends the call with the resume hint of what is committed. The slow steps run as tasks
// on the service's ingest Executor, the writer's turn handed to them:
//   - after the first message of a resumed upload, hashing the bytes already committed (up to
//     max_upload_bytes), then that message's chunk; then the writer continues on its Executor;
//   - after the final message (finish_write), the session's Finish (parse, validate, store).
// `mu_` guards the queue and the flags between the reader and the writer (the hand-off that
// ThreadSanitizer sees). The call ends with exactly one Finish, in Done, which is the last thing
// that touches `this`: OnDone deletes the reactor, possibly at once on another thread. A read
// still outstanding then fails (OnReadDone(false), which sees `ended_` and does nothing).
//
// Cancellation (the client went away, its deadline passed, or the server is shutting down): a
// pending read then fails and ends the call; a queued task sees `cancelled_` and ends it at once,
// keeping the committed bytes for a resume. Parsing has no cancel hook: a parse already running
// completes and stores the cloud (the client's next attempt then finds it by its hash).
class UploadReactor final : public grpc::ServerReadReactor<v1::UploadRequest> {
  public:
    // What the reader runs ahead of the writer at most (bytes of received, unappended chunks;
    // messages): a bounded queue per upload, beside gRPC's own HTTP/2 window. The buffers of
    // appended messages kept for later reads hold at most kAheadBytes too (stale bytes, not in
    // flight).
    static constexpr std::size_t kAheadBytes = 2u << 20;
    static constexpr std::size_t kAheadMessages = 16;

    UploadReactor(SurfelService& service, const Caller& caller, v1::Cloud* response)
        : service_(service), caller_(caller), response_(response), writers_(service.transfers()) {
        StartRead(&request_);
    }

    void OnReadDone(bool ok) override {
        bool start_writer = false;
        {
            std::lock_guard lock(mu_);
            if (ended_) return;  // the writer ended the call; this read failed or came after
            const std::size_t bytes = ok ? request_.data().size() : 0;
            bool last = !ok || request_.finish_write();
            std::exception_ptr refused;
            if (bytes > 0) {
                if (reader_id_.empty()) reader_id_ = request_.upload_id();
                try {
                    service_.ops().ReserveInflight(bytes, reader_id_);
                    reserved_ += bytes;
                } catch (...) {  // past --max-upload-inflight-mb: the writer refuses it
                    refused = std::current_exception();
                    last = true;
                }
            }
            queue_.push_back(Received{ok, std::move(request_), refused});
            if (!spare_.empty()) {  // reuse a message's buffer (its capacity): no allocation per chunk
                request_ = std::move(spare_.back());
                spare_.pop_back();
                spare_capacity_ -= request_.data().capacity();
            }
            pending_bytes_ += bytes;
            ++pending_messages_;
            if (!last) {
                if (RoomLocked())
                    StartRead(&request_);
                else
                    paused_ = true;
            }
            start_writer = !writer_active_;
            writer_active_ = true;
        }
        if (start_writer) StartWriter();
    }

    void OnCancel() override { cancelled_.store(true); }

    void OnDone() override { delete this; }

  private:
    struct Received {
        bool ok = false;  // false: the read failed (the stream ended without finish_write)
        v1::UploadRequest request;
        std::exception_ptr refused;  // not counted in flight: ReserveInflight's error
    };
    using Task = void (UploadReactor::*)();

    // Under mu_: whether the reader may start another read now. Nothing is read ahead before the
    // session is open: a resumed upload's committed bytes are counted in flight first, as when
    // each chunk is appended before the next is read.
    bool RoomLocked() const {
        if (pending_messages_ == 0) return true;
        return writers_ != nullptr && opened_ && pending_bytes_ < kAheadBytes &&
               pending_messages_ < kAheadMessages;
    }

    // Under mu_: a paused reader reads again when there is room.
    void ResumeReaderLocked() {
        if (paused_ && RoomLocked()) {
            paused_ = false;
            StartRead(&request_);
        }
    }

    std::string Id() const { return session_ ? session_->id() : upload_id_; }

    // ---- the writer (it holds the turn while writer_active_)

    // Gives the writer's turn to the writer Executor (or runs it here without one).
    void StartWriter() {
        if (!writers_) {
            Write();
            return;
        }
        if (writers_->TrySubmit([this] { Write(); })) return;
        Done(grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                          "upload " + Id() + ": the server is busy writing other uploads, try again" +
                              (session_ ? "; " + session_->ResumeHint() : std::string())));
    }

    // Takes the queued messages in order until the queue is empty (the turn given back), the call
    // ended, or a task on the ingest Executor took the turn over.
    void Write() {
        for (;;) {
            Received m;
            {
                std::lock_guard lock(mu_);
                if (queue_.empty()) {
                    writer_active_ = false;
                    return;
                }
                m = std::move(queue_.front());
                queue_.pop_front();
            }
            if (!m.ok) {  // the client closed (or broke) the stream without finish_write
                Done(grpc::Status(
                    grpc::StatusCode::FAILED_PRECONDITION,
                    "upload " + Id() + " incomplete: " + (session_ ? session_->ResumeHint() : "")));
                return;
            }
            if (m.refused) {
                Refuse(m);
                return;
            }
            if (!Take(m.request)) return;
            Appended(std::move(m.request));
        }
    }

    // Checks one message and appends its chunk. False when the call ended or a task took the
    // writer's turn (the final message: ingest; the first of a resumed upload: its hash, and
    // then current_ holds the message, moved out of `request`).
    bool Take(v1::UploadRequest& request) {
        try {
            Open(request);
            CheckChunk(request);
        } catch (...) {
            Done(CurrentExceptionStatus());
            return false;
        }
        if (!session_->hashed()) {  // resuming: hash what is committed, off this thread, first
            current_.emplace(std::move(request));  // before the task can run
            Offload(&UploadReactor::ResumeTask);
            return false;
        }
        return Accept(request, false);
    }

    // Ends the call at a message the reader could not count in flight: with the error a one-stage
    // reactor gives that message (its checks first, then the in-flight limit at its Append).
    void Refuse(const Received& m) {
        try {
            Open(m.request);
            CheckChunk(m.request);
            std::rethrow_exception(m.refused);
        } catch (...) {
            Done(CurrentExceptionStatus());
        }
    }

    // Opens the session at the call's first message.
    void Open(const v1::UploadRequest& request) {
        if (session_) return;
        upload_id_ = request.upload_id();
        session_ = std::make_unique<UploadSession>(service_.ops(), caller_, request.upload_id(),
                                                   request.filename());
        std::lock_guard lock(mu_);
        opened_ = true;
        ResumeReaderLocked();
    }

    // Checks a message against the upload's state (cheap: a refused resume is answered before
    // anything is hashed).
    void CheckChunk(const v1::UploadRequest& request) {
        if (!request.upload_id().empty() && request.upload_id() != session_->id())
            throw Error(ErrorCode::kInvalidArgument, "upload_id: changed within one call");
        if (request.write_offset() != static_cast<std::int64_t>(session_->committed()))
            throw Error(ErrorCode::kFailedPrecondition,
                        "write_offset " + std::to_string(request.write_offset()) +
                            " does not match the committed size " +
                            std::to_string(session_->committed()) + " of upload " + session_->id() +
                            " (QueryUpload tells)");
        const std::size_t max_chunk = service_.limits().max_chunk_bytes;
        if (request.data().size() > max_chunk)
            throw Error(ErrorCode::kInvalidArgument,
                        "data: a chunk holds at most " + std::to_string(max_chunk) + " bytes");
        if (request.total_size() != 0) session_->ExpectSize(request.total_size());
        session_->CheckFits(request.data().size());
    }

    // Appends the message's chunk (a bounded write: the page cache absorbs it). After the final
    // message, ingests (here when on the ingest Executor already) and returns false.
    bool Accept(const v1::UploadRequest& request, bool on_executor) {
        {
            std::lock_guard lock(mu_);
            reserved_ -= request.data().size();  // Append takes the count over
        }
        try {
            session_->Append(request.data());
        } catch (...) {
            Done(CurrentExceptionStatus());
            return false;
        }
        if (!request.finish_write()) return true;
        if (on_executor)
            IngestTask();
        else
            Offload(&UploadReactor::IngestTask);
        return false;
    }

    // A message appended: it no longer counts against the reader's lead, and its buffer is
    // kept for a later read; a paused reader reads again.
    void Appended(v1::UploadRequest&& request) {
        std::lock_guard lock(mu_);
        pending_bytes_ -= request.data().size();
        --pending_messages_;
        const std::size_t capacity = request.data().capacity();
        if (spare_.size() < kAheadMessages && spare_capacity_ + capacity <= kAheadBytes) {
            spare_capacity_ += capacity;
            spare_.push_back(std::move(request));
        }
        ResumeReaderLocked();
    }

    // Hands the writer's turn to the ingest executor; a full queue ends the call, the committed
    // bytes kept.
    void Offload(Task task) {
        if (service_.ingest().TrySubmit([this, task] { (this->*task)(); })) return;
        Done(grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                          "upload " + Id() +
                              ": the server is busy ingesting other uploads, "
                              "try again; " +
                              session_->ResumeHint()));
    }

    // ---- tasks on the ingest executor
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
        v1::UploadRequest request = std::move(*current_);
        current_.reset();
        if (!Accept(request, true)) return;
        Appended(std::move(request));
        StartWriter();  // the rest of the queue back on the writer Executor
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

    // Ends the call: once, by the writer's turn, and nothing may touch `this` after Finish.
    void Done(const grpc::Status& status) {
        const std::string id = Id();
        std::uint64_t unappended = 0;
        {
            std::lock_guard lock(mu_);
            ended_ = true;
            queue_.clear();  // received after the end: never appended
            unappended = reserved_;
            reserved_ = 0;
        }
        service_.ops().ReleaseInflight(unappended);
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
    Executor* const writers_;  // null: the writer runs inline in OnReadDone
    std::atomic<bool> cancelled_{false};

    // The reader's: the message being read (while a read is outstanding, gRPC's).
    v1::UploadRequest request_;

    std::mutex mu_;  // guards what follows, between the reader and the writer
    std::deque<Received> queue_;
    std::vector<v1::UploadRequest> spare_;  // appended messages, their buffers kept for reads
    std::size_t spare_capacity_ = 0;         // of spare_'s chunks, at most kAheadBytes
    std::size_t pending_bytes_ = 0;          // chunks received and not yet appended
    std::uint64_t reserved_ = 0;             // of those, counted in flight and not yet appended
    std::string reader_id_;                  // the first message's upload_id (the reader's)
    std::size_t pending_messages_ = 0;
    bool paused_ = false;         // no read outstanding: the reader waits for the writer
    bool opened_ = false;         // the writer opened the session (it may be read ahead of)
    bool writer_active_ = false;  // the writer's turn is taken (a task queued or running)
    bool ended_ = false;          // Finish was called (or is about to be)

    // The writer's (whoever holds its turn).
    std::string upload_id_;
    std::unique_ptr<UploadSession> session_;
    std::optional<v1::UploadRequest> current_;  // the first chunk of a resume, while hashing
};

}  // namespace

grpc::ServerReadReactor<v1::UploadRequest>* NewUploadReactor(SurfelService& service,
                                                             const Caller& caller,
                                                             v1::Cloud* response) {
    return new UploadReactor(service, caller, response);
}

}  // namespace surfel::server
