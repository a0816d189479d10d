#pragma once
/// \file
/// The Download call: a SUCCEEDED job's result in chunks.

#include "service.h"

namespace surfel::server {

/// A reactor for one Download call; it deletes itself in OnDone.
grpc::ServerWriteReactor<v1::DataChunk>* NewDownloadReactor(SurfelService& service, const Caller& caller,
                                                            const v1::DownloadRequest& request);

}  // namespace surfel::server
