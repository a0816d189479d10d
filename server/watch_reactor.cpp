#include "watch_reactor.h"

#include <spdlog/spdlog.h>

#include <deque>
#include <memory>
#include <mutex>
#include <optional>

#include "chunk_reader.h"
#include "surfel/worker/job_state.h"
#include "surfel/worker/status.h"

namespace surfel::server {
namespace {

using worker::CurrentExceptionStatus;

// ---- Watch reactor ----------------------------------------------------------------------------
//
// Threads. Events arrive from the job manager (its worker threads, or the caller of Submit and
// Cancel) through a listener that must not block: it queues the event and starts a write when
// none is in flight. OnWriteDone starts the next one. All state is under sink_->mutex, which the
// listener reaches through a weak pointer, so a late event after OnDone finds no reactor.
// The result, with include_result, is read one chunk per write (download_chunk_bytes), never
// whole. OnCancel's cancel_on_disconnect is the manager's Cancel: a flag, or one SQLite update
// for a queued job, the same work as the unary Cancel.
class WatchReactor final : public grpc::ServerWriteReactor<v1::JobEvent> {
public:
    WatchReactor(SurfelService& service, const Caller& caller, const v1::WatchRequest& request)
        : service_(service), caller_(caller), request_(request) {
        sink_ = std::make_shared<Sink>();
        sink_->reactor = this;
        std::weak_ptr<Sink> weak = sink_;
        std::optional<v1::Job> job;
        try {
            if (caller.scoped) service_.ops().GetJob(caller, request_.job_id());  // NOT_FOUND if not its own
            job = service_.jobs().Subscribe(
                request_.job_id(),
                [weak](const v1::JobEvent& e) {
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
        subscribed_ = !worker::IsFinal(job->state());
        if (!subscribed_) {  // already final: its state and its final event
            std::lock_guard lock(sink_->mutex);
            for (const v1::JobEvent& e : Operations::FinalEvents(*job)) Push(e);
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
                spdlog::warn("job {}: cancel on disconnect failed: {}", request_.job_id(),
                             CurrentExceptionStatus().error_message());
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
        if (e.has_running() && pending_.size() > 1 && pending_.back().has_running()) {
            pending_.back() = e;
        } else {
            pending_.push_back(e);
        }
        if (e.has_finished() || e.has_failed()) {
            final_queued_ = true;
            if (e.has_finished() && request_.include_result()) {
                bool open = false;
                try {
                    open = reader_.Open(service_.store().blobs(), e.job_id(), e.finished());
                } catch (const std::exception&) {  // the blob store is unreachable
                }
                if (!open) {
                    pending_.back().clear_finished();
                    pending_.back().mutable_failed()->set_code(grpc::StatusCode::NOT_FOUND);
                    std::string why = "result of job " + e.job_id() + " is gone";
                    try {
                        why = service_.ops().ResultGoneMessage(caller_, e.job_id());  // "evicted …"
                    } catch (const std::exception&) {  // the store is unreachable: the plain words
                    }
                    pending_.back().mutable_failed()->set_message(why);
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
            bool more = false;
            try {
                more = reader_.Next(chunk.mutable_result_chunk(), service_.limits().download_chunk_bytes);
            } catch (...) {
                FinishLocked(CurrentExceptionStatus());
                return;
            }
            if (more) {
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
    Caller caller_;
    v1::WatchRequest request_;
    std::shared_ptr<Sink> sink_;
    std::uint64_t token_ = 0;
    bool subscribed_ = false;
    std::deque<v1::JobEvent> pending_;  // front is being written while writing_
    bool writing_ = false, final_queued_ = false, finished_ = false, streaming_result_ = false;
    ChunkReader reader_;
};

}  // namespace

grpc::ServerWriteReactor<v1::JobEvent>* NewWatchReactor(SurfelService& service, const Caller& caller,
                                                       const v1::WatchRequest& request) {
    return new WatchReactor(service, caller, request);
}

}  // namespace surfel::server
