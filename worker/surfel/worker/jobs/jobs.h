#pragma once
/// \file
/// The job kinds, one file each in this folder. Only job_kind.cpp's lookup names them.

#include "surfel/boolean/boolean.h"
#include "surfel/worker/job_kind.h"

namespace surfel::worker {

const JobKind& RenderKind();    ///< jobs/render_job.cpp
const JobKind& SimplifyKind();  ///< jobs/simplify_job.cpp
const JobKind& ResampleKind();  ///< jobs/resample_job.cpp
const JobKind& BooleanKind();   ///< jobs/boolean_job.cpp

/// The core operation of a proto BooleanJob.Op; throws Error(kInvalidArgument) naming `field`
/// ("boolean.op: is required ...") for OP_UNSPECIFIED or an unknown value. jobs/boolean_job.cpp.
BooleanOp BooleanOpFromProto(int op, const std::string& field);
/// B's placement from the proto, checked: throws Error(kInvalidArgument) naming
/// "<field>.rotation", "<field>.translation" or "<field>.scale". jobs/boolean_job.cpp.
Similarity SimilarityFromProto(const v1::Similarity& t, const std::string& field);

}  // namespace surfel::worker
