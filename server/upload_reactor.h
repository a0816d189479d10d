#pragma once
/// \file
/// The Upload call: a client stream of chunks fed to an UploadSession (upload_session.h), which
/// does the hashing, limits, parsing and storing; this reactor only adapts gRPC's reads to it and
/// runs the slow steps on the service's ingest Executor, never on a gRPC thread.

#include "service.h"

namespace surfel::server {

/// A reactor for one Upload call; it deletes itself in OnDone.
grpc::ServerReadReactor<v1::UploadRequest>* NewUploadReactor(SurfelService& service, const Caller& caller,
                                                             v1::Cloud* response);

}  // namespace surfel::server
