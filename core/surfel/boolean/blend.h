#pragma once
/// \file
/// Particle-based blending of a boolean result's creases (course notes, Pauly 3.1.4): the
/// samples within a blend radius of the intersection curve become oriented particles [ST92]
/// whose inter-particle potentials make the surface there smooth; the samples just beyond the
/// radius stay fixed and hold the blend tangent to the untouched surface.

#include <cstddef>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"

namespace surfel {

/// Limits of the blending options (BooleanOptions::blend_radius, blend_iterations).
inline constexpr int kMinBlendIterations = 1;
inline constexpr int kMaxBlendIterations = 10000;
inline constexpr int kDefaultBlendIterations = 200;

struct BlendReport {
    std::size_t moved = 0;           ///< Samples within the radius of the curve (the particles).
    std::size_t fixed = 0;           ///< Samples just beyond it that held the boundary.
    std::size_t creases_cleared = 0; ///< Surfel pairs that became ordinary samples.
    std::size_t knife_edges = 0;     ///< Surfel pairs over 120 degrees apart, held fixed.
    int iterations = 0;
    double max_displacement = 0.0;   ///< Largest distance a particle moved (model units).
    double mean_displacement = 0.0;  ///< Over the particles.
};

/// Smooths the creases of a boolean result in place (notes 3.1.4).
///
/// `cloud` is what Boolean() returns: unit normals outward, splat radii (the local spacing) and
/// the extras "crease" / "crease_n{x,y,z}" marking the surfel pairs of the intersection curve.
/// Every sample (but a knife edge) whose distance d to the nearest curve sample is below
/// `radius` becomes a particle; those with radius <= d < radius + support (support = 2.5 x the particles' median
/// spacing) are fixed neighbours. A curve sample starts with the mean of its two normals. Each
/// of `iterations` Jacobi steps moves every particle by its forces, scaled by the fall-off
/// (1 - (d / radius)^2)^2 so that the simulation stays near the curve:
/// - rotational, co-normality [ST92]: half-way towards the neighbours' mean normal (the
///   co-circularity torque, each neighbour's normal mirrored in the plane orthogonal to r_ij,
///   flipped normals from a sharp start: docs/boolean.md);
/// - positional, co-circularity: along n_i + n_j until (n_i + n_j) . r_ij = 0;
/// - the linear repulsion of the particle engine (notes 2.3, eq. 2.2-2.3) within 1.5 spacings,
///   in the tangent plane, to keep the distribution even.
/// Pairs are weighted by (1 - |r_ij|^2 / support^2)^2. Two planes meeting at a line, with the
/// boundary held at distance R along each, relax towards the cylinder of the fillet tangent to
/// both there (cylinders and spheres satisfy co-circularity exactly). The pairs' crease flags
/// and second normals are all cleared: the result renders as one smooth surface. A knife edge (a
/// pair's normals more than 120 degrees apart, a surface leaving the other almost tangentially)
/// is held fixed with its A-side normal; when knife edges are more than half of the pairs the
/// cloud is left as it is (report.moved 0, knife_edges set): blending such a rim tears it. Neighbourhoods are rebuilt every 10 steps and join
/// only samples whose starting normals are less than 90 degrees apart, so the two sheets of an
/// obtuse crease or a thin part interact only through the pairs between them. Deterministic
/// whatever the thread count. A cloud without curve samples is left as it is (report.moved 0).
///
/// Throws Error(kInvalidArgument) for a non-finite or negative radius, or iterations outside
/// kMinBlendIterations..kMaxBlendIterations; Error(kCancelled) when `progress` asks to stop.
BlendReport BlendCreases(PointCloud& cloud, double radius, int iterations = kDefaultBlendIterations,
                         ProgressTracker* progress = nullptr);

}  // namespace surfel
