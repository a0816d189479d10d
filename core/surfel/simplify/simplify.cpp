#include "surfel/simplify/simplify.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_group.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <limits>
#include <numbers>
#include <numeric>
#include <optional>
#include <string>

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/simplify/cluster_sums.h"
#include "surfel/simplify/simplify_internal.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/spatial/neighbor_radii.h"
#include "surfel/spatial/uniform_grid.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/poly_fit.h"

namespace surfel {

const char* SimplifyMethodName(SimplifyMethod method) {
    switch (method) {
        case SimplifyMethod::kHierarchical: return "hierarchical";
        case SimplifyMethod::kIncremental: return "incremental";
        case SimplifyMethod::kIterative: return "iterative";
        case SimplifyMethod::kParticle: return "particle";
        case SimplifyMethod::kVoxel: return "voxel";
    }
    return "?";
}

std::optional<SimplifyMethod> ParseSimplifyMethod(std::string_view name) {
    for (SimplifyMethod m : kSimplifyMethods)
        if (name == SimplifyMethodName(m)) return m;
    return std::nullopt;
}

const char* SimplifyRepresentativeName(SimplifyRepresentative representative) {
    switch (representative) {
        case SimplifyRepresentative::kCentroid: return "centroid";
        case SimplifyRepresentative::kMember: return "member";
    }
    return "?";
}

std::optional<SimplifyRepresentative> ParseSimplifyRepresentative(std::string_view name) {
    for (SimplifyRepresentative r : {SimplifyRepresentative::kCentroid, SimplifyRepresentative::kMember})
        if (name == SimplifyRepresentativeName(r)) return r;
    return std::nullopt;
}

// Validation: one check per field in the order of the job spec, then the combinations.
void SimplifyOptions::Validate() const {
    if (std::find(kSimplifyMethods.begin(), kSimplifyMethods.end(), method) == kSimplifyMethods.end())
        InvalidField("method", "unknown method " + std::to_string(static_cast<int>(method)));
    CheckRange("error", error, 0.0, kMaxErrorBound);
    if (target > 0 && error > 0) InvalidField("target", "give target or error, not both");
    CheckRange("max_variation", max_variation, kMinMaxVariation, kMaxMaxVariation);
    const bool error_bound = method == SimplifyMethod::kHierarchical || method == SimplifyMethod::kIterative;
    const bool own_bound = method == SimplifyMethod::kHierarchical || method == SimplifyMethod::kIncremental;
    if (error > 0 && !error_bound) InvalidField("error", "this method takes a target, not an error bound");
    if (target == 0 && error == 0 && !own_bound) InvalidField("target", "is required for this method");
    CheckRange("max_cluster_size", static_cast<double>(max_cluster_size), 1.0, static_cast<double>(kMaxMaxClusterSize));
    CheckRange("neighbors", neighbors, kMinNeighbors, kMaxNeighbors);
    CheckRange("particle_iterations", particle_iterations, 0, kMaxParticleIterations);
    if (representative != SimplifyRepresentative::kCentroid && representative != SimplifyRepresentative::kMember)
        InvalidField("representative", "unknown representative " + std::to_string(static_cast<int>(representative)));
    if (representative == SimplifyRepresentative::kMember && method == SimplifyMethod::kParticle)
        InvalidField("representative",
                     "particle simulation places its own points; member is for hierarchical, incremental, "
                     "iterative and voxel");
}

double PeakResidentMiB() {
    std::ifstream status("/proc/self/status");
    std::string line;
    while (std::getline(status, line))
        if (line.rfind("VmHWM:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;  // kB
    return 0.0;
}

// A cluster's centroid lies inside the curve of a bent surface (below a convex cap, above a
// concave one), so the result's surface shrinks. The representative is the centroid lifted onto
// the cluster's own surface: a least-squares quadratic height field z = g(x, y) over the
// cluster's regression plane (notes 1.3's local polynomial, unweighted, over the members), taken
// at the centroid (x = y = 0). Still a low-pass average (notes 2: clustering resamples, it does not
// subsample). Clusters with fewer than kMinFit members, or whose fit is degenerate or moves the
// point farther than the cluster's thickness, keep the centroid.
//
// Each cluster's members in input order (a counting sort by cluster); cluster_sums.h adds their
// terms, kLanes clusters of about the same size at a time, with the bits of adding each point to
// its cluster's Moments and PolyFit::Add in input order.
// Sets rep[c] and done[c] = 1 for every fitted cluster c: the lifted point, or where the fit fails
// the centroid (from the same sums as BuildFromClusters' centroids: the members' positions in
// double, added in input order, divided by the count; the same bits).
void RepresentativesOnSurface(std::span<const Vec3f> points, const Clustering& clusters,
                              std::span<const std::uint32_t> count, std::vector<Vec3f>& rep,
                              std::vector<char>& done) {
    constexpr std::uint32_t kMinFit = 20;
    constexpr int kLanes = cluster_sums::kLanes;
    const std::size_t n = points.size(), m = clusters.count;
    // Members of the fitted clusters (slot s for cluster fitted[s]; kNone for the others), each
    // cluster's in input order.
    constexpr std::uint32_t kNone = std::numeric_limits<std::uint32_t>::max();
    std::vector<std::uint32_t> slot(m, kNone), fitted, start{0};
    for (std::size_t c = 0; c < m; ++c)
        if (count[c] >= kMinFit) {
            slot[c] = static_cast<std::uint32_t>(fitted.size());
            fitted.push_back(static_cast<std::uint32_t>(c));
            start.push_back(start.back() + count[c]);
        }
    if (fitted.empty()) return;
    std::vector<std::uint32_t> members(start.back()), next(start.begin(), start.end() - 1);
    for (std::size_t i = 0; i < n; ++i)
        if (const std::uint32_t s = slot[clusters.label[i]]; s != kNone) members[next[s]++] = static_cast<std::uint32_t>(i);
    // Groups of kLanes clusters, largest first (a group's lanes run as long as its largest).
    std::vector<std::uint32_t> by_size(fitted.size());
    std::iota(by_size.begin(), by_size.end(), 0u);
    std::stable_sort(by_size.begin(), by_size.end(), [&](std::uint32_t a, std::uint32_t b) {
        return start[a + 1] - start[a] > start[b + 1] - start[b];
    });
    const std::size_t groups = (fitted.size() + kLanes - 1) / kLanes;
    const cluster_sums::Kernels& kernels = cluster_sums::Best();
    const float* xyz = points.data()->data();  // Vec3f: three packed floats
    // The groups in parallel (each writes only its own clusters' representatives: the same bits
    // whatever the thread count); at 1 % nearly every input point is in a fitted cluster.
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, groups, 8), [&](const tbb::blocked_range<std::size_t>& range) {
        for (std::size_t group = range.begin(); group != range.end(); ++group) {
            std::uint32_t cluster[kLanes], size[kLanes];
            const std::uint32_t* mine[kLanes];
            for (int l = 0; l < kLanes; ++l) {
                const std::size_t k = group * kLanes + l;
                const std::uint32_t s = k < by_size.size() ? by_size[k] : kNone;
                cluster[l] = s == kNone ? kNone : fitted[s];
                size[l] = s == kNone ? 0 : start[s + 1] - start[s];
                mine[l] = s == kNone ? nullptr : members.data() + start[s];
            }
            double mo[9 * kLanes], frame[13 * kLanes] = {}, t[21 * kLanes];
            kernels.moments(xyz, mine, size, mo);
            // Each cluster's plane (Moments, Analyze), frame and the fit's scale.
            LocalFrame lf[kLanes];
            double h[kLanes] = {}, thickness[kLanes] = {};
            for (int l = 0; l < kLanes; ++l) {
                if (size[l] == 0) continue;
                const auto at = [&](int k) { return mo[k * kLanes + l]; };
                detail::Moments mom;
                mom.n = double(size[l]);
                mom.sum = Eigen::Vector3d(at(0), at(1), at(2));
                mom.outer << at(3), at(4), at(5), at(4), at(6), at(7), at(5), at(7), at(8);
                const detail::Spread sp = detail::Analyze(mom);
                lf[l] = LocalFrame::FromNormal(mom.Centroid(), sp.v0);
                thickness[l] = 3.0 * std::sqrt(sp.eigenvalues[0]);
                h[l] = std::max(std::sqrt(sp.eigenvalues[2]), 1e-30);
                const Vec3d* axes[4] = {&lf[l].origin, &lf[l].u, &lf[l].v, &lf[l].n};
                for (int a = 0; a < 4; ++a)
                    for (int k = 0; k < 3; ++k) frame[(3 * a + k) * kLanes + l] = (*axes[a])[k];
                frame[12 * kLanes + l] = PolyFit(2, h[l]).inv_h();
            }
            kernels.fit(xyz, mine, size, frame, t);
            for (int l = 0; l < kLanes; ++l) {
                if (size[l] == 0) continue;
                PolyFit fit(2, h[l]);
                double sums[21];
                for (int k = 0; k < 21; ++k) sums[k] = t[k * kLanes + l];
                fit.AddSums(sums);
                PolyCoeffs g;
                done[cluster[l]] = 1;
                if (!fit.Solve(&g) || !(std::abs(g.c[0]) <= thickness[l])) {
                    rep[cluster[l]] = lf[l].origin.cast<float>();  // the centroid
                    continue;
                }
                rep[cluster[l]] = lf[l].ToWorld(0.0, 0.0, g.c[0]).cast<float>();
            }
        }
    });
}

std::vector<std::uint32_t> NearestMembers(std::span<const Vec3f> points, const Clustering& clusters,
                                          std::span<const Vec3f> near) {
    const std::size_t n = points.size(), m = clusters.count;
    SURFEL_CHECK(clusters.label.size() == n);
    SURFEL_CHECK(near.empty() || near.size() == m);
    // The plain centroids where no points are given: the members' positions in double, in input order.
    std::vector<Vec3d> target(m, Vec3d::Zero());
    if (near.empty()) {
        std::vector<std::uint32_t> count(m, 0);
        for (std::size_t i = 0; i < n; ++i) {
            target[clusters.label[i]] += points[i].cast<double>();
            ++count[clusters.label[i]];
        }
        for (std::size_t c = 0; c < m; ++c) target[c] /= std::max(1u, count[c]);
    } else {
        for (std::size_t c = 0; c < m; ++c) target[c] = near[c].cast<double>();
    }
    constexpr std::uint32_t kNone = std::numeric_limits<std::uint32_t>::max();
    std::vector<std::uint32_t> member(m, kNone);
    std::vector<double> best(m, std::numeric_limits<double>::infinity());
    for (std::size_t i = 0; i < n; ++i) {  // the first in input order wins a tie
        const std::uint32_t c = clusters.label[i];
        const double d2 = (points[i].cast<double>() - target[c]).squaredNorm();
        if (d2 < best[c] || member[c] == kNone) best[c] = d2, member[c] = static_cast<std::uint32_t>(i);
    }
    for (std::size_t c = 0; c < m; ++c)
        if (member[c] == kNone)
            throw Error(ErrorCode::kInternal, "simplify: output point " + std::to_string(c) + " has no member");
    return member;
}

PointCloud BuildFromClusters(const PointCloud& input, std::span<const Vec3f> normals, const Clustering& clusters,
                             std::span<const Vec3f> positions, bool positions_only, const KdTree* given_input_tree) {
    const std::size_t n = input.size(), m = clusters.count;
    SURFEL_CHECK(clusters.label.size() == n);
    SURFEL_CHECK(positions.empty() || positions.size() == m);
    PointCloud out;
    std::vector<Vec3d> sum(m, Vec3d::Zero()), nsum(normals.empty() ? 0 : m, Vec3d::Zero());
    std::vector<std::array<double, 4>> csum(input.has_colors() ? m : 0, {0, 0, 0, 0});
    std::vector<std::uint32_t> count(m, 0);
    for (std::size_t i = 0; i < n; ++i) ++count[clusters.label[i]];
    // The fitted clusters' representatives first (at 1 % nearly all points are in one): the sums
    // below then skip their positions.
    out.positions.resize(m);
    std::vector<char> done(m, 0);
    if (positions.empty()) RepresentativesOnSurface(input.positions, clusters, count, out.positions, done);
    for (std::size_t i = 0; i < n; ++i) {
        const std::uint32_t c = clusters.label[i];
        if (!done[c]) sum[c] += input.positions[i].cast<double>();
        if (!normals.empty()) nsum[c] += normals[i].cast<double>();
        if (input.has_colors())
            for (int k = 0; k < 4; ++k) csum[c][k] += input.colors[i][k];
    }
    for (std::size_t c = 0; c < m; ++c)
        if (!done[c])
            out.positions[c] = positions.empty() ? Vec3f((sum[c] / std::max(1u, count[c])).cast<float>()) : positions[c];
    if (positions_only) return out;

    // The nearest input point stands in for clusters without members (particles can end up
    // with none) and for normals that cancel out.
    std::unique_ptr<KdTree> input_tree;
    auto nearest_input = [&](const Vec3f& p) {
        if (given_input_tree) return given_input_tree->Nearest(p).index;
        if (!input_tree) input_tree = std::make_unique<KdTree>(input.positions);
        return input_tree->Nearest(p).index;
    };

    // Splat radius: covers every member (3D distance, so also within the splat's plane), and
    // reaches at least the nearest other representative so neighbouring splats overlap. The
    // members' distances (one serial pass over the input, in input order) run beside the
    // representatives' neighbour searches and orientation below.
    std::vector<float> cover(m, 0.0f);
    tbb::task_group side;  // beside the normals: the cover distances, then the nearest distances
    side.run([&] {
        for (std::size_t i = 0; i < n; ++i) {
            const std::uint32_t c = clusters.label[i];
            const Vec3f d = input.positions[i] - out.positions[c];
            cover[c] = std::max(cover[c], d.norm());
        }
    });

    // Over the representatives: one k-nearest table (KnnAll, nearest first, ties by index) for
    // all their neighbour searches where normals are found here: its first column is the radii's
    // nearest other representative, its first orient_k columns the orientation graph, all its
    // columns the covariance neighbourhoods (the rows each separate search gave).
    std::unique_ptr<KdTree> out_tree;
    if (m >= 2) out_tree = std::make_unique<KdTree>(out.positions);
    KnnTable out_knn;
    std::vector<float> nn;  // from out_knn: the nearest other representative
    if (!normals.empty()) {
        out.normals.resize(m);
        for (std::size_t c = 0; c < m; ++c) {
            const double len = nsum[c].norm();
            out.normals[c] = len > 1e-6 * count[c] && count[c] > 0 ? Vec3f((nsum[c] / len).cast<float>())
                                                                    : normals[nearest_input(out.positions[c])];
        }
    } else if (m >= 3 && clusters.normals.size() == m) {
        // The clusters' own normals (hierarchical: the v0 of each cluster's covariance, notes
        // 1.2, over all of its members), oriented over the representatives (notes 1.2, MST). A
        // cluster too small or too thin for a plane takes the covariance normal of its nearest
        // representatives: the 16 nearest of its own position, itself included (KdTree::Knn),
        // which are itself ranked into its table row by (distance, index) at distance 0.
        out.normals = clusters.normals;
        const int kn = std::min<int>(16, static_cast<int>(m));
        out_knn = out_tree->KnnAll(std::min<int>(16, static_cast<int>(m) - 1));
        side.run([&] { nn = NearestDistances(out.positions, out_knn); });
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 1024), [&](const tbb::blocked_range<std::size_t>& r) {
            std::vector<std::uint32_t> idx;
            for (std::size_t c = r.begin(); c != r.end(); ++c) {
                if (out.normals[c] != Vec3f::Zero()) continue;
                const auto row = out_knn.Row(c);
                const auto d2 = out_knn.Dist2(c);
                const auto self = static_cast<std::uint32_t>(c);
                idx.clear();
                std::size_t j = 0;
                while (static_cast<int>(idx.size()) < kn && j < row.size() && d2[j] == 0.0f && row[j] < self)
                    idx.push_back(row[j++]);
                if (static_cast<int>(idx.size()) < kn) idx.push_back(self);
                while (static_cast<int>(idx.size()) < kn) idx.push_back(row[j++]);
                out.normals[c] = AnalyzeNeighborhood(out.positions, idx).normal.cast<float>();
            }
        });
        NormalOptions no;
        no.orient_k = std::min<int>(10, static_cast<int>(m) - 1);
        OrientNormals(out.positions, out_knn, out.normals, no);
    } else if (m >= 4) {
        NormalOptions no;
        no.k = std::min<int>(16, static_cast<int>(m) - 1);
        no.orient_k = std::min<int>(10, static_cast<int>(m) - 1);
        out_knn = out_tree->KnnAll(no.k);
        side.run([&] { nn = NearestDistances(out.positions, out_knn); });
        out.normals = EstimateNormals(*out_tree, out_knn, no).normals;
    } else if (m == 3) {
        // Too few for EstimateNormals (k >= 3 other points): the three representatives' plane.
        const Vec3f cross = (out.positions[1] - out.positions[0]).cross(out.positions[2] - out.positions[0]);
        const float len = cross.norm();
        out.normals.assign(m, len > 0.0f && std::isfinite(len) ? Vec3f(cross / len) : Vec3f::UnitZ());
    } else {
        out.normals.assign(m, Vec3f::UnitZ());
    }

    if (input.has_colors()) {
        out.colors.resize(m);
        out.color_type = input.color_type;
        out.color_has_alpha = input.color_has_alpha;
        for (std::size_t c = 0; c < m; ++c) {
            if (count[c] == 0) {
                out.colors[c] = input.colors[nearest_input(out.positions[c])];
                continue;
            }
            for (int k = 0; k < 4; ++k) out.colors[c][k] = static_cast<float>(csum[c][k] / count[c]);
        }
    }

    side.wait();
    out.radii.resize(m);
    if (out_knn.k) {
        // The nearest other representative, from the table (KthNeighborDistances' values).
        for (std::size_t c = 0; c < m; ++c) out.radii[c] = std::max(cover[c], nn[c]);
    } else if (out_tree) {
        // The nearest other representative (a grid, exact: the same as the tree's KnnAll(1)).
        nn = KthNeighborDistances(out.positions, 1, out_tree.get());
        for (std::size_t c = 0; c < m; ++c) out.radii[c] = std::max(cover[c], nn[c]);
    } else {
        out.radii = cover;
    }
    return out;
}

SimplifyResult Simplify(const PointCloud& input, const SimplifyOptions& options, const ProgressFn& progress) {
    const std::string method = SimplifyMethodName(options.method);
    const std::size_t n = input.size();
    options.Validate();
    if (n == 0) throw Error(ErrorCode::kInvalidArgument, "simplify: the input cloud has no points");
    if (options.target > n)
        InvalidField("target", "must not exceed the input's " + std::to_string(n) + " points, got " +
                                   std::to_string(options.target));
    // Its neighbour graph takes at least 2 neighbours a point (issue 18: a 1- or 2-point cloud
    // indexed past the kd-tree's padded rows).
    if (options.method == SimplifyMethod::kIncremental && n < 3)
        throw Error(ErrorCode::kInvalidArgument, "simplify: incremental clustering needs at least 3 input points");
    if (options.method == SimplifyMethod::kParticle && n < 8)
        throw Error(ErrorCode::kInvalidArgument, "simplify: particle simulation needs at least 8 input points");

    SimplifyResult result;
    SimplifyReport& report = result.report;
    report.method = method;
    report.representative = SimplifyRepresentativeName(options.representative);
    report.adaptive = options.adaptive;
    report.input_points = n;

    const bool needs_input_normals = options.method == SimplifyMethod::kIterative ||
                                     options.method == SimplifyMethod::kParticle;
    ProgressTracker tracker(progress, 1.0, std::string(method) + " simplification");
    const Stopwatch clock;

    std::vector<Vec3f> normals = input.normals;
    std::vector<float> variation;
    std::unique_ptr<KdTree> input_tree;  // built for the input normals, kept for the attributes
    KnnTable input_knn;  // iterative: the k = 16 neighbours of the normals also give its graph
    NormalOptions no;
    no.k = std::min<int>(16, static_cast<int>(n) - 1);
    no.orient_k = std::min<int>(10, static_cast<int>(n) - 1);
    // Neither method needs oriented input normals: the particles only tangent planes (2.3.3),
    // the quadrics of iterative contraction hold n n^T, d n and d^2, the same for -n. The
    // output normals are oriented afterwards, over the m output points instead of the n
    // input points.
    no.orient = false;
    // The particle simulation without the adaptive variant's variation (of every point) leaves
    // its engine to estimate the normals of the input points its particles visit (the same
    // normals, bit for bit): a few thousand particles touch a small part of a large scan.
    const bool lazy_particle_normals =
        options.method == SimplifyMethod::kParticle && !options.adaptive && normals.empty();
    if (options.method == SimplifyMethod::kParticle)
        input_tree = std::make_unique<KdTree>(input.positions);
    if (lazy_particle_normals) {
        report.normals_estimated = true;
    } else if ((needs_input_normals && normals.empty()) ||
               (options.method == SimplifyMethod::kParticle && options.adaptive)) {
        if (!input_tree) input_tree = std::make_unique<KdTree>(input.positions);
        const KdTree& tree = *input_tree;
        if (n >= 3) {  // fewer: EstimateNormals names the problem
            // One k-nearest table for the normals, the iterative graph and the particle engine.
            const int k =
                options.method == SimplifyMethod::kIterative
                    ? std::max(no.k, std::min<int>(options.neighbors, static_cast<int>(n) - 1))
                    : no.k;
            input_knn = tree.KnnAll(k);
        }
        NormalResult nr = input_knn.k ? EstimateNormals(tree, input_knn, no) : EstimateNormals(tree, no);
        if (normals.empty()) {
            normals = std::move(nr.normals);
            report.normals_estimated = true;
        }
        variation = std::move(nr.surface_variation);
    }
    // Report the start (fraction 0) whatever the method: a small job whose method reports in
    // coarse steps still shows its stage, and a cancel that came before the work stops it here.
    tracker.Advance(0.0);

    Clustering clusters;
    std::vector<Vec3f> positions, particle_normals;
    switch (options.method) {
        case SimplifyMethod::kHierarchical:
            clusters = detail::HierarchicalClustering(input.positions, options, tracker);
            break;
        case SimplifyMethod::kIncremental:
            clusters = detail::IncrementalClustering(input.positions, options, tracker);
            break;
        case SimplifyMethod::kVoxel:
            clusters = detail::VoxelClustering(input.positions, options, tracker);
            break;
        case SimplifyMethod::kIterative:
            clusters = detail::IterativeSimplification(input.positions, normals, std::move(input_knn),
                                                       report.normals_estimated, options, positions, tracker);
            break;
        case SimplifyMethod::kParticle: {
            // Particle simulation (2.3) by the resample module's engine, over the input's tree
            // (and k-nearest table, when the normals were estimated here).
            ParticleEngine::Shared shared;
            shared.tree = input_tree.get();
            if (input_knn.k) shared.knn = &input_knn;
            shared.lazy_normals = no;
            // The tree's index is built on first use, by the first walk or lazy normal of the
            // simulation: one thread builds it here while the others find the engine's sampling
            // density on its grid (session 13: the build ran alone on one core, ~0.05 s).
            tbb::task_group build;
            build.run([&] { input_tree->Nearest(input.positions.front()); });
            const ParticleEngine engine(input, normals, variation, options.adaptive, shared);
            build.wait();
            ParticleParams params;
            params.count = options.target;
            params.seed = options.seed;
            params.iterations = options.particle_iterations;
            engine.Run(params, positions, particle_normals, tracker);
            // Clusters for the attributes: each original point belongs to its closest particle
            // (the lower index on a tie). A grid of the particles finds it exactly wherever one
            // lies within the repulsion radius r0 (nearly every point: the particles cover the
            // surface at about that spacing), the kd-tree elsewhere. Consecutive input points lie
            // close together (scans): the particles within 2 r0 of one point are the candidates
            // of every point within 0.95 r0 of it (each particle within r0 of such a point is
            // within 1.95 r0 of the first), tested with the same float distance and bound, so the
            // same labels (session 13: one grid query a point cost ~14 % of the process's CPU).
            const KdTree ptree(positions);
            const float cell = static_cast<float>(
                2.0 * std::sqrt(engine.WeightedArea() /
                                (std::numbers::pi * static_cast<double>(positions.size()))));
            const bool use_grid = cell > 0.0f && std::isfinite(cell);
            const float reach = 2.0f * cell, r2 = cell * cell, move2 = 0.95f * cell * 0.95f * cell;
            const std::optional<UniformGrid> pgrid =
                use_grid ? std::optional<UniformGrid>(std::in_place, positions, reach)
                         : std::nullopt;
            clusters.label.resize(n);
            tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 4096),
                              [&](const tbb::blocked_range<std::size_t>& r) {
                                  std::vector<std::pair<std::uint32_t, Vec3f>> near;
                                  Vec3f centre = Vec3f::Zero();
                                  bool have = false;
                                  for (std::size_t i = r.begin(); i != r.end(); ++i) {
                                      const Vec3f& x = input.positions[i];
                                      float best = INFINITY;
                                      std::uint32_t nearest = UINT32_MAX;
                                      if (pgrid) {
                                          if (!have || (x - centre).squaredNorm() > move2) {
                                              centre = x;
                                              have = true;
                                              near.clear();
                                              pgrid->ForEachWithin(centre, reach,
                                                                   [&](std::uint32_t j, const Vec3f& p, float) {
                                                                       near.emplace_back(j, p);
                                                                   });
                                          }
                                          for (const auto& [j, p] : near) {
                                              const float d2 = (p - x).squaredNorm();
                                              if (d2 <= r2 && (d2 < best || (d2 == best && j < nearest)))
                                                  best = d2, nearest = j;
                                          }
                                      }
                                      clusters.label[i] =
                                          nearest != UINT32_MAX ? nearest : ptree.Nearest(x).index;
                                  }
                              });
            clusters.count = positions.size();
            // Normals: the particles' MLS normals. Oriented like given input normals as they
            // are; oriented over the output (BuildFromClusters, as the clusters' own normals)
            // where the input normals were estimated without a sign.
            if (report.normals_estimated) clusters.normals = particle_normals;
            break;
        }
    }
    tracker.Check();
    // A subset of the input: each cluster's member nearest the point it would have given.
    std::vector<std::uint32_t> members;
    if (options.representative == SimplifyRepresentative::kMember) {
        members = NearestMembers(input.positions, clusters, positions);
        positions.resize(members.size());
        for (std::size_t c = 0; c < members.size(); ++c) positions[c] = input.positions[members[c]];
    }
    // Estimated (unoriented) input normals reach the output through the clusters' own normals.
    const bool unoriented =
        report.normals_estimated && (options.method == SimplifyMethod::kIterative ||
                                     options.method == SimplifyMethod::kParticle);
    result.cloud = BuildFromClusters(input, unoriented ? std::span<const Vec3f>{} : std::span<const Vec3f>(normals),
                                     clusters, positions, options.positions_only, input_tree.get());
    if (!members.empty() && !options.positions_only) {
        // The members' own attributes, unchanged (BuildFromClusters averaged them): a given
        // normal and a colour. Estimated normals stay the clusters' own, oriented over the output.
        PointCloud& out = result.cloud;
        for (std::size_t c = 0; c < members.size(); ++c) {
            if (!input.normals.empty()) out.normals[c] = input.normals[members[c]];
            if (input.has_colors()) out.colors[c] = input.colors[members[c]];
        }
    }
    if (!particle_normals.empty() && !options.positions_only &&
        (!report.normals_estimated || result.cloud.size() < 3)) {
        result.cloud.normals = particle_normals;  // the MLS normals at the projected positions
        // Radii were measured in the planes of the member-averaged normals; close enough, and
        // the nearest-neighbour floor still holds.
    }
    report.time_ms = clock.ElapsedMs();
    report.output_points = result.cloud.size();
    report.peak_rss_mb = PeakResidentMiB();

    if (options.measure_error && result.cloud.size() >= 8) {
        const Stopwatch error_clock;
        SurfaceErrorOptions eo;
        eo.max_samples = options.error_samples;
        eo.seed = options.seed;
        report.error = MeasureSurfaceError(input, result.cloud, eo);
        report.error_time_ms = error_clock.ElapsedMs();
    }
    return result;
}

}  // namespace surfel
