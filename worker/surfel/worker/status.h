#pragma once
/// \file
/// The one mapping from the core's errors to gRPC status codes, used by every handler and for
/// the status of failed jobs.

#include <grpcpp/support/status.h>

#include <exception>

#include "surfel/base/error.h"

namespace surfel::worker {

/// kInvalidArgument -> INVALID_ARGUMENT, kNotFound -> NOT_FOUND, kResourceExhausted ->
/// RESOURCE_EXHAUSTED, kCancelled -> CANCELLED, kDeadlineExceeded -> DEADLINE_EXCEEDED,
/// kUnavailable -> UNAVAILABLE, kFailedPrecondition -> FAILED_PRECONDITION, kInternal -> INTERNAL,
/// kDataLoss -> DATA_LOSS.
grpc::StatusCode ToStatusCode(ErrorCode code);
/// The inverse, for a client that reports a failed job as a core error (codes with no core
/// counterpart become kInternal).
ErrorCode FromStatusCode(int code);

/// The status for an exception caught at a handler boundary: surfel::Error by its code and
/// message; anything else is INTERNAL ("internal error: ..."), a bug.
grpc::Status ToStatus(const std::exception& e);
/// Same, for the exception in flight (call inside a catch block); never throws.
grpc::Status CurrentExceptionStatus() noexcept;

}  // namespace surfel::worker
