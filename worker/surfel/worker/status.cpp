#include "surfel/worker/status.h"

#include <string>

namespace surfel::worker {

grpc::StatusCode ToStatusCode(ErrorCode code) {
    switch (code) {
        case ErrorCode::kInvalidArgument: return grpc::StatusCode::INVALID_ARGUMENT;
        case ErrorCode::kNotFound: return grpc::StatusCode::NOT_FOUND;
        case ErrorCode::kResourceExhausted: return grpc::StatusCode::RESOURCE_EXHAUSTED;
        case ErrorCode::kCancelled: return grpc::StatusCode::CANCELLED;
        case ErrorCode::kDeadlineExceeded: return grpc::StatusCode::DEADLINE_EXCEEDED;
        case ErrorCode::kUnavailable: return grpc::StatusCode::UNAVAILABLE;
        case ErrorCode::kFailedPrecondition: return grpc::StatusCode::FAILED_PRECONDITION;
        case ErrorCode::kInternal: return grpc::StatusCode::INTERNAL;
        case ErrorCode::kDataLoss: return grpc::StatusCode::DATA_LOSS;
        case ErrorCode::kUnauthenticated: return grpc::StatusCode::UNAUTHENTICATED;
    }
    return grpc::StatusCode::INTERNAL;
}

ErrorCode FromStatusCode(int code) {
    for (ErrorCode c : {ErrorCode::kInvalidArgument, ErrorCode::kNotFound, ErrorCode::kResourceExhausted,
                        ErrorCode::kCancelled, ErrorCode::kDeadlineExceeded, ErrorCode::kUnavailable,
                        ErrorCode::kFailedPrecondition, ErrorCode::kDataLoss,
                        ErrorCode::kUnauthenticated})
        if (static_cast<int>(ToStatusCode(c)) == code) return c;
    return ErrorCode::kInternal;
}

grpc::Status ToStatus(const std::exception& e) {
    if (const auto* err = dynamic_cast<const Error*>(&e)) return {ToStatusCode(err->code()), err->what()};
    return {grpc::StatusCode::INTERNAL, std::string("internal error: ") + e.what()};
}

grpc::Status CurrentExceptionStatus() noexcept {
    try {
        throw;
    } catch (const std::exception& e) {
        return ToStatus(e);
    } catch (...) {
        return {grpc::StatusCode::INTERNAL, "internal error: unknown exception"};
    }
}

}  // namespace surfel::worker
