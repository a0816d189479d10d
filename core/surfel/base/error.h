#pragma once
/// \file
/// Errors thrown by the core library and the checks for programming mistakes.

#include <cstdio>
#include <cstdlib>
#include <sstream>
#include <stdexcept>
#include <string>
#include <string_view>

namespace surfel {

/// What went wrong, in the vocabulary the service maps to gRPC status codes.
enum class ErrorCode {
    kInvalidArgument,    ///< Bad input: a malformed file, an option out of range.
    kNotFound,           ///< A named file, cloud or job does not exist.
    kResourceExhausted,  ///< A configured limit (points, bytes, queue) was exceeded.
    kCancelled,          ///< The progress hook asked to stop.
    kDeadlineExceeded,   ///< The work ran past its deadline.
    kUnavailable,        ///< The service is shutting down or cannot take work now; retry later.
    kFailedPrecondition, ///< The request does not fit the current state (a result before its job ended).
    kInternal,           ///< A bug: an invariant of the library did not hold.
    kDataLoss,           ///< Stored bytes no longer match their SHA-256 (a flipped byte on disk).
    kUnauthenticated,    ///< The caller presented no valid credentials (the service's auth).
};

/// The name of a code, e.g. "InvalidArgument".
std::string_view ErrorCodeName(ErrorCode code);

/// The one exception type of the core. The message names what is wrong (file, line or element,
/// field) and is meant to be shown to the user as it is.
class Error : public std::runtime_error {
public:
    Error(ErrorCode code, const std::string& message) : std::runtime_error(message), code_(code) {}
    ErrorCode code() const { return code_; }

private:
    ErrorCode code_;
};

namespace detail {
[[noreturn]] void CheckFailed(const char* expr, const char* file, int line, const std::string& msg);
}  // namespace detail

}  // namespace surfel

/// Aborts with the expression, location and message when a programming invariant fails.
/// Never used for bad input: that is an Error.
#define SURFEL_CHECK(cond, ...)                                                        \
    do {                                                                               \
        if (!(cond)) [[unlikely]] {                                                    \
            std::ostringstream surfel_check_os_;                                       \
            surfel_check_os_ << "" __VA_OPT__(<< __VA_ARGS__);                                        \
            ::surfel::detail::CheckFailed(#cond, __FILE__, __LINE__, surfel_check_os_.str()); \
        }                                                                              \
    } while (false)
