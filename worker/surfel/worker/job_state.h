#pragma once
/// \file
/// Facts about job states shared by the job manager and the transports.

#include "surfel/v1/surfel.pb.h"

namespace surfel::worker {

/// True for the states a job never leaves: SUCCEEDED, FAILED, CANCELLED.
inline bool IsFinal(v1::JobState state) {
    return state == v1::SUCCEEDED || state == v1::FAILED || state == v1::CANCELLED;
}

}  // namespace surfel::worker
