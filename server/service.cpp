#include "service.h"

#include <spdlog/spdlog.h>

#include <cstdio>
#include <deque>
#include <filesystem>
#include <fstream>
#include <memory>
#include <algorithm>
#include <cctype>

#include "surfel/base/error.h"
#include "surfel/io/ply.h"
#include "surfel/worker/job_runner.h"
#include "surfel/worker/status.h"

namespace surfel::server {
namespace fs = std::filesystem;
using worker::CurrentExceptionStatus;

namespace {

bool IsFinal(v1::JobState s) { return s == v1::SUCCEEDED || s == v1::FAILED || s == v1::CANCELLED; }

// Upload ids name files: [A-Za-z0-9_-]{1,128}.
void CheckUploadId(const std::string& id) {
    const bool ok = !id.empty() && id.size() <= 128 && std::all_of(id.begin(), id.end(), [](char c) {
        return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-';
    });
    if (!ok) throw Error(ErrorCode::kInvalidArgument, "upload_id: must match [A-Za-z0-9_-]{1,128}");
}

std::string SniffFormat(std::string_view bytes) {
    if (bytes.substr(0, 3) != "ply") return "xyz";
    const auto line_end = bytes.find('\n', 3);
    const std::string_view head = bytes.substr(0, line_end == std::string_view::npos ? 256 : line_end + 80);
    if (head.find("binary_little_endian") != std::string_view::npos) return "ply-binary-le";
    if (head.find("binary_big_endian") != std::string_view::npos) return "ply-binary-be";
    return "ply-ascii";
}

// Runs `fn` and finishes a unary call with OK or the mapped status of what it threw.
template <typename Fn>
grpc::ServerUnaryReactor* Unary(grpc::CallbackServerContext* ctx, Fn&& fn) {
    auto* reactor = ctx->DefaultReactor();
    grpc::Status status;
    try {
        fn();
    } catch (...) {
        status = CurrentExceptionStatus();
    }
    reactor->Finish(status);
    return reactor;
}

// ---- Upload ---------------------------------------------------------------------------------

class UploadReactor final : public grpc::ServerReadReactor<v1::UploadRequest> {
public:
    UploadReactor(SurfelService& service, v1::Cloud* response) : service_(service), response_(response) {
        StartRead(&request_);
    }

    void OnReadDone(bool ok) override {
        if (!ok) {  // the client closed (or broke) the stream without finish_write
            Done(grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                              "upload " + id_ + " incomplete: " + std::to_string(committed_) +
                                  " bytes committed; resume at write_offset " + std::to_string(committed_) +
                                  " and end with finish_write"));
            return;
        }
        try {
            Chunk();
            if (request_.finish_write()) {
                Complete();
                Done(grpc::Status::OK);
                return;
            }
        } catch (...) {
            Done(CurrentExceptionStatus());
            return;
        }
        StartRead(&request_);
    }

    void OnDone() override { delete this; }

private:
    void Chunk() {
        if (!started_) {
            id_ = request_.upload_id();
            CheckUploadId(id_);
            if (!service_.ClaimUpload(id_))
                throw Error(ErrorCode::kFailedPrecondition, "upload " + id_ + " is in progress on another call");
            claimed_ = true;
            filename_ = request_.filename().empty() ? id_ : fs::path(request_.filename()).filename().string();
            path_ = service_.store().UploadPath(id_);
            std::error_code ec;
            committed_ = fs::exists(path_, ec) ? fs::file_size(path_, ec) : 0;
            if (committed_ > 0) {  // resuming: hash what is already there
                std::ifstream in(path_, std::ios::binary);
                std::string buf(1 << 20, '\0');
                while (in) {
                    in.read(buf.data(), static_cast<std::streamsize>(buf.size()));
                    hash_.Update(std::string_view(buf.data(), static_cast<std::size_t>(in.gcount())));
                }
            }
            out_.open(path_, std::ios::binary | std::ios::app);
            if (!out_) throw Error(ErrorCode::kInternal, "cannot open " + path_);
            started_ = true;
        } else if (!request_.upload_id().empty() && request_.upload_id() != id_) {
            throw Error(ErrorCode::kInvalidArgument, "upload_id: changed within one call");
        }
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
        out_.write(data.data(), static_cast<std::streamsize>(data.size()));
        out_.flush();
        if (!out_) throw Error(ErrorCode::kInternal, "writing " + path_ + " failed");
        hash_.Update(data);
        committed_ += data.size();
        service_.metrics().AddBytesIn(data.size());
    }

    void Complete() {
        out_.close();
        const std::string id = hash_.FinishHex();
        if (auto existing = service_.store().FindCloud(id)) {  // stored before: no need to read it back
            const std::uint64_t size = committed_;
            Discard();
            *response_ = *existing;
            response_->set_deduplicated(true);
            spdlog::info("upload {}: {} bytes, already stored as cloud {}", id_, size, id);
            service_.metrics().CountUpload(true);
            return;
        }
        const std::string bytes = ReadFileBytes(path_);
        PointCloud cloud;
        try {
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
        c.set_format(SniffFormat(bytes));
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

    void Done(const grpc::Status& status) {
        if (claimed_) service_.ReleaseUpload(id_);
        claimed_ = false;
        if (!status.ok()) spdlog::info("upload {}: {}", id_.empty() ? "?" : id_, status.error_message());
        Finish(status);
    }

    SurfelService& service_;
    v1::Cloud* response_;
    v1::UploadRequest request_;
    bool started_ = false, claimed_ = false;
    std::string id_, filename_, path_;
    std::uint64_t committed_ = 0;
    std::ofstream out_;
    worker::Sha256 hash_;
};

// ---- Result chunks shared by Watch and Download ------------------------------------------------

class ChunkReader {
public:
    bool Open(const std::string& path) {
        in_.open(path, std::ios::binary);
        if (!in_) return false;
        in_.seekg(0, std::ios::end);
        total_ = static_cast<std::int64_t>(in_.tellg());
        in_.seekg(0);
        return true;
    }
    /// Fills the next chunk; false at the end.
    bool Next(v1::DataChunk* chunk, std::size_t size) {
        if (sent_any_ && offset_ >= total_) return false;  // an empty result is one empty chunk
        std::string data(static_cast<std::size_t>(std::min<std::int64_t>(size, total_ - offset_)), '\0');
        in_.read(data.data(), static_cast<std::streamsize>(data.size()));
        chunk->set_offset(offset_);
        chunk->set_total_size(total_);
        chunk->set_data(std::move(data));
        offset_ += static_cast<std::int64_t>(chunk->data().size());
        sent_any_ = true;
        return true;
    }

private:
    std::ifstream in_;
    std::int64_t total_ = 0, offset_ = 0;
    bool sent_any_ = false;
};

// ---- Watch ------------------------------------------------------------------------------------

class WatchReactor final : public grpc::ServerWriteReactor<v1::JobEvent> {
public:
    WatchReactor(SurfelService& service, const v1::WatchRequest& request) : service_(service), request_(request) {
        sink_ = std::make_shared<Sink>();
        sink_->reactor = this;
        std::weak_ptr<Sink> weak = sink_;
        std::optional<v1::Job> job;
        try {
            job = service_.jobs().Subscribe(
                request_.job_id(), [weak](const v1::JobEvent& e) {
                    if (auto s = weak.lock()) {
                        std::lock_guard lock(s->mutex);
                        if (s->reactor) s->reactor->Push(e);
                    }
                },
                &token_);
        } catch (...) {
            FinishOnce(CurrentExceptionStatus());
            return;
        }
        if (!job) {
            FinishOnce(grpc::Status(grpc::StatusCode::NOT_FOUND, "job " + request_.job_id() + " not found"));
            return;
        }
        subscribed_ = !IsFinal(job->state());
        if (!subscribed_) {  // already final: its state and its final event
            std::lock_guard lock(sink_->mutex);
            v1::JobEvent first;
            first.set_job_id(job->id());
            *first.mutable_state() = *job;
            Push(first);
            v1::JobEvent last;
            last.set_job_id(job->id());
            if (job->state() == v1::SUCCEEDED) *last.mutable_finished() = job->result();
            else {
                last.mutable_failed()->set_code(job->status_code());
                last.mutable_failed()->set_message(job->status_message());
            }
            Push(last);
        }
    }

    void OnWriteDone(bool ok) override {
        std::lock_guard lock(sink_->mutex);
        writing_ = false;
        if (!ok) {
            FinishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "watch stream broken"));
            return;
        }
        if (!pending_.empty()) pending_.pop_front();
        Kick();
    }

    void OnCancel() override {
        if (request_.cancel_on_disconnect()) {
            try {
                service_.jobs().Cancel(request_.job_id());
                spdlog::info("job {}: cancelled because its watcher went away", request_.job_id());
            } catch (...) {
            }
        }
        std::lock_guard lock(sink_->mutex);
        FinishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "watch cancelled by the client"));
    }

    void OnDone() override {
        if (subscribed_) service_.jobs().Unsubscribe(request_.job_id(), token_);
        {
            std::lock_guard lock(sink_->mutex);
            sink_->reactor = nullptr;
        }
        delete this;
    }

private:
    struct Sink {
        std::recursive_mutex mutex;  // recursive: a reaction could run inline inside StartWrite
        WatchReactor* reactor = nullptr;
    };

    // sink_->mutex held.
    void Push(const v1::JobEvent& e) {
        if (final_queued_ || finished_) return;
        // Coalesce progress: replace a waiting running event rather than queueing another.
        if (e.has_running() && pending_.size() > 1 && pending_.back().has_running()) pending_.back() = e;
        else pending_.push_back(e);
        if (e.has_finished() || e.has_failed()) {
            final_queued_ = true;
            if (e.has_finished() && request_.include_result()) {
                if (!reader_.Open(service_.store().ResultPath(e.job_id()))) {
                    pending_.back().clear_finished();
                    pending_.back().mutable_failed()->set_code(grpc::StatusCode::NOT_FOUND);
                    pending_.back().mutable_failed()->set_message("result of job " + e.job_id() + " is gone");
                } else {
                    streaming_result_ = true;
                }
            }
        }
        Kick();
    }

    // sink_->mutex held: start the next write, or finish when everything is sent.
    void Kick() {
        if (writing_ || finished_) return;
        if (pending_.empty() && streaming_result_) {
            v1::JobEvent chunk;
            chunk.set_job_id(request_.job_id());
            if (reader_.Next(chunk.mutable_result_chunk(), service_.limits().download_chunk_bytes)) {
                service_.metrics().AddBytesOut(chunk.result_chunk().data().size());
                pending_.push_back(std::move(chunk));
            } else {
                streaming_result_ = false;
            }
        }
        if (!pending_.empty()) {
            writing_ = true;
            StartWrite(&pending_.front());
            return;
        }
        if (final_queued_) FinishLocked(grpc::Status::OK);
    }

    void FinishOnce(const grpc::Status& status) {
        std::lock_guard lock(sink_->mutex);
        FinishLocked(status);
    }
    void FinishLocked(const grpc::Status& status) {
        if (finished_) return;
        finished_ = true;
        Finish(status);
    }

    SurfelService& service_;
    v1::WatchRequest request_;
    std::shared_ptr<Sink> sink_;
    std::uint64_t token_ = 0;
    bool subscribed_ = false;
    std::deque<v1::JobEvent> pending_;  // front is being written while writing_
    bool writing_ = false, final_queued_ = false, finished_ = false, streaming_result_ = false;
    ChunkReader reader_;
};

// ---- Download ---------------------------------------------------------------------------------

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
        if (reader_.Next(&chunk_, service_.limits().download_chunk_bytes)) {
            service_.metrics().AddBytesOut(chunk_.data().size());
            StartWrite(&chunk_);
        } else {
            Finish(grpc::Status::OK);
        }
    }
    SurfelService& service_;
    ChunkReader reader_;
    v1::DataChunk chunk_;
};

}  // namespace

SurfelService::SurfelService(worker::Store& store, worker::JobManager& jobs, Metrics& metrics, ServiceLimits limits)
    : store_(store), jobs_(jobs), metrics_(metrics), limits_(limits) {}

bool SurfelService::ClaimUpload(const std::string& id) {
    std::lock_guard lock(uploads_mutex_);
    return active_uploads_.insert(id).second;
}
void SurfelService::ReleaseUpload(const std::string& id) {
    std::lock_guard lock(uploads_mutex_);
    active_uploads_.erase(id);
}

grpc::ServerReadReactor<v1::UploadRequest>* SurfelService::Upload(grpc::CallbackServerContext*, v1::Cloud* response) {
    return new UploadReactor(*this, response);
}

grpc::ServerUnaryReactor* SurfelService::QueryUpload(grpc::CallbackServerContext* ctx, const v1::QueryUploadRequest* req,
                                                     v1::QueryUploadResponse* resp) {
    return Unary(ctx, [&] {
        std::error_code ec;
        const std::string path = store_.UploadPath(req->upload_id());
        CheckUploadId(req->upload_id());
        resp->set_committed_size(fs::exists(path, ec) ? static_cast<std::int64_t>(fs::file_size(path, ec)) : 0);
    });
}

grpc::ServerUnaryReactor* SurfelService::GetCloud(grpc::CallbackServerContext* ctx, const v1::GetCloudRequest* req,
                                                  v1::Cloud* resp) {
    return Unary(ctx, [&] {
        auto c = store_.FindCloud(req->cloud_id());
        if (!c) throw Error(ErrorCode::kNotFound, "cloud " + req->cloud_id() + " not found");
        *resp = *c;
    });
}

grpc::ServerUnaryReactor* SurfelService::DeleteCloud(grpc::CallbackServerContext* ctx, const v1::DeleteCloudRequest* req,
                                                     v1::DeleteCloudResponse* resp) {
    return Unary(ctx, [&] {
        if (!store_.DeleteCloud(req->cloud_id()))
            throw Error(ErrorCode::kNotFound, "cloud " + req->cloud_id() + " not found");
        resp->set_deleted(true);
        spdlog::info("cloud {} deleted", req->cloud_id());
    });
}

grpc::ServerUnaryReactor* SurfelService::Submit(grpc::CallbackServerContext* ctx, const v1::SubmitRequest* req,
                                                v1::Job* resp) {
    return Unary(ctx, [&] {
        *resp = jobs_.Submit(req->spec());
        metrics_.SetQueueDepth(jobs_.QueueDepth());
    });
}

grpc::ServerWriteReactor<v1::JobEvent>* SurfelService::Watch(grpc::CallbackServerContext*, const v1::WatchRequest* req) {
    return new WatchReactor(*this, *req);
}

grpc::ServerWriteReactor<v1::DataChunk>* SurfelService::Download(grpc::CallbackServerContext*,
                                                                  const v1::DownloadRequest* req) {
    return new DownloadReactor(*this, *req);
}

grpc::ServerUnaryReactor* SurfelService::Cancel(grpc::CallbackServerContext* ctx, const v1::CancelRequest* req,
                                                v1::Job* resp) {
    return Unary(ctx, [&] {
        *resp = jobs_.Cancel(req->job_id());
        metrics_.SetQueueDepth(jobs_.QueueDepth());
    });
}

grpc::ServerUnaryReactor* SurfelService::GetJob(grpc::CallbackServerContext* ctx, const v1::GetJobRequest* req,
                                                v1::Job* resp) {
    return Unary(ctx, [&] {
        auto job = jobs_.Get(req->job_id());
        if (!job) throw Error(ErrorCode::kNotFound, "job " + req->job_id() + " not found");
        *resp = *job;
    });
}

grpc::ServerUnaryReactor* SurfelService::ListJobs(grpc::CallbackServerContext* ctx, const v1::ListJobsRequest* req,
                                                  v1::ListJobsResponse* resp) {
    return Unary(ctx, [&] {
        if (req->limit() > 10000) throw Error(ErrorCode::kInvalidArgument, "limit: at most 10000");
        for (v1::Job& j : jobs_.List(req->limit(), req->state())) *resp->add_jobs() = std::move(j);
    });
}

}  // namespace surfel::server
