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

/// Normal estimation options.
struct NormalOptions {
    int k = 16;                ///< Neighbours per point for the covariance (notes 1.2).
    bool weighted = false;     ///< Gaussian-weighted covariance theta(d) = exp(-d^2/h^2) instead of plain PCA.
    float h = 0.0f;            ///< Scale for the weighted variant; 0 = the k-th neighbour distance / 2 per point.
    /// Refine the PCA normal with the gradient at p of a quadratic height field fitted over the PCA
    /// plane (MLS-style, notes 1.3): removes the tilt that curvature and uneven neighbourhoods
    /// give plain PCA (on a torus sampled with 20k points: max error 6.0 -> under 2 degrees).
    bool refine = true;
    bool orient = true;        ///< Orient consistently with OrientNormals.
    int orient_k = 10;         ///< Neighbours in the graph the orientation propagates over.
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
NormalResult EstimateNormals(const KdTree& tree, const NormalOptions& options = {}, const ProgressFn& progress = {});

/// Consistent orientation (notes 1.2, after Hoppe et al. 1992): a minimum spanning tree of the
/// symmetric k-neighbour graph with edge cost 1 - |n_i . n_j| per connected component; each tree
/// starts at the component's point of largest z, whose normal is turned away from the
/// component's centroid, and every other normal is flipped to agree with its tree parent.
/// Returns the number of components; `flipped` receives how many normals were flipped.
std::size_t OrientNormals(const KdTree& tree, std::vector<Vec3f>& normals, int k = 10, std::size_t* flipped = nullptr,
                          const ProgressFn& progress = {});

/// Normal variation (notes 1.2): lambda'_1 of the covariance of the neighbours' normals.
std::vector<float> NormalVariation(const KdTree& tree, std::span<const Vec3f> normals, int k = 16);

}  // namespace surfel
