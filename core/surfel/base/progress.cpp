#include "surfel/base/progress.h"

#include <algorithm>

#include "surfel/base/error.h"

namespace surfel {

ProgressTracker::ProgressTracker(ProgressFn hook, double total, std::string stage)
    : hook_(std::move(hook)), total_(std::max(total, 1e-12)), stage_(std::move(stage)) {}

void ProgressTracker::Advance(double units) {
    if (!hook_) return;
    std::lock_guard lock(mutex_);
    if (!cancelled_) {
        done_ += units;
        const double fraction = std::min(1.0, done_ / total_);
        if (fraction - last_reported_ >= 0.01 || fraction >= 1.0) {
            last_reported_ = fraction;
            if (!hook_(fraction)) cancelled_ = true;
        }
    }
    if (cancelled_) throw Error(ErrorCode::kCancelled, "cancelled during " + stage_);
}

void ProgressTracker::Check() const {
    if (cancelled()) throw Error(ErrorCode::kCancelled, "cancelled during " + stage_);
}

bool ProgressTracker::cancelled() const {
    std::lock_guard lock(mutex_);
    return cancelled_;
}

}  // namespace surfel
