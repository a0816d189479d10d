#include "service.h"

#include "download_reactor.h"
#include "upload_reactor.h"
#include "watch_reactor.h"

namespace surfel::server {

SurfelService::SurfelService(worker::Store& store, worker::JobManager& jobs, Metrics& metrics, Executor& ingest,
                             ServiceLimits limits)
    : store_(store), jobs_(jobs), metrics_(metrics), ingest_(ingest), limits_(limits) {}

bool SurfelService::ClaimUpload(const std::string& id) {
    std::lock_guard lock(uploads_mutex_);
    return active_uploads_.insert(id).second;
}

void SurfelService::ReleaseUpload(const std::string& id) {
    std::lock_guard lock(uploads_mutex_);
    active_uploads_.erase(id);
}

// ---- Streaming calls: one reactor each, in its own file -------------------------------------

grpc::ServerReadReactor<v1::UploadRequest>* SurfelService::Upload(grpc::CallbackServerContext*, v1::Cloud* response) {
    return NewUploadReactor(*this, response);
}

grpc::ServerWriteReactor<v1::JobEvent>* SurfelService::Watch(grpc::CallbackServerContext*, const v1::WatchRequest* req) {
    return NewWatchReactor(*this, *req);
}

grpc::ServerWriteReactor<v1::DataChunk>* SurfelService::Download(grpc::CallbackServerContext*,
                                                                  const v1::DownloadRequest* req) {
    return NewDownloadReactor(*this, *req);
}

}  // namespace surfel::server
