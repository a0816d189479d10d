#pragma once
/// \file
/// The checks every `Options::Validate()` is written with. Each throws
/// `Error(ErrorCode::kInvalidArgument, "<field>: <what>")`, where `field` is the name the user
/// wrote (the job spec's field path); the worker and the CLI prefix their own path
/// ("render.width: must lie in 1..16384, got 0").

#include <cctype>
#include <cmath>
#include <sstream>
#include <string>
#include <string_view>

#include "surfel/base/error.h"
#include "surfel/base/point_cloud.h"

namespace surfel {

/// Throws `Error(kInvalidArgument, field + ": " + what)`.
[[noreturn]] inline void InvalidField(const std::string& field, const std::string& what) {
    throw Error(ErrorCode::kInvalidArgument, field + ": " + what);
}

/// Accepts a finite `value` in the closed range [lo, hi]; otherwise throws
/// "<field>: must lie in LO..HI, got V" (LO, HI and V in ostream default formatting, so 1e6 is
/// written "1e+06" and 0.5 "0.5"). NaN and +-inf are always rejected.
inline void CheckRange(const std::string& field, double value, double lo, double hi) {
    if (std::isfinite(value) && value >= lo && value <= hi) return;
    std::ostringstream msg;
    msg << "must lie in " << lo << ".." << hi << ", got " << value;
    InvalidField(field, msg.str());
}

/// Accepts a finite `value` >= lo; otherwise throws "<field>: must be finite and at least LO, got V"
/// (for limits with no upper bound, e.g. a scale where 0 means "derive it").
inline void CheckAtLeast(const std::string& field, double value, double lo) {
    if (std::isfinite(value) && value >= lo) return;
    std::ostringstream msg;
    msg << "must be finite and at least " << lo << ", got " << value;
    InvalidField(field, msg.str());
}

/// Accepts a finite `value` > 0; otherwise throws "<field>: must be positive, got V".
inline void CheckPositive(const std::string& field, double value) {
    if (std::isfinite(value) && value > 0) return;
    std::ostringstream msg;
    msg << "must be positive, got " << value;
    InvalidField(field, msg.str());
}

/// Accepts a finite scalar; otherwise throws "<field>: must be finite".
inline void CheckFinite(const std::string& field, double value) {
    if (!std::isfinite(value)) InvalidField(field, "must be finite");
}

/// Accepts a vector whose three components are finite; otherwise throws "<field>: must be finite".
inline void CheckFinite(const std::string& field, const Vec3d& v) {
    if (!std::isfinite(v.x()) || !std::isfinite(v.y()) || !std::isfinite(v.z())) InvalidField(field, "must be finite");
}

/// True when `message` starts with a field path and a colon ("width: ...", "mls.degree: ...",
/// "lights[0].kind: ..."), not with prose ("the surface needs ...").
inline bool StartsWithFieldPath(std::string_view message) {
    std::size_t i = 0;
    while (i < message.size() && (std::isalnum(static_cast<unsigned char>(message[i])) || message[i] == '_' ||
                                  message[i] == '.' || message[i] == '[' || message[i] == ']'))
        ++i;
    return i > 0 && i < message.size() && message[i] == ':';
}

/// Runs `fn` (an Options::Validate(), or work whose errors name fields) and rethrows an
/// Error(kInvalidArgument) from it with `prefix` + "." before its message: nested Options and the
/// worker's adapters add where a field sits ("degree: ..." -> "mls.degree: ...",
/// "width: ..." -> "render.width: ..."). A message that names no field gets `prefix` + ": "
/// ("the surface needs ..." -> "render: the surface needs ..."); one that starts with `prefix`
/// + ":" is kept.
template <typename Fn>
void WithFieldPrefix(const std::string& prefix, Fn&& fn) {
    try {
        fn();
    } catch (const Error& e) {
        const std::string_view what = e.what();
        if (e.code() != ErrorCode::kInvalidArgument || what.rfind(prefix + ":", 0) == 0) throw;
        throw Error(e.code(), prefix + (StartsWithFieldPath(what) ? "." : ": ") + e.what());
    }
}

}  // namespace surfel
