#pragma once
/// \file
/// Surface error between two point-sampled surfaces (course notes, Pauly 2.4.1, Metro-style).

#include <cstdint>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/surface/mls.h"

namespace surfel {

struct SurfaceErrorOptions {
    float h_source = 0.0f;       ///< MLS scale for S (sampling Q on it), model units, >= 0; 0 = default of P.
    float h_target = 0.0f;       ///< MLS scale for S' (measuring distances), model units, >= 0; 0 = default of P'.
    std::size_t max_samples = 0; ///< |Q|: 0 = every point of P; else a seeded uniform subset.
    std::uint64_t seed = 1;      ///< Seed of that subset; every value is valid.
    /// Polynomial degree of the projection onto S', kMinMlsDegree..kMaxMlsDegree. The notes use a
    /// linear basis (1); its plane fit sits inside curved surfaces by about h^2 / (2 r), which
    /// would dominate the error of a good approximation, so the default is quadratic.
    int degree = 2;
    bool symmetric = false;      ///< Also measure S' -> S and report the larger maximum / mean of both.

    /// Throws Error(kInvalidArgument, "<field>: <what>") for the first bad field: "h_source",
    /// "h_target", "degree" (e.g. "degree: must lie in 0..2, got 3").
    void Validate() const;
};

struct SurfaceError {
    double max = 0.0;        ///< Delta_max (eq. 2.4), absolute
    /// Delta_avg (eq. 2.5), absolute: "the area-weighted integral of the point-to-surface
    /// distances". The notes draw Q uniformly by area (a particle simulation); Q here is P's own
    /// samples, so each q is weighted by the area its sample stands for (1 / rho, from its 16
    /// nearest neighbours, capped at 64 x the median) and a scanner's uneven density does not
    /// weight the regions it sampled densely.
    double avg = 0.0;
    double rms = 0.0;             ///< Root mean square distance, area-weighted like avg.
    double avg_per_sample = 0.0;  ///< The plain mean of d(q, S') over Q (density-weighted).
    double diagonal = 0.0;   ///< Bounding-box diagonal of P, the reference length
    double max_relative() const { return diagonal > 0 ? max / diagonal : 0.0; }
    double avg_relative() const { return diagonal > 0 ? avg / diagonal : 0.0; }
    double avg_per_sample_relative() const { return diagonal > 0 ? avg_per_sample / diagonal : 0.0; }
    std::size_t samples = 0; ///< |Q| actually measured
    /// Samples whose projection onto S' failed or extrapolated (landed farther than the nearest
    /// sample of P' plus h'); their distance is the one to that nearest sample. Samples that
    /// cannot be projected onto S are left out and counted here too.
    std::size_t failed = 0;
};

/// Delta_max(S, S') and Delta_avg(S, S'): Q is P projected onto its own MLS surface S (so Q lies
/// on S), and d(q, S') = |q - Psi_P'(q)| with the MLS projection onto S' (options.degree); where
/// that projection fails or extrapolates, the distance to the nearest sample of P'. Calls
/// options.Validate() first; each cloud needs at least 3 points.
SurfaceError MeasureSurfaceError(const PointCloud& p, const PointCloud& p_prime, const SurfaceErrorOptions& options = {},
                                 const ProgressFn& progress = {});

}  // namespace surfel
