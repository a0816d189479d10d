#pragma once
/// \file
/// Rendering booleans of point-sampled solids (course notes, Pauly 3.1.3) with the renderer's
/// layers (surface_layers.h):
/// - RenderCsg ray-traces op(A, B) with no resampling: both Adamson-Alexa surfaces in one scene, a
///   hit on A counting only where Omega_B keeps it by Table 3.1 (and vice versa), the normals of
///   a subtracted solid turned over, for shadow rays as for primary rays.
/// - RenderWithCreases renders a boolean result with surfel pairs (Boolean()'s output) as two
///   one-sided surfaces that clip each other at the pairs: the ray-tracing counterpart of the
///   notes' mutual surfel clipping, so the crease stays sharp instead of the surface rounding it.

#include <cstdint>

#include "surfel/boolean/boolean.h"
#include "surfel/render/renderer.h"

namespace surfel {

/// What a CSG render classified (the coherence spheres of 3.1.1 at work on ray hits).
struct CsgRenderReport {
    std::uint64_t classifications = 0;  ///< Omega queries asked for (one per converged hit).
    std::uint64_t queries_saved = 0;    ///< Answered by a coherence sphere, without a search.
    bool normals_estimated_a = false, normals_estimated_b = false;
};

struct CsgRenderResult {
    RenderResult render;
    CsgRenderReport report;
};

/// Ray-traces the boolean `op` of the solids bounded by `a` and `b` (b placed by
/// boolean.transform). The classification is Boolean()'s (SolidClassifier with boolean's mls,
/// normals, coincident_tolerance, max_open_area; coherence spheres per tile when
/// boolean.coherence), so the same options give the boundary `surfel boolean` samples. Image,
/// channels and determinism as Render(); N is the outward normal of the result. Throws
/// Error(kInvalidArgument) for bad render options (RenderOptions::Validate), bad boolean options
/// (BooleanOptions::Validate: "transform.scale: ..."), and inputs Boolean() refuses ("a: ...",
/// "b: ..."); Error(kCancelled) when `progress` asks to stop.
CsgRenderResult RenderCsg(const PointCloud& a, const PointCloud& b, BooleanOp op, const RenderOptions& render,
                          const BooleanOptions& boolean = {}, const ProgressFn& progress = {});

/// Whether `cloud` carries surfel pairs: the extras of a boolean result (kCreaseAttribute,
/// kSourceAttribute, kCreaseNormal{X,Y,Z}) with at least one sample of crease = 1.
bool HasSurfelPairs(const PointCloud& cloud);

/// Renders a boolean result with sharp creases. Layer A' = the samples of source 0 and the curve
/// samples with their A-side normals, layer B' = source 1 and the curve samples with their B-side
/// normals, each its own surface. A hit on A' within 3 spacings of its nearest curve sample q
/// counts only on the side of the partner plane (q, n_B(q)) where A's kept samples lie (behind
/// it at a convex crease, in front at a concave one), and vice versa. Called by Render() for such
/// a cloud when options.creases is set; the cloud needs no other attribute than Boolean()'s.
RenderResult RenderWithCreases(const PointCloud& cloud, const RenderOptions& options,
                               const ProgressFn& progress = {});

}  // namespace surfel
