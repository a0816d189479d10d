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
class UploadReactor final : public grpc::ServerReadReactor<grpc::ByteBuffer> {
  public:
    // What the reader runs ahead of the writer at most (bytes of received, unappended chunks;
    // messages): a bounded queue per upload, beside gRPC's own HTTP/2 window. The chunks stay in
    // gRPC's receive slices (ParseUploadMessage), written and hashed from there.
    static constexpr std::size_t kAheadBytes = 2u << 20;
    static constexpr std::size_t kAheadMessages = 16;

    UploadReactor(SurfelService& service, const Caller& caller, grpc::ByteBuffer* response)
        : service_(service), caller_(caller), response_(response), writers_(service.transfers()) {
        StartRead(&request_);
    }

    void OnReadDone(bool ok) override {
        bool start_writer = false;
        {
            std::lock_guard lock(mu_);
            if (ended_) return;  // the writer ended the call; this read failed or came after
            Message m;
            // A message that is not an UploadRequest is a failed read, as gRPC's own parse makes
            // it.
            if (ok) ok = ParseUploadMessage(request_, &m.fields, &m.data, &m.size);
            request_.Clear();  // the chunk's slices are m's now
            const std::size_t bytes = ok ? m.size : 0;
            bool last = !ok || m.fields.finish_write();
            std::exception_ptr refused;
            if (bytes > 0) {
                if (reader_id_.empty()) reader_id_ = m.fields.upload_id();
                try {
                    service_.ops().ReserveInflight(bytes, reader_id_);
                    reserved_ += bytes;
                } catch (...) {  // past --max-upload-inflight-mb: the writer refuses it
                    refused = std::current_exception();
                    last = true;
                }
            }
            queue_.push_back(Received{ok, std::move(m), refused});
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
    // One UploadRequest: its fields but `data`, and the chunk in gRPC's slices.
    struct Message {
        v1::UploadRequest fields;
        std::vector<grpc::Slice> data;
        std::size_t size = 0;
    };
    struct Received {
        bool ok = false;  // false: the read failed (the stream ended without finish_write)
        Message request;
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
    bool Take(Message& request) {
        try {
            Open(request.fields);
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
            Open(m.request.fields);
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
    void CheckChunk(const Message& message) {
        const v1::UploadRequest& request = message.fields;
        if (!request.upload_id().empty() && request.upload_id() != session_->id())
            throw Error(ErrorCode::kInvalidArgument, "upload_id: changed within one call");
        if (request.write_offset() != static_cast<std::int64_t>(session_->committed()))
            throw Error(ErrorCode::kFailedPrecondition,
                        "write_offset " + std::to_string(request.write_offset()) +
                            " does not match the committed size " +
                            std::to_string(session_->committed()) + " of upload " + session_->id() +
                            " (QueryUpload tells)");
        const std::size_t max_chunk = service_.limits().max_chunk_bytes;
        if (message.size > max_chunk)
            throw Error(ErrorCode::kInvalidArgument,
                        "data: a chunk holds at most " + std::to_string(max_chunk) + " bytes");
        if (request.total_size() != 0) session_->ExpectSize(request.total_size());
        session_->CheckFits(message.size);
    }

    // Appends the message's chunk (a bounded write: the page cache absorbs it). After the final
    // message, ingests (here when on the ingest Executor already) and returns false.
    bool Accept(const Message& request, bool on_executor) {
        {
            std::lock_guard lock(mu_);
            reserved_ -= request.size;  // Append takes the count over
        }
        try {
            std::vector<std::string_view> pieces;
            pieces.reserve(request.data.size());
            for (const grpc::Slice& s : request.data)
                pieces.emplace_back(reinterpret_cast<const char*>(s.begin()), s.size());
            session_->Append(pieces);
        } catch (...) {
            Done(CurrentExceptionStatus());
            return false;
        }
        if (!request.fields.finish_write()) return true;
        if (on_executor)
            IngestTask();
        else
            Offload(&UploadReactor::IngestTask);
        return false;
    }

    // A message appended: it no longer counts against the reader's lead (its slices go back to
    // gRPC); a paused reader reads again.
    void Appended(Message&& request) {
        const Message done = std::move(request);
        std::lock_guard lock(mu_);
        pending_bytes_ -= done.size;
        --pending_messages_;
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
        Message request = std::move(*current_);
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
        v1::Cloud cloud;
        try {
            cloud = session_->Finish();
            bool own = false;
            status = grpc::SerializationTraits<v1::Cloud>::Serialize(cloud, response_, &own);
        } catch (...) {
            status = CurrentExceptionStatus();
        }
        if (status.ok() && cancelled_.load())
            spdlog::info("upload {}: the caller went away; cloud {} is stored anyway", Id(),
                         cloud.id());
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
    grpc::ByteBuffer* response_;  // the Cloud, serialized
    Executor* const writers_;  // null: the writer runs inline in OnReadDone
    std::atomic<bool> cancelled_{false};

    // The reader's: the message being read (while a read is outstanding, gRPC's).
    grpc::ByteBuffer request_;

    std::mutex mu_;  // guards what follows, between the reader and the writer
    std::deque<Received> queue_;
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
    std::optional<Message> current_;  // the first chunk of a resume, while hashing
};

}  // namespace

// ---- Reading an UploadRequest without copying its chunk --------------------------------------

namespace {

// A cursor over a message's slices (protobuf's wire format: varints, fixed and length-delimited
// values, any of them split between slices).
class WireCursor {
  public:
    explicit WireCursor(const std::vector<grpc::Slice>& slices) : slices_(slices) { Skip(); }
    bool done() const { return slice_ == slices_.size(); }
    std::size_t left() const { return left_; }
    void set_left(std::size_t n) { left_ = n; }

    bool Byte(std::uint8_t* b) {
        if (done()) return false;
        *b = slices_[slice_].begin()[at_++];
        --left_;
        Skip();
        return true;
    }
    // A varint of at most 10 bytes, its bytes appended to `raw` when given.
    bool Varint(std::uint64_t* v, std::string* raw = nullptr) {
        *v = 0;
        for (int shift = 0; shift < 70; shift += 7) {
            std::uint8_t b;
            if (!Byte(&b)) return false;
            if (raw) raw->push_back(static_cast<char>(b));
            *v |= static_cast<std::uint64_t>(b & 0x7f) << shift;
            if (!(b & 0x80)) return true;
        }
        return false;
    }
    // The next n bytes: appended to `raw` (copy) or as sub-slices to `out` (no copy).
    bool Take(std::size_t n, std::string* raw, std::vector<grpc::Slice>* out) {
        if (n > left_) return false;
        while (n > 0) {
            const grpc::Slice& s = slices_[slice_];
            const std::size_t k = std::min(n, s.size() - at_);
            if (raw) raw->append(reinterpret_cast<const char*>(s.begin()) + at_, k);
            if (out) out->push_back(s.sub(at_, at_ + k));
            at_ += k;
            left_ -= k;
            n -= k;
            Skip();
        }
        return true;
    }

  private:
    void Skip() {  // past the end of this slice (and empty ones)
        while (slice_ < slices_.size() && at_ == slices_[slice_].size()) {
            ++slice_;
            at_ = 0;
        }
    }
    const std::vector<grpc::Slice>& slices_;
    std::size_t slice_ = 0, at_ = 0;
    std::size_t left_ = 0;
};

// The whole message parsed by protobuf, its chunk copied into one slice.
bool ParseWhole(const std::vector<grpc::Slice>& slices, v1::UploadRequest* fields,
                std::vector<grpc::Slice>* data, std::size_t* data_size) {
    std::string bytes;
    for (const grpc::Slice& s : slices)
        bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
    if (!fields->ParseFromString(bytes)) return false;
    data->clear();
    *data_size = fields->data().size();
    if (*data_size > 0) data->emplace_back(fields->data());
    fields->clear_data();
    return true;
}

}  // namespace

bool ParseUploadMessage(const grpc::ByteBuffer& message, v1::UploadRequest* fields,
                        std::vector<grpc::Slice>* data, std::size_t* data_size) {
    constexpr std::uint64_t kDataField = 4;  // UploadRequest.data
    std::vector<grpc::Slice> slices;
    if (message.Valid() && !message.Dump(&slices).ok()) return false;
    data->clear();
    *data_size = 0;
    WireCursor in(slices);
    in.set_left(message.Valid() ? message.Length() : 0);
    std::string rest;  // every field but data, as it came
    bool seen_data = false;
    while (!in.done()) {
        std::uint64_t tag;
        std::string tag_bytes;
        if (!in.Varint(&tag, &tag_bytes)) return false;
        const std::uint64_t field = tag >> 3;
        const int wire_type = static_cast<int>(tag & 7);
        if (field == kDataField && wire_type == 2) {
            std::uint64_t n;
            if (seen_data || !in.Varint(&n) || n > in.left())
                return ParseWhole(slices, fields, data, data_size);
            if (!in.Take(static_cast<std::size_t>(n), nullptr, data)) return false;
            *data_size = static_cast<std::size_t>(n);
            seen_data = true;
            continue;
        }
        rest += tag_bytes;
        std::uint64_t v;
        switch (wire_type) {
            case 0:
                if (!in.Varint(&v, &rest)) return false;
                break;
            case 1:
                if (!in.Take(8, &rest, nullptr)) return false;
                break;
            case 2:
                if (!in.Varint(&v, &rest) || v > in.left() ||
                    !in.Take(static_cast<std::size_t>(v), &rest, nullptr))
                    return false;
                break;
            case 5:
                if (!in.Take(4, &rest, nullptr)) return false;
                break;
            default:  // groups (3, 4), or not a wire type: protobuf decides
                return ParseWhole(slices, fields, data, data_size);
        }
    }
    return fields->ParseFromString(rest);
}

grpc::ServerReadReactor<grpc::ByteBuffer>* NewUploadReactor(SurfelService& service,
                                                            const Caller& caller,
                                                            grpc::ByteBuffer* response) {
    return new UploadReactor(service, caller, response);
}

}  // namespace surfel::server
