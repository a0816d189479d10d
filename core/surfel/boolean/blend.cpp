// Particle-based blending of a boolean result's creases (course notes, Pauly 3.1.4): oriented
// particles [Szeliski & Tonnesen 1992] with co-circularity potentials and the particle engine's
// repulsion, confined to a band around the intersection curve by a smooth fall-off.

#include "surfel/boolean/blend.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/boolean/boolean.h"
#include "surfel/resample/particle_engine.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/spatial/uniform_grid.h"

namespace surfel {
namespace {

ExtraAttribute* FindExtraMutable(PointCloud& cloud, const char* name) {
    for (ExtraAttribute& e : cloud.extras)
        if (e.name == name) return &e;
    return nullptr;
}

// Neighbours whose normals differ by more than this (cosine) do not interact.
constexpr float kMinPairCosine = 0.0f;

// The fall-off of 3.1.4: 1 on the curve, 0 at the blend radius, C1 at both ends.
double FallOff(double t) {
    if (t >= 1.0) return 0.0;
    const double s = 1.0 - t * t;
    return s * s;
}

}  // namespace

BlendReport BlendCreases(PointCloud& cloud, double radius, int iterations, ProgressTracker* progress) {
    CheckAtLeast("blend_radius", radius, 0.0);
    CheckRange("blend_iterations", iterations, kMinBlendIterations, kMaxBlendIterations);
    cloud.CheckConsistent();
    BlendReport report;
    report.iterations = iterations;
    ExtraAttribute* crease = FindExtraMutable(cloud, kCreaseAttribute);
    ExtraAttribute* cnx = FindExtraMutable(cloud, kCreaseNormalX);
    ExtraAttribute* cny = FindExtraMutable(cloud, kCreaseNormalY);
    ExtraAttribute* cnz = FindExtraMutable(cloud, kCreaseNormalZ);
    const std::size_t n = cloud.size();
    if (radius == 0.0 || n == 0 || !crease || !cloud.has_normals() || !cloud.has_radii()) return report;

    // The curve: every surfel pair. A pair's starting normal is the mean of its two.
    std::vector<Vec3f> curve;
    for (std::size_t i = 0; i < n; ++i)
        if (crease->values[i] != 0.0) curve.push_back(cloud.positions[i]);
    if (curve.empty()) return report;
    const KdTree curve_tree(curve);

    // Distance of every sample to the curve; the particles and the support from their spacing.
    std::vector<float> dist(n);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 4096), [&](const auto& range) {
        for (std::size_t i = range.begin(); i != range.end(); ++i)
            dist[i] = std::sqrt(curve_tree.Nearest(cloud.positions[i]).dist2);
    });
    std::vector<float> spacing;
    for (std::size_t i = 0; i < n; ++i)
        if (dist[i] < radius) spacing.push_back(cloud.radii[i]);
    if (spacing.empty()) return report;
    std::nth_element(spacing.begin(), spacing.begin() + static_cast<std::ptrdiff_t>(spacing.size() / 2),
                     spacing.end());
    const float eta = std::max(spacing[spacing.size() / 2], 1e-30f);
    const float support = 2.5f * eta, repulsion = 1.0f * eta;

    // A knife edge (a surfel pair whose normals differ by more than 120 degrees, where a surface
    // leaves the other almost tangentially) has no mean normal to start from, and its two sheets
    // lie within the support: it stays where it is, and the sheets beside it blend only within
    // themselves (pairs of normals over 90 degrees apart do not interact, below).
    std::vector<std::uint8_t> knife(n, 0);
    if (cnx && cny && cnz)
        for (std::size_t i = 0; i < n; ++i)
            if (crease->values[i] != 0.0) {
                const Vec3d other(cnx->values[i], cny->values[i], cnz->values[i]);
                knife[i] = cloud.normals[i].cast<double>().dot(other) < -0.5;
                report.knife_edges += knife[i];
            }
    // Mostly knife edges (a rim sharper than 60 degrees all round, as a bite out of a sphere):
    // blending such a rim tore the render (docs/boolean.md), so the result stays sharp and the
    // report says why (moved = 0). With a few knife edges among blendable pairs (the bunny - sphere:
    // 104 of 470) the pairs are held fixed and the rest blends.
    if (2 * report.knife_edges > curve.size()) return report;

    // The simulated set: particles first, then the fixed ring beyond the radius and the knife
    // edges.
    std::vector<std::uint32_t> index;
    std::vector<float> falloff;
    for (std::size_t i = 0; i < n; ++i)
        if (dist[i] < radius && !knife[i]) index.push_back(static_cast<std::uint32_t>(i));
    const std::size_t moving = index.size();
    for (std::size_t i = 0; i < n; ++i)
        if ((dist[i] >= radius && dist[i] < radius + support) || (knife[i] && dist[i] < radius))
            index.push_back(static_cast<std::uint32_t>(i));
    const std::size_t m = index.size();
    report.moved = moving;
    report.fixed = m - moving;

    std::vector<Vec3f> pos(m), nrm(m), start(moving);
    falloff.resize(moving);
    for (std::size_t k = 0; k < m; ++k) {
        const std::uint32_t i = index[k];
        pos[k] = cloud.positions[i];
        nrm[k] = cloud.normals[i];
        if (crease->values[i] != 0.0 && !knife[i] && cnx && cny && cnz) {
            const Vec3f mean = nrm[k] + Vec3f(static_cast<float>(cnx->values[i]), static_cast<float>(cny->values[i]),
                                              static_cast<float>(cnz->values[i]));
            if (mean.squaredNorm() > 1e-6f) nrm[k] = mean.normalized();
        }
        if (k < moving) {
            falloff[k] = static_cast<float>(FallOff(dist[i] / radius));
            start[k] = pos[k];
        }
    }

    // The neighbourhoods, rebuilt every kNeighbourRefresh steps and kept in between (notes 3.3:
    // the particles move little, so "the neighborhood relations typically remain constant for a
    // certain number of iterations"): every sample within the support whose STARTING normal
    // differs from the particle's starting normal by less than 90 degrees. Judging by the
    // starting normals keeps two sheets that meet at an obtuse crease from joining as their
    // normals turn (judged by the current normals, the denser sheet's normals took the other's
    // over on the bunny), and a thin part's two sides apart; the sheets of a crease interact
    // through its surfel pairs, whose mean normal is within 90 degrees of both.
    constexpr int kNeighbourRefresh = 10;
    const std::vector<Vec3f> start_normal(nrm);
    std::vector<std::uint32_t> first(moving + 1, 0), nbr;
    std::vector<std::vector<std::uint32_t>> lists(moving);
    const auto find_neighbours = [&] {
        const UniformGrid grid(pos, support);
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, moving, 256), [&](const auto& range) {
            for (std::size_t k = range.begin(); k != range.end(); ++k) {
                lists[k].clear();
                grid.ForEachWithin(pos[k], support, [&](std::uint32_t j, const Vec3f&, float d2) {
                    if (j != k && d2 > 0.0f && start_normal[j].dot(start_normal[k]) >= kMinPairCosine)
                        lists[k].push_back(j);
                });
            }
        });
        nbr.clear();
        for (std::size_t k = 0; k < moving; ++k) {
            first[k + 1] = first[k] + static_cast<std::uint32_t>(lists[k].size());
            nbr.insert(nbr.end(), lists[k].begin(), lists[k].end());
        }
    };

    std::vector<Vec3f> next_pos(pos), next_nrm(nrm);
    const double support2 = static_cast<double>(support) * support;
    for (int iter = 0; iter < iterations; ++iter) {
        if (progress) progress->Check();
        if (iter % kNeighbourRefresh == 0) find_neighbours();
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, moving, 256), [&](const auto& range) {
            for (std::size_t k = range.begin(); k != range.end(); ++k) {
                const Vec3f x = pos[k], nk = nrm[k];
                Vec3d mirrored = Vec3d::Zero(), circ = Vec3d::Zero(), push = Vec3d::Zero();
                double wsum = 0.0;
                for (std::uint32_t e = first[k]; e != first[k + 1]; ++e) {
                    const std::uint32_t j = nbr[e];
                    const Vec3d r = (pos[j] - x).cast<double>(), nj = nrm[j].cast<double>();
                    const double d2 = r.squaredNorm();
                    if (d2 >= support2 || d2 <= 0.0) continue;
                    const double w = (1.0 - d2 / support2) * (1.0 - d2 / support2);
                    const double len = std::sqrt(d2);
                    // Rotational, co-normality: towards the neighbours' normals.
                    mirrored += w * nj;
                    // Positional: along n_i + n_j onto (n_i + n_j) . r_ij = 0.
                    const Vec3d mij = nk.cast<double>() + nj;
                    const double mm = mij.squaredNorm();
                    if (mm > 1.0) circ += w * (mij.dot(r) / mm) * mij;
                    wsum += w;
                    // The particle engine's linear repulsion (eq. 2.2-2.3), directed in the
                    // tangent plane: two particles stacked along the normal (the two sides of a
                    // crease meeting) are pushed apart sideways, not off the surface.
                    if (len < repulsion) {
                        const Vec3d rt = r - r.dot(nk.cast<double>()) * nk.cast<double>();
                        const double lt = rt.norm();
                        if (lt > 1e-9 * len) push -= (repulsion - len) * rt / lt;
                    }
                }
                const double f = falloff[k];
                if (wsum <= 0.0 || f <= 0.0) {
                    next_pos[k] = x;
                    next_nrm[k] = nk;
                    continue;
                }
                const Vec3d n0 = nk.cast<double>();
                Vec3d target = mirrored / wsum;
                Vec3d nn = n0;
                if (target.squaredNorm() > 1e-12) nn = (n0 + 0.5 * f * (target.normalized() - n0)).normalized();
                // The engine's gain and step bound.
                Vec3d step = push * (ParticleEngine::kRepulsionGain / repulsion);
                const double sl = step.norm();
                if (sl > ParticleEngine::kMaxStep * repulsion) step *= ParticleEngine::kMaxStep * repulsion / sl;
                const Vec3d moved = x.cast<double>() + f * (0.5 * circ / wsum + step);
                next_pos[k] = moved.cast<float>();
                next_nrm[k] = nn.allFinite() ? nn.cast<float>() : nk;
            }
        });
        std::copy(next_pos.begin(), next_pos.begin() + static_cast<std::ptrdiff_t>(moving), pos.begin());
        std::copy(next_nrm.begin(), next_nrm.begin() + static_cast<std::ptrdiff_t>(moving), nrm.begin());
    }

    double sum = 0.0;
    for (std::size_t k = 0; k < moving; ++k) {
        const std::uint32_t i = index[k];
        const double d = (pos[k] - start[k]).cast<double>().norm();
        report.max_displacement = std::max(report.max_displacement, d);
        sum += d;
        cloud.positions[i] = pos[k];
        cloud.normals[i] = nrm[k];
    }
    report.mean_displacement = moving ? sum / static_cast<double>(moving) : 0.0;
    // Every surfel pair becomes an ordinary sample, the knife edges too (with their A-side
    // normal): a blended result renders as one smooth surface. Keeping the knife edges as creases
    // among cleared ones confused the crease-aware renderer (torn rims on the bunny).
    for (std::size_t i = 0; i < n; ++i)
        if (crease->values[i] != 0.0) {
            crease->values[i] = 0.0;
            if (cnx && cny && cnz) cnx->values[i] = cny->values[i] = cnz->values[i] = 0.0;
            ++report.creases_cleared;
        }
    return report;
}

}  // namespace surfel
