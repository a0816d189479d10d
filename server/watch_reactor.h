#pragma once
/// \file
/// The Watch call: a job's events as they happen (progress coalesced while a write is in
/// flight), then, with include_result, its result in chunks.

#include "service.h"

namespace surfel::server {

/// A reactor for one Watch call; it deletes itself in OnDone.
grpc::ServerWriteReactor<v1::JobEvent>* NewWatchReactor(SurfelService& service, const Caller& caller,
                                                       const v1::WatchRequest& request);

}  // namespace surfel::server
