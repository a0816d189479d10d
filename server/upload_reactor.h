#pragma once
/// \file
/// The Upload call: a client stream of chunks fed to an UploadSession (upload_session.h), which
/// does the hashing, limits, parsing and storing; this reactor only adapts gRPC's reads to it and
/// runs the slow steps on the service's ingest Executor, never on a gRPC thread.

#include <cstddef>
#include <vector>

#include "service.h"

namespace surfel::server {

/// A reactor for one Upload call; it deletes itself in OnDone. `response`: the Cloud, serialized.
grpc::ServerReadReactor<grpc::ByteBuffer>* NewUploadReactor(SurfelService& service,
                                                            const Caller& caller,
                                                            grpc::ByteBuffer* response);

/// An UploadRequest read from gRPC's raw message without copying its chunk: `fields` holds every
/// field but `data`, whose bytes are `data` (slices of the message's own, in order; `data_size`
/// bytes in all). The same message as protobuf's parse of the whole buffer (the fields in any
/// order, unknown fields kept); a message with `data` twice or with groups is parsed whole by
/// protobuf (the last `data` wins) and its chunk copied once. False: not a valid UploadRequest.
bool ParseUploadMessage(const grpc::ByteBuffer& message, v1::UploadRequest* fields,
                        std::vector<grpc::Slice>* data, std::size_t* data_size);

}  // namespace surfel::server
