#include "surfel/render/csg_render.h"

#include <tbb/enumerable_thread_specific.h>

#include <atomic>
#include <cmath>

#include "surfel/base/error.h"
#include "surfel/boolean/classifier.h"
#include "surfel/render/surface_layers.h"
#include "surfel/spatial/kd_tree.h"

namespace surfel {

// ---- The CSG render ---------------------------------------------------------------------------

CsgRenderResult RenderCsg(const PointCloud& a, const PointCloud& b, BooleanOp op, const RenderOptions& render,
                          const BooleanOptions& boolean, const ProgressFn& progress) {
    render.Validate();
    boolean.Validate();
    Stopwatch watch;
    // Omega of each solid, as Boolean() classifies; the surfaces over the placed samples.
    const SolidClassifier omega_a(a, boolean, false, "a"), omega_b(b, boolean, true, "b");
    const PointCloud world_a = omega_a.WorldCloud(), world_b = omega_b.WorldCloud();
    const AaSurface surface_a(world_a, render.surface), surface_b(world_b, render.surface);
    const double surface_ms = watch.ElapsedMs();

    // A subtracted solid's normals turn over (which hits count is Table 3.1).
    const bool flip_a = op == BooleanOp::kReverseDifference, flip_b = op == BooleanOp::kDifference;
    tbb::enumerable_thread_specific<CoherenceCache> cache_a, cache_b;  // queries against A, B
    std::atomic<std::uint64_t> queries{0}, saved{0};
    // A hit of one solid counts where the other's Omega keeps it; the query's outward normal is
    // the solid's own (the hit's normal before the flip).
    auto keep = [&](const SolidClassifier& other, tbb::enumerable_thread_specific<CoherenceCache>& caches, bool of_a,
                    bool flipped) {
        return [&, of_a, flipped](const AaHit& hit) {
            const Vec3f x = hit.position.cast<float>();
            const Vec3f n = (flipped ? -hit.normal : hit.normal).cast<float>();
            ++queries;
            CoherenceCache& cache = caches.local();
            std::optional<SolidAnswer> answer;
            if (boolean.coherence) answer = cache.Find(x);
            if (answer) {
                ++saved;
            } else {
                answer = other.Classify(x, n);
                if (boolean.coherence) cache.Add(x, *answer);
            }
            return TableKeeps(answer->side, of_a, op);
        };
    };
    const SurfaceLayer layers[2] = {
        {&surface_a, keep(omega_b, cache_b, true, flip_a), flip_a, [&] { cache_b.local().Clear(); }},
        {&surface_b, keep(omega_a, cache_a, false, flip_b), flip_b, [&] { cache_a.local().Clear(); }},
    };
    CsgRenderResult result;
    result.render = RenderLayers(layers, render, progress);
    result.render.stats.setup_ms += surface_ms;
    result.render.stats.time_ms += surface_ms;
    result.report.classifications = queries;
    result.report.queries_saved = saved;
    result.report.normals_estimated_a = omega_a.normals_estimated();
    result.report.normals_estimated_b = omega_b.normals_estimated();
    return result;
}

// ---- Crease-aware rendering of a boolean result ------------------------------------------------

namespace {

const ExtraAttribute* Extra(const PointCloud& cloud, const char* name) { return cloud.FindExtra(name); }

// A hit within kClipReach spacings of a surfel pair is clipped by the partner's plane.
constexpr float kClipReach = 3.0f;

// The surfel pairs: curve sample j at q[j] with the A-side normal na[j], the B-side normal nb[j],
// its spacing eta[j] and the crease's kind: side[j] = -1 where each side's kept samples lie behind
// the partner's plane (a convex crease: intersection, differences), +1 in front (concave: union).
struct Pairs {
    std::vector<Vec3f> q, na, nb;
    std::vector<float> eta, side;
};

}  // namespace

bool HasSurfelPairs(const PointCloud& cloud) {
    const ExtraAttribute* crease = Extra(cloud, kCreaseAttribute);
    if (!crease || !Extra(cloud, kSourceAttribute) || !Extra(cloud, kCreaseNormalX) ||
        !Extra(cloud, kCreaseNormalY) || !Extra(cloud, kCreaseNormalZ) || !cloud.has_normals())
        return false;
    for (double c : crease->values)
        if (c == 1.0) return true;
    return false;
}

RenderResult RenderWithCreases(const PointCloud& cloud, const RenderOptions& options, const ProgressFn& progress) {
    options.Validate();
    if (!HasSurfelPairs(cloud))
        throw Error(ErrorCode::kInvalidArgument, "cloud: has no surfel pairs (a boolean result's crease attributes)");
    Stopwatch watch;
    const ExtraAttribute& source = *Extra(cloud, kSourceAttribute);
    const ExtraAttribute &cx = *Extra(cloud, kCreaseNormalX), &cy = *Extra(cloud, kCreaseNormalY),
                         &cz = *Extra(cloud, kCreaseNormalZ);
    // The two one-sided clouds and the pairs.
    PointCloud side_a, side_b;
    Pairs pairs;
    auto add = [&](PointCloud& to, std::size_t i, const Vec3f& n) {
        to.positions.push_back(cloud.positions[i]);
        to.normals.push_back(n);
        if (cloud.has_radii()) to.radii.push_back(cloud.radii[i]);
        if (cloud.has_colors()) to.colors.push_back(cloud.colors[i]);
    };
    for (std::size_t i = 0; i < cloud.size(); ++i) {
        const int s = static_cast<int>(source.values[i]);
        if (s == 0) {
            add(side_a, i, cloud.normals[i]);
        } else if (s == 1) {
            add(side_b, i, cloud.normals[i]);
        } else {
            const Vec3f nb = Vec3d(cx.values[i], cy.values[i], cz.values[i]).cast<float>().normalized();
            add(side_a, i, cloud.normals[i]);
            add(side_b, i, nb);
            pairs.q.push_back(cloud.positions[i]);
            pairs.na.push_back(cloud.normals[i]);
            pairs.nb.push_back(nb);
        }
    }
    const KdTree tree_a(side_a.positions), tree_b(side_b.positions), tree_q(pairs.q);
    // Each pair's spacing (to its nearest curve neighbour) and the side of the partner plane its
    // own kept samples lie on, from the mean offset of the nearby samples of each side.
    const std::size_t m = pairs.q.size();
    pairs.eta.resize(m);
    pairs.side.resize(m);
    std::vector<Neighbor> nb;
    for (std::size_t j = 0; j < m; ++j) {
        tree_q.Knn(pairs.q[j], 2, &nb);
        float eta = nb.size() > 1 ? std::sqrt(nb[1].dist2) : 0.0f;
        tree_a.Knn(pairs.q[j], 8, &nb);
        if (!nb.empty()) eta = std::max(eta, std::sqrt(nb[std::min<std::size_t>(1, nb.size() - 1)].dist2));
        pairs.eta[j] = eta;
        double lean = 0;  // > 0: the kept samples lie in front of the partner planes
        for (const Neighbor& n : nb) lean += (side_a.positions[n.index] - pairs.q[j]).dot(pairs.nb[j]);
        tree_b.Knn(pairs.q[j], 8, &nb);
        for (const Neighbor& n : nb) lean += (side_b.positions[n.index] - pairs.q[j]).dot(pairs.na[j]);
        pairs.side[j] = lean > 0 ? 1.0f : -1.0f;
    }
    const AaSurface surface_a(side_a, options.surface), surface_b(side_b, options.surface);
    const double surface_ms = watch.ElapsedMs();

    // A hit of one side near a pair counts on its own side of the partner's plane.
    auto clip = [&](bool of_a) {
        return [&, of_a](const AaHit& hit) {
            const Vec3f x = hit.position.cast<float>();
            const Neighbor n = tree_q.Nearest(x);
            const std::uint32_t j = n.index;
            if (n.dist2 > kClipReach * kClipReach * pairs.eta[j] * pairs.eta[j]) return true;
            const Vec3f& partner = of_a ? pairs.nb[j] : pairs.na[j];
            return pairs.side[j] * (x - pairs.q[j]).dot(partner) >= 0.0f;
        };
    };
    const SurfaceLayer layers[2] = {{&surface_a, clip(true), false, {}}, {&surface_b, clip(false), false, {}}};
    RenderResult result = RenderLayers(layers, options, progress);
    result.stats.setup_ms += surface_ms;
    result.stats.time_ms += surface_ms;
    return result;
}

}  // namespace surfel
