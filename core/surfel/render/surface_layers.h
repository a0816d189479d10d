#pragma once
/// \file
/// The renderer's multi-surface seam: several Adamson-Alexa surfaces in one Embree scene (one
/// user geometry each), each with its own hit filter and normal orientation. The CSG render and
/// the crease-aware render of a boolean result (csg_render.h) are built on it; Render() is the
/// one-layer case.

#include <functional>
#include <span>

#include "surfel/render/renderer.h"

namespace surfel {

/// One surface of a layered render.
struct SurfaceLayer {
    /// The surface (kept by reference during the call; its cloud gives the colours).
    const AaSurface* surface = nullptr;
    /// Which converged hits of this surface count, with the semantics of HitFilter (called with
    /// the hit's normal already flipped when flip_normals is set); empty = every hit. The
    /// render's RenderOptions::hit_filter applies on top.
    HitFilter keep;
    /// Turn the surface's normals over (a subtracted solid: its inside becomes the outside).
    bool flip_normals = false;
    /// Called on the rendering thread before each tile, so that a filter's thread-local cache
    /// can restart per tile: the image then does not depend on which thread renders which tile.
    std::function<void()> on_tile;
};

/// Renders the layers as one scene: a ray's hit is the nearest accepted hit over all layers
/// (primary and shadow rays alike). Calls options.Validate() (options.surface is ignored: the
/// surfaces are built). Stats: setup_ms is the BVH build; h and precision are layer 0's.
/// Otherwise as Render().
RenderResult RenderLayers(std::span<const SurfaceLayer> layers, const RenderOptions& options,
                          const ProgressFn& progress = {});

}  // namespace surfel
