#include "surfel/base/error.h"

namespace surfel {

std::string_view ErrorCodeName(ErrorCode code) {
    switch (code) {
        case ErrorCode::kInvalidArgument: return "InvalidArgument";
        case ErrorCode::kNotFound: return "NotFound";
        case ErrorCode::kResourceExhausted: return "ResourceExhausted";
        case ErrorCode::kCancelled: return "Cancelled";
        case ErrorCode::kDeadlineExceeded: return "DeadlineExceeded";
        case ErrorCode::kUnavailable: return "Unavailable";
        case ErrorCode::kFailedPrecondition: return "FailedPrecondition";
        case ErrorCode::kUnauthenticated: return "Unauthenticated";
        case ErrorCode::kInternal: return "Internal";
        case ErrorCode::kDataLoss: return "DataLoss";
    }
    return "Unknown";
}

namespace detail {
void CheckFailed(const char* expr, const char* file, int line, const std::string& msg) {
    std::fprintf(stderr, "SURFEL_CHECK failed: %s at %s:%d %s\n", expr, file, line, msg.c_str());
    std::abort();
}
}  // namespace detail

}  // namespace surfel
