#pragma once
/// \file
/// The job kinds, one file each in this folder. Only job_kind.cpp's lookup names them.

#include "surfel/worker/job_kind.h"

namespace surfel::worker {

const JobKind& RenderKind();    ///< jobs/render_job.cpp
const JobKind& SimplifyKind();  ///< jobs/simplify_job.cpp
const JobKind& ResampleKind();  ///< jobs/resample_job.cpp
const JobKind& BooleanKind();   ///< jobs/boolean_job.cpp

}  // namespace surfel::worker
