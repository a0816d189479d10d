#include "service.h"

#include "download_reactor.h"
#include "upload_reactor.h"
#include "watch_reactor.h"

namespace surfel::server {

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
