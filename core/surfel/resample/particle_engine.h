#pragma once
/// \file
/// The particle engine (course notes, Pauly 2.3, after Turk 1992) shared by particle
/// simplification and resampling: particles spread over the sampled surface by density, linear
/// repulsion within radius r on a dynamic grid, kept on the surface by projection onto the
/// tangent plane of the closest original point, and a final MLS projection.

#include <atomic>
#include <cstdint>
#include <memory>
#include <random>
#include <span>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/surface/local_analysis.h"

namespace surfel {

class KdTree;

namespace detail {

/// Portable uniform numbers from mt19937_64 (whose output sequence the standard fixes).
class Random {
public:
    explicit Random(std::uint64_t seed) : engine_(seed) {}
    double Uniform() { return static_cast<double>(engine_() >> 11) * (1.0 / 9007199254740992.0); }
    std::size_t Index(std::size_t n) { return static_cast<std::size_t>(Uniform() * static_cast<double>(n)) % n; }

private:
    std::mt19937_64 engine_;
};

}  // namespace detail

/// Neighbourhood size n of the surface variation sigma_n that the adaptive engine reads (the
/// k of EstimateNormals' default).
inline constexpr int kVariationNeighbors = 16;

/// The curvature measure of the adaptive particle engine (notes 2.3.4 with 1.2): the surface
/// variation sigma_n of each point's n = kVariationNeighbors neighbourhood (`variation`, as
/// EstimateNormals returns it) put at one scale for every point, sigma_n / r_n^2 (r_n the
/// distance to the n-th neighbour; on a smooth surface sigma_n grows with r_n^2, so a random
/// sampling's uneven r_n would otherwise make sigma_n noisy), then averaged over the point and its
/// n neighbours. Units 1 / length^2; only ratios matter. Needs variation.size() == tree.size() >= 2.
std::vector<double> CommonScaleVariation(const KdTree& tree, std::span<const float> variation);
/// The same from a table the caller has, `knn` = tree.KnnAll(K) with K >= min(kVariationNeighbors,
/// n - 1) (its first columns; the same result as above).
std::vector<double> CommonScaleVariation(const KnnTable& knn, std::span<const float> variation);

/// The force constant of eq. 2.2 as a step (ParticleParams::gain), unless a caller sets another.
inline constexpr double kDefaultParticleGain = 0.3;

/// One run of the particle engine.
struct ParticleParams {
    std::size_t count = 0;    ///< m, the particles that move (>= 1).
    std::uint64_t seed = 1;   ///< Seeds the spreading (2.3.1) and its tangential jitter.
    int iterations = 40;      ///< Relaxation steps (2.3.2-2.3.3), >= 0.
    /// The force constant k of eq. 2.2 as a step: a lone neighbour at distance d < r moves a
    /// particle by gain (r - d). In (0, 1).
    /// Resampling uses 0.5, which reaches at 20 steps the evenness 0.3 reaches at 40 (and 0.8
    /// oscillates: NN CV 0.127 at 15 steps on the bunny x4; bench/results-resample.md).
    double gain = kDefaultParticleGain;
    /// The input samples act as particles that repel but never move (keep-input resampling):
    /// the repulsion radius is then that of count + input size particles.
    bool fixed_input = false;
    /// Initial placement (2.3.1). kJitter: each particle at its sample, jittered within r0 / 4 in
    /// the tangent plane. kDisk: the particles a sample receives split its tangent disk of the
    /// sample's area on a Vogel spiral (the splitting of notes 3.2.2 done at once), so that the
    /// start is already nearly even and fewer relaxation steps reach the same spacing.
    enum class Spread { kJitter, kDisk } spread = Spread::kJitter;
    /// Stop relaxing once the mean step of a relaxation step falls below this fraction of the
    /// repulsion radius (0 = always run `iterations`). The mean is summed in particle order, so
    /// the stopping step does not depend on the thread count.
    double tolerance = 0.0;
    /// Final projection by cached local fits: the MLS fit (MlsSurface::Fit) at each original
    /// point that is some particle's closest, every particle moved onto its closest point's
    /// polynomial. false: every particle's own MLS projection (notes 2.3.3).
    bool cached_fits = false;
};

/// What one Run did.
struct ParticleStats {
    int iterations = 0;           ///< Relaxation steps run (<= params.iterations).
    int neighbor_rebuilds = 0;    ///< Verlet neighbour lists built.
    double last_mean_step = 0.0;  ///< Mean step of the last relaxation step / r0.
};

/// A particle simulation prepared over one input cloud: its kd-tree, sampling density
/// (notes 1.1.1, k = 6) and per-sample spreading weights. Run() may be called many times.
class ParticleEngine {
public:
    /// The linear repulsion's step (eq. 2.2-2.3): a lone neighbour at distance d < r moves a
    /// particle by kRepulsionGain (r - d), and no step is longer than kMaxStep r. Shared with
    /// the blending of boolean creases (core/surfel/boolean/blend.cpp).
    static constexpr double kRepulsionGain = kDefaultParticleGain;
    static constexpr double kMaxStep = 0.5;

    /// `normals`: one oriented unit normal per input point. `variation`: sigma_n per point of its
    /// kVariationNeighbors-neighbourhood (notes 1.2), used when `adaptive` (2.3.4: repulsion
    /// radius scaled by 1 / sigma relative to the median, clamped to [1/2, 2], with sigma the
    /// CommonScaleVariation of `variation`); may be empty otherwise. Needs at least 2 points.
    ParticleEngine(const PointCloud& input, std::span<const Vec3f> normals, std::span<const float> variation,
                   bool adaptive);

    /// What a caller that has already analysed the input can share with the engine.
    struct Shared {
        /// A kd-tree over input.positions, used instead of building one; must outlive the engine.
        const KdTree* tree = nullptr;
        /// tree->KnnAll(K) with K >= min(8, n - 1): the engine's walk graph (its first 8 columns),
        /// sampling density (the 6th) and, with K >= min(kVariationNeighbors, n - 1), the
        /// adaptive variation, instead of three more neighbour searches. Needs `tree`.
        const KnnTable* knn = nullptr;
        /// With empty `normals`: each input point's unoriented normal is estimated when the
        /// simulation first needs its tangent plane (EstimateNormalAt with these options: the
        /// same normal EstimateNormals gives it, bit for bit), so a simplification to a few
        /// particles analyses only the input points they visit. Needs `tree`.
        NormalOptions lazy_normals;
    };
    /// As above, with what `shared` provides; `normals` may be empty (see Shared::lazy_normals),
    /// unless `adaptive`, which needs `variation` (of every point) anyway.
    ParticleEngine(const PointCloud& input, std::span<const Vec3f> normals,
                   std::span<const float> variation, bool adaptive, const Shared& shared);
    ~ParticleEngine();
    ParticleEngine(const ParticleEngine&) = delete;
    ParticleEngine& operator=(const ParticleEngine&) = delete;

    /// Sum over the input of area / scale^2 (model units squared): the sampled surface's area
    /// for the uniform engine (each sample stands for 1 / rho, capped at 4x the median).
    double WeightedArea() const { return total_; }

    /// Runs the simulation: `positions` and `normals` (MLS normals, oriented like the closest
    /// input normal) of params.count particles. Deterministic for a seed, whatever the thread
    /// count (Jacobi updates). Advances `progress` by 1 in all.
    void Run(const ParticleParams& params, std::vector<Vec3f>& positions, std::vector<Vec3f>& normals,
             ProgressTracker& progress, ParticleStats* stats = nullptr) const;

    /// Relaxation filter of dynamic sampling (notes 3.2.3): `iterations` Jacobi steps of the
    /// linear repulsion (eq. 2.2-2.3, as in Run) among `positions` within `radius` (model units,
    /// > 0), each move put back onto the tangent plane of the closest input point and within its
    /// reach. Deterministic whatever the thread count. With `movable`, only the positions it
    /// flags move (the others still push): the local relaxation of a split round. With
    /// `rim_outward` (one unit vector per input point, zero except at the input's rims), a move
    /// whose closest input point is a rim sample keeps no component along its outward direction
    /// beyond it: the samples stay on the sampled side of the rim instead of drifting up to the
    /// reach past it.
    void Relax(std::vector<Vec3f>& positions, double radius, int iterations,
               const std::vector<std::uint8_t>* movable = nullptr,
               std::span<const Vec3f> rim_outward = {}) const;

    /// The kd-tree over the input positions.
    const KdTree& tree() const { return *tree_; }

    /// The unit normal of input point i (the given one, or its lazy estimate). Thread-safe.
    const Vec3f& Normal(std::uint32_t i) const;

  private:
    // Row i of the input's kWalkNeighbors-nearest-neighbour graph (UINT32_MAX padding); computed
    // on first use when no table was given. Thread-safe; `buffer` holds a row another thread is
    // still writing.
    std::span<const std::uint32_t> GraphRow(std::uint32_t i,
                                            std::vector<std::uint32_t>& buffer) const;
    // A moved particle back onto the sampled surface (2.3.3): the tangent plane of the closest
    // original point, within that point's reach.
    // With `rim_outward` (see Relax), not past a rim sample of the input.
    Vec3f OntoSurface(Vec3f moved, std::span<const Vec3f> rim_outward = {}) const;
    // The same with the closest original point found by WalkNearest from `home`, which it updates.
    Vec3f OntoSurface(Vec3f moved, std::uint32_t& home) const;
    // The input point closest to x by a greedy walk over the input's k-nearest-neighbour graph
    // from `start` (a particle moves a fraction of the spacing per step, so its closest sample
    // is its last one or a neighbour of it); ties go to the lower index.
    // `margin` (optional): how much nearer than the result its nearest graph neighbour is not
    // (less a rounding allowance), so that a walk from the result to any point within margin / 2
    // of x ends where it starts.
    std::uint32_t WalkNearest(const Vec3f& x, std::uint32_t start, float* margin = nullptr) const;
    // `moved` onto the tangent plane of input point q, within q's reach (the second half of
    // OntoSurface).
    Vec3f OntoPlane(Vec3f moved, std::uint32_t q) const;

    const PointCloud& input_;
    std::span<const Vec3f> normals_;
    std::unique_ptr<KdTree> own_tree_;
    const KdTree* tree_ = nullptr;
    std::vector<float> reach_radius_;  // r_i of the sampling density (distance to the 6th neighbour)
    std::vector<double> scale_;        // repulsion radius scale per input point
    std::vector<double> weight_;       // area / scale^2 per input point
    std::vector<double> area_;         // the (capped) area 1 / rho each input point stands for
    // The input's k-nearest-neighbour graph, for WalkNearest: rows of a shared table (stride
    // graph_stride_), of its own KnnAll, or filled on first use (graph_state_: 0 empty,
    // 1 being written, 2 ready).
    const KnnTable* shared_knn_ = nullptr;
    mutable KnnTable graph_;
    int graph_k_ = 0;
    mutable std::unique_ptr<std::atomic<std::uint8_t>[]> graph_state_;
    // Lazily estimated normals (empty when given), with the same three states.
    NormalOptions lazy_options_;
    mutable std::vector<Vec3f> lazy_normals_;
    mutable std::unique_ptr<std::atomic<std::uint8_t>[]> normal_state_;
    double total_ = 0.0;
    float median_radius_ = 0.0f;
    float mls_h_ =
        0.0f;  // the final MLS projection's h (MlsSurface's default, from the density above)
};

}  // namespace surfel
