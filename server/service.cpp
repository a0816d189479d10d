#include "service.h"

#include "download_reactor.h"
#include "surfel/worker/status.h"
#include "upload_reactor.h"
#include "watch_reactor.h"

namespace surfel::server {
namespace {

// A streaming call refused before it started (UNAUTHENTICATED): finished at once.
template <typename Base>
class Refused final : public Base {
  public:
    explicit Refused(const grpc::Status& status) { this->Finish(status); }
    void OnDone() override { delete this; }
};

// The caller of `ctx`, or the status that refuses the call.
template <typename Reactor, typename Start>
Reactor* Authenticated(const SurfelService& service, grpc::CallbackServerContext* ctx, Start&& start) {
    Caller caller;
    try {
        caller = service.Authenticate(ctx);
    } catch (...) {
        return new Refused<Reactor>(worker::CurrentExceptionStatus());
    }
    return start(caller);
}

}  // namespace

Caller SurfelService::Authenticate(const grpc::CallbackServerContext* ctx) const {
    if (!ops_.auth().enabled()) return {};
    const auto& metadata = ctx->client_metadata();
    const auto it = metadata.find("authorization");
    return ops_.auth().Authenticate(it == metadata.end() ? std::string_view()
                                                         : std::string_view(it->second.data(), it->second.size()));
}

// ---- Streaming calls: one reactor each, in its own file -------------------------------------

grpc::ServerReadReactor<grpc::ByteBuffer>* SurfelService::Upload(grpc::CallbackServerContext* ctx,
                                                                 grpc::ByteBuffer* response) {
    return Authenticated<grpc::ServerReadReactor<grpc::ByteBuffer>>(
        *this, ctx,
        [&](const Caller& caller) { return NewUploadReactor(*this, caller, response); });
}

grpc::ServerWriteReactor<v1::JobEvent>* SurfelService::Watch(grpc::CallbackServerContext* ctx,
                                                             const v1::WatchRequest* req) {
    return Authenticated<grpc::ServerWriteReactor<v1::JobEvent>>(
        *this, ctx, [&](const Caller& caller) { return NewWatchReactor(*this, caller, *req); });
}

grpc::ServerWriteReactor<v1::DataChunk>* SurfelService::Download(grpc::CallbackServerContext* ctx,
                                                                  const v1::DownloadRequest* req) {
    return Authenticated<grpc::ServerWriteReactor<v1::DataChunk>>(
        *this, ctx, [&](const Caller& caller) { return NewDownloadReactor(*this, caller, *req); });
}

}  // namespace surfel::server
