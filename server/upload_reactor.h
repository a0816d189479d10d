#pragma once
/// \file
/// The Upload call: a client stream of chunks appended to <data>/uploads/<id>.part, hashed while
/// written; on the final message the file is parsed, validated and stored as a cloud on the
/// service's ingest Executor, never on a gRPC thread.

#include <string>

#include "service.h"

namespace surfel::server {

/// Throws Error(kInvalidArgument) unless `id` matches [A-Za-z0-9_-]{1,128} (upload ids name files).
void CheckUploadId(const std::string& id);

/// A reactor for one Upload call; it deletes itself in OnDone.
grpc::ServerReadReactor<v1::UploadRequest>* NewUploadReactor(SurfelService& service, v1::Cloud* response);

}  // namespace surfel::server
