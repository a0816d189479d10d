#include "upload_reactor.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <filesystem>
#include <fstream>

#include "surfel/base/error.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/file_bytes.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/sha256.h"
#include "surfel/worker/status.h"

namespace surfel::server {
namespace fs = std::filesystem;
using worker::CurrentExceptionStatus;

void CheckUploadId(const std::string& id) {
    const bool ok = !id.empty() && id.size() <= 128 && std::all_of(id.begin(), id.end(), [](char c) {
        return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-';
    });
    if (!ok) throw Error(ErrorCode::kInvalidArgument, "upload_id: must match [A-Za-z0-9_-]{1,128}");
}

namespace {

// ---- Upload reactor ---------------------------------------------------------------------------
//
// Threads. Reactions (OnReadDone, OnCancel) run on gRPC's threads and do only bounded work: one
// chunk of at most max_chunk_bytes appended and flushed, a stat of the part file. The slow steps
// run as one task on the service's ingest executor, while no read is outstanding:
//   - after the first message of a resumed upload, hashing the bytes already committed (up to
//     max_upload_bytes), then that message's chunk, then the next read is started from there;
//   - after the final message (finish_write), reading, parsing and validating the file, renaming
//     it into the cloud store and building the Cloud.
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
    UploadReactor(SurfelService& service, v1::Cloud* response) : service_(service), response_(response) {
        StartRead(&request_);
    }

    void OnReadDone(bool ok) override {
        if (!ok) {  // the client closed (or broke) the stream without finish_write
            Done(grpc::Status(grpc::StatusCode::FAILED_PRECONDITION, "upload " + id_ + " incomplete: " + ResumeHint()));
            return;
        }
        try {
            if (!started_) Begin();
            CheckChunk();
        } catch (...) {
            Done(CurrentExceptionStatus());
            return;
        }
        if (!hashed_) {  // resuming: hash what is committed, off this thread, before this chunk
            Offload(&UploadReactor::ResumeTask);
            return;
        }
        Accept(false);
    }

    void OnCancel() override { cancelled_.store(true); }

    void OnDone() override { delete this; }

private:
    using Task = void (UploadReactor::*)();

    std::string ResumeHint() const {
        return std::to_string(committed_) + " bytes committed; resume at write_offset " + std::to_string(committed_) +
               " and end with finish_write";
    }

    // First message: claims the id, opens the part file for appending, finds its size.
    void Begin() {
        id_ = request_.upload_id();
        CheckUploadId(id_);
        if (!service_.ClaimUpload(id_))
            throw Error(ErrorCode::kFailedPrecondition, "upload " + id_ + " is in progress on another call");
        claimed_ = true;
        filename_ = request_.filename().empty() ? id_ : fs::path(request_.filename()).filename().string();
        path_ = service_.store().UploadPath(id_);
        std::error_code ec;
        committed_ = fs::exists(path_, ec) ? fs::file_size(path_, ec) : 0;
        hashed_ = committed_ == 0;
        out_.open(path_, std::ios::binary | std::ios::app);
        if (!out_) throw Error(ErrorCode::kInternal, "cannot open " + path_);
        started_ = true;
    }

    // Appends request_'s chunk (checked), then reads the next message or, after the final one,
    // ingests.
    void Accept(bool on_executor) {
        try {
            AppendChunk();
        } catch (...) {
            Done(CurrentExceptionStatus());
            return;
        }
        if (!request_.finish_write()) StartRead(&request_);
        else if (on_executor) IngestTask();
        else Offload(&UploadReactor::IngestTask);
    }

    // Hands the rest of the call to the ingest executor; a full queue ends the call, the
    // committed bytes kept.
    void Offload(Task task) {
        if (service_.ingest().TrySubmit([this, task] { (this->*task)(); })) return;
        Done(grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                          "upload " + id_ + ": the server is busy ingesting other uploads, try again; " + ResumeHint()));
    }

    // ---- tasks on the executor
    void ResumeTask() {
        if (cancelled_.load()) {
            Done(grpc::Status(grpc::StatusCode::CANCELLED, "upload " + id_ + " cancelled; " + ResumeHint()));
            return;
        }
        try {
            HashCommitted();
        } catch (...) {
            Done(CurrentExceptionStatus());
            return;
        }
        Accept(true);
    }

    void IngestTask() {
        if (cancelled_.load()) {
            Done(grpc::Status(grpc::StatusCode::CANCELLED, "upload " + id_ + " cancelled before parsing; " + ResumeHint()));
            return;
        }
        grpc::Status status;
        try {
            Ingest();
        } catch (...) {
            status = CurrentExceptionStatus();
        }
        if (status.ok() && cancelled_.load())
            spdlog::info("upload {}: the caller went away; cloud {} is stored anyway", id_, response_->id());
        Done(status);
    }

    // ---- steps
    void HashCommitted() {
        std::ifstream in(path_, std::ios::binary);
        if (!in) throw Error(ErrorCode::kInternal, "cannot read " + path_);
        std::string buf(1 << 20, '\0');
        std::uint64_t hashed = 0;
        while (in) {
            in.read(buf.data(), static_cast<std::streamsize>(buf.size()));
            const auto n = static_cast<std::size_t>(in.gcount());
            hash_.Update(std::string_view(buf.data(), n));
            hashed += n;
        }
        if (hashed != committed_)
            throw Error(ErrorCode::kInternal, "reading " + path_ + ": " + std::to_string(hashed) + " of " +
                                                  std::to_string(committed_) + " bytes");
        hashed_ = true;
    }

    // Checks request_ against the upload's state (cheap: a refused resume is answered before
    // anything is hashed).
    void CheckChunk() {
        if (!request_.upload_id().empty() && request_.upload_id() != id_)
            throw Error(ErrorCode::kInvalidArgument, "upload_id: changed within one call");
        if (request_.write_offset() != static_cast<std::int64_t>(committed_))
            throw Error(ErrorCode::kFailedPrecondition,
                        "write_offset " + std::to_string(request_.write_offset()) + " does not match the committed size " +
                            std::to_string(committed_) + " of upload " + id_ + " (QueryUpload tells)");
        const std::string& data = request_.data();
        if (data.size() > service_.limits().max_chunk_bytes)
            throw Error(ErrorCode::kInvalidArgument, "data: a chunk holds at most " +
                                                         std::to_string(service_.limits().max_chunk_bytes) + " bytes");
        if (committed_ + data.size() > service_.limits().max_upload_bytes) {
            Discard();
            throw Error(ErrorCode::kResourceExhausted, "upload " + id_ + " exceeds the limit of " +
                                                           std::to_string(service_.limits().max_upload_bytes) + " bytes");
        }
    }

    // Appends request_'s chunk. Chunks are at most max_chunk_bytes, so the write stays in the
    // reaction (the page cache absorbs it); the flush keeps committed_ equal to the file's size,
    // which QueryUpload reports.
    void AppendChunk() {
        const std::string& data = request_.data();
        out_.write(data.data(), static_cast<std::streamsize>(data.size()));
        out_.flush();
        if (!out_) throw Error(ErrorCode::kInternal, "writing " + path_ + " failed");
        hash_.Update(data);
        committed_ += data.size();
        service_.metrics().AddBytesIn(data.size());
    }

    // The whole file is here: a cloud stored before is answered at once; otherwise the bytes are
    // parsed (which validates them), moved to the content-addressed store and recorded.
    void Ingest() {
        out_.close();
        const std::string id = hash_.FinishHex();
        if (auto existing = service_.store().FindCloud(id)) {
            const std::uint64_t size = committed_;
            Discard();
            *response_ = *existing;
            response_->set_deduplicated(true);
            spdlog::info("upload {}: {} bytes, already stored as cloud {}", id_, size, id);
            service_.metrics().CountUpload(true);
            return;
        }
        std::string bytes;
        PointCloud cloud;
        try {
            bytes = ReadFileBytes(path_);
            PlyReadOptions limits;
            limits.max_points = service_.limits().max_points;
            cloud = ParsePointCloud(bytes, filename_, limits);
            if (cloud.empty()) throw Error(ErrorCode::kInvalidArgument, filename_ + ": the cloud has no points");
        } catch (...) {
            Discard();
            service_.metrics().CountUpload(false);
            throw;
        }
        std::error_code ec;
        fs::rename(path_, service_.store().CloudPath(id), ec);
        if (ec) throw Error(ErrorCode::kInternal, "storing cloud " + id + ": " + ec.message());
        v1::Cloud c;
        c.set_id(id);
        c.set_points(cloud.size());
        const BoundingBox box = cloud.Bounds();
        *c.mutable_bounds_min() = worker::ToProto(box.min.cast<double>());
        *c.mutable_bounds_max() = worker::ToProto(box.max.cast<double>());
        for (const std::string& a : cloud.AttributeNames()) c.add_attributes(a);
        c.set_size_bytes(bytes.size());
        c.set_format(std::string(SniffCloudFormat(bytes)));
        service_.store().PutCloud(c);
        *response_ = c;
        service_.metrics().CountUpload(true);
        spdlog::info("upload {}: stored cloud {} ({} points, {} bytes)", id_, id, cloud.size(), bytes.size());
    }

    void Discard() {
        out_.close();
        std::error_code ec;
        fs::remove(path_, ec);
        committed_ = 0;
    }

    // Ends the call: once, and nothing may touch `this` after Finish.
    void Done(const grpc::Status& status) {
        if (claimed_) service_.ReleaseUpload(id_);
        claimed_ = false;
        if (!status.ok()) {
            const std::string& message = status.error_message();
            if (!id_.empty() && message.find(id_) != std::string::npos) spdlog::info("{}", message);
            else spdlog::info("upload {}: {}", id_.empty() ? "?" : id_, message);
        }
        Finish(status);
    }

    SurfelService& service_;
    v1::Cloud* response_;
    v1::UploadRequest request_;
    std::atomic<bool> cancelled_{false};
    bool started_ = false, claimed_ = false;
    bool hashed_ = false;  // hash_ covers the committed bytes (false while a resume is unhashed)
    std::string id_, filename_, path_;
    std::uint64_t committed_ = 0;
    std::ofstream out_;
    worker::Sha256 hash_;
};

}  // namespace

grpc::ServerReadReactor<v1::UploadRequest>* NewUploadReactor(SurfelService& service, v1::Cloud* response) {
    return new UploadReactor(service, response);
}

}  // namespace surfel::server
