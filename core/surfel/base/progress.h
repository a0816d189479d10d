#pragma once
/// \file
/// The progress/cancel hook every long algorithm takes.

#include <chrono>
#include <functional>
#include <mutex>
#include <string>

namespace surfel {

/// Called with the fraction done in [0, 1]; returns false to ask the algorithm to stop.
/// May be called from several threads at once (calls are serialised by ProgressTracker).
using ProgressFn = std::function<bool(double fraction)>;

/// Thread-safe progress accounting over a known amount of work units. Long loops call
/// Advance(n) after each chunk; when the hook returns false (or was cancelled before) the next
/// call to Advance or Check throws Error(kCancelled) naming the stage.
class ProgressTracker {
public:
    /// \param hook may be empty (no reporting, never cancelled).
    /// \param total number of work units, > 0.
    /// \param stage a short name used in the cancellation message, e.g. "normal estimation".
    ProgressTracker(ProgressFn hook, double total, std::string stage);

    /// Records `units` more work done, calls the hook at most every ~1 % of progress and throws
    /// Error(kCancelled) if it asked to stop.
    void Advance(double units = 1.0);

    /// Throws Error(kCancelled) if the hook has asked to stop, without reporting progress.
    void Check() const;

    /// True once the hook returned false.
    bool cancelled() const;

private:
    ProgressFn hook_;
    double total_;
    std::string stage_;
    mutable std::mutex mutex_;
    double done_ = 0.0;
    double last_reported_ = -1.0;
    bool cancelled_ = false;
};

/// Milliseconds elapsed since construction, for `time_ms` in reports.
class Stopwatch {
public:
    Stopwatch() : start_(std::chrono::steady_clock::now()) {}
    double ElapsedMs() const {
        return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start_)
            .count();
    }

private:
    std::chrono::steady_clock::time_point start_;
};

}  // namespace surfel
