#pragma once
/// \file
/// Local surface analysis (course notes, Pauly, chapter 1): sampling density and spacing,
/// covariance analysis, normals, surface variation, and consistent normal orientation.

#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/spatial/kd_tree.h"

namespace surfel {

/// Sampling density (notes 1.1.1): r_i is the radius of the smallest sphere around p_i holding
/// its k nearest neighbours, rho_i = k / (pi r_i^2) and the spacing eta_i = 1 / sqrt(rho_i).
struct SamplingDensity {
    std::vector<float> radius;   ///< r_i (distance to the k-th neighbour)
    std::vector<float> density;  ///< rho_i, samples per unit area
    std::vector<float> spacing;  ///< eta_i, a typical distance between samples
    float median_spacing = 0.0f;
};

/// Computes SamplingDensity with the k nearest neighbours (default 6, as Adamson & Alexa); k is
/// clamped to size() - 1. The k-th distances come from KthNeighborDistances (a fine grid, the
/// tree where the grid does not suit the cloud).
SamplingDensity ComputeSamplingDensity(const KdTree& tree, int k = 6, const ProgressFn& progress = {});
/// The same from the positions alone, for callers that need no kd-tree.
SamplingDensity ComputeSamplingDensity(std::span<const Vec3f> points, int k = 6);

/// The spacing eta = 1 / sqrt(rho), rho = k / (pi r^2) (notes 1.1.1), of a sample whose k-th
/// nearest other sample lies at distance r: the side of the area 1 / rho the sample stands for.
float SpacingFromRadius(float r, int k);

/// The median of the spacing eta over at most `max_samples` points (an even stride through the
/// cloud; all of them when it is smaller): what DefaultScale needs, without a density per point.
float MedianSpacing(const KdTree& tree, int k = 6, std::size_t max_samples = 20000);
/// The same median from a density already computed with the same k (its eta at the same strided
/// points): equal to MedianSpacing(tree, k, max_samples) for the tree the density came from.
float MedianSpacing(const SamplingDensity& density, std::size_t max_samples = 20000);

/// The default MLS / surface scale h of a cloud: 2 x the median sample spacing (eta). With the
/// Gaussian theta(d) = exp(-d^2/h^2) about 4*pi samples carry most weight, enough for a stable
/// plane and quadratic fit on well-sampled scans while keeping features of about 2 spacings.
float DefaultScale(const SamplingDensity& density);
/// Convenience: builds what it needs from the positions.
float DefaultScale(const KdTree& tree);

/// Result of covariance analysis of one neighbourhood (notes 1.2, eq. 1.1).
struct CovarianceFrame {
    Vec3d centroid;
    Vec3d normal;       ///< v0, eigenvector of the smallest eigenvalue (unoriented)
    Vec3d eigenvalues;  ///< lambda_0 <= lambda_1 <= lambda_2
    /// sigma_n = lambda_0 / (lambda_0 + lambda_1 + lambda_2): 0 on a plane, 1/3 isotropic.
    double SurfaceVariation() const {
        const double s = eigenvalues.sum();
        return s > 0 ? eigenvalues[0] / s : 0.0;
    }
};

/// Covariance analysis of the points `indices` (optionally weighted).
CovarianceFrame AnalyzeNeighborhood(std::span<const Vec3f> points, std::span<const std::uint32_t> indices,
                                    std::span<const float> weights = {});

/// Limits of NormalOptions, written once here; the CLI and the docs read them.
/// Range of `k`: a covariance plane needs 3 points; 1000 neighbours is far past any scan's need.
inline constexpr int kMinNormalNeighbors = 3;
inline constexpr int kMaxNormalNeighbors = 1000;
/// Range of `orient_k`, the neighbours per point in the orientation graph.
inline constexpr int kMinOrientNeighbors = 1;
inline constexpr int kMaxOrientNeighbors = 1000;
/// Largest `orient_crossing_weight` (the tilt it weighs lies in 0..1, the plain cost in 0..1).
inline constexpr double kMaxOrientCrossingWeight = 100.0;

/// Normal estimation options.
struct NormalOptions {
    /// Neighbours per point for the covariance (notes 1.2), kMinNormalNeighbors..kMaxNormalNeighbors;
    /// EstimateNormals clamps it to size() - 1.
    int k = 16;
    bool weighted = false;     ///< Gaussian-weighted covariance theta(d) = exp(-d^2/h^2) instead of plain PCA.
    /// Scale for the weighted variant, model units, >= 0; 0 = the k-th neighbour distance / 2 per point.
    float h = 0.0f;
    /// Refine the PCA normal with the gradient at p of a quadratic height field fitted over the PCA
    /// plane (MLS-style, notes 1.3): removes the tilt that curvature and uneven neighbourhoods
    /// give plain PCA (on a torus sampled with 20k points: max error 6.0 -> under 2 degrees).
    bool refine = true;
    bool orient = true;        ///< Orient consistently with OrientNormals.
    /// Neighbours per point in the graph the orientation propagates over,
    /// kMinOrientNeighbors..kMaxOrientNeighbors (clamped to size() - 1).
    int orient_k = 10;
    /// w in the orientation's edge cost 1 - |n_i . n_j| + w (|e . n_i| + |e . n_j|) / 2, e the unit
    /// edge direction, 0..kMaxOrientCrossingWeight; 0 = Hoppe's cost alone. See OrientNormals.
    float orient_crossing_weight = 1.0f;

    /// Throws Error(kInvalidArgument, "<field>: <what>") for the first bad field: "k", "h",
    /// "orient_k", "orient_crossing_weight" (e.g. "k: must lie in 3..1000, got 1").
    void Validate() const;
};

/// What EstimateNormals computed.
struct NormalResult {
    std::vector<Vec3f> normals;             ///< Unit normals, oriented if options.orient.
    std::vector<float> surface_variation;   ///< sigma_n per point.
    std::size_t components = 0;             ///< Connected components of the orientation graph.
    std::size_t flipped = 0;                ///< Normals the orientation flipped.
};

/// Estimates a normal per point by covariance analysis of its k nearest neighbours and, by
/// default, orients them consistently. Parallel; the result does not depend on the thread count.
/// Calls options.Validate() first; needs at least 3 points.
NormalResult EstimateNormals(const KdTree& tree, const NormalOptions& options = {}, const ProgressFn& progress = {});
/// The same over neighbours the caller already has: `knn` = tree.KnnAll(K) for some K (rows
/// nearest first); its first min(options.k, K) columns are the covariance neighbourhoods, the
/// same result as EstimateNormals(tree, options) when K >= options.k.
NormalResult EstimateNormals(const KdTree& tree, const KnnTable& knn, const NormalOptions& options,
                             const ProgressFn& progress = {});

/// Reusable buffers of NormalAt / EstimateNormalAt (one per thread).
struct NormalScratch {
    std::vector<std::uint32_t> indices, row;
    std::vector<float> weights, dist2;
    std::vector<Neighbor> neighbors;
};

/// The unoriented normal EstimateNormals gives point i of `pts` from its neighbours `row`
/// (nearest first, UINT32_MAX padding allowed) at squared distances `dist2`: covariance analysis
/// (notes 1.2) and, with options.refine and at least 6 neighbours, the quadratic refinement.
/// `variation` (optional) receives sigma_n. options.k is not read (the row's length is k).
Vec3f NormalAt(std::span<const Vec3f> pts, std::size_t i, std::span<const std::uint32_t> row,
               std::span<const float> dist2, const NormalOptions& options, NormalScratch& scratch,
               float* variation = nullptr);
/// The unoriented normal of the tree's point i alone, bit for bit the one EstimateNormals(tree,
/// options) gives it before orientation (the same k = min(options.k, size() - 1) neighbours, the
/// same arithmetic): for callers that need the tangent planes of a few points of a large cloud.
/// Needs size() >= 3; options are not validated here.
Vec3f EstimateNormalAt(const KdTree& tree, std::size_t i, const NormalOptions& options,
                       NormalScratch& scratch, float* variation = nullptr);

/// Consistent orientation (notes 1.2, after Hoppe et al. 1992), outward on closed surfaces.
///
/// Propagation: per connected component of the symmetric options.orient_k-neighbour graph, a
/// minimum spanning tree (Prim's, from the component's point of largest z; ties by index, so
/// thread-count independent; where the least tree is unique, or its ties change no sign, Kruskal's
/// over the edges sorted in parallel gives the same normals), and every normal flipped to agree
/// with its tree parent. The edge
/// cost is Hoppe's 1 - |n_i . n_j| plus options.orient_crossing_weight times the edge's mean tilt
/// out of the two tangent planes, (|e . n_i| + |e . n_j|) / 2: where a thin part (a fin, a
/// hand, a sleeve) is thinner than the neighbourhood, an edge across it joins two antiparallel
/// normals, the plain cost rates it best, and the whole subtree behind it comes out inverted.
/// On the shared scans this takes the buddha from 40.2 % to 99.4 % outward, Lucy from 98.1 % to
/// 99.1 % (tests/unit/surface/test_normals.cpp).
///
/// Seed: the notes and Hoppe turn the extremal point's normal "away from the centroid", CGAL's
/// mst_orient_normals makes the normal at the highest point point up. Both trust one normal, and
/// the one at an extremal point is the least reliable (the tip of an ear or of a noise spike: it
/// lies nearly in the tangent plane, its sign whatever propagated through the feature; the
/// horse came out 99.9 % inward). Instead, once a component is consistent, its extremal points in
/// 26 directions d (the cube's faces, edges and corners) vote: on a closed surface the outward
/// normal there is d, and each direction votes with the mean n . d of its 8 most extremal
/// points. A component whose vote is negative is turned over. A flat sheet, whose votes along d
/// and -d cancel (under 0.05 per direction), keeps CGAL's rule: the highest point's normal up.
///
/// Returns the number of components; `flipped` receives how many normals end opposite to their
/// input. Calls options.Validate() first (only orient_k and orient_crossing_weight are used).
std::size_t OrientNormals(const KdTree& tree, std::vector<Vec3f>& normals, const NormalOptions& options = {},
                          std::size_t* flipped = nullptr, const ProgressFn& progress = {});
/// The same over neighbours the caller already has: `knn` = KdTree(points).KnnAll(K) (rows nearest
/// first, ties by index) with K >= min(options.orient_k, size() - 1); the graph is its first
/// min(options.orient_k, size() - 1) columns, the rows KnnAll(orient_k) gives, so the same
/// normals, flips and components as OrientNormals(tree, normals, options). For callers that also
/// need the neighbours for something else (one search instead of two). `knn` may be empty for
/// fewer than 2 points.
std::size_t OrientNormals(std::span<const Vec3f> points, const KnnTable& knn, std::vector<Vec3f>& normals,
                          const NormalOptions& options = {}, std::size_t* flipped = nullptr,
                          const ProgressFn& progress = {});

namespace detail {
/// How OrientNormals builds its minimum spanning trees. kAuto: Kruskal's over the edges sorted in
/// parallel wherever that gives the normals of Prim's trees (finite costs, and a unique least forest
/// or ties that change no sign), Prim's otherwise; kPrim: Prim's always. Both give the same
/// normals; for tests.
enum class SpanningTrees { kAuto, kPrim };
/// OrientNormals with the method chosen; `by_kruskal` (optional) says whether Kruskal's gave the trees.
std::size_t OrientNormals(const KdTree& tree, std::vector<Vec3f>& normals, const NormalOptions& options,
                          SpanningTrees method, std::size_t* flipped = nullptr, bool* by_kruskal = nullptr);
}  // namespace detail

/// Normal variation (notes 1.2): lambda'_1 of the covariance of the neighbours' normals.
std::vector<float> NormalVariation(const KdTree& tree, std::span<const Vec3f> normals, int k = 16);

}  // namespace surfel
