#include "surfel/resample/resample.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <numbers>
#include <numeric>
#include <sstream>
#include <string>

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/resample/particle_engine.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/spatial/neighbor_radii.h"
#include "surfel/spatial/uniform_grid.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/poly_fit.h"

namespace surfel {
namespace {

// Interpolation filter (notes 3.2.3): the attributes of a new sample from the original samples,
// which never move (the notes' zombies). A Gaussian-weighted linear fit a(u, v) = c0 + g . (u, v)
// over the k nearest originals in the tangent plane at x, evaluated at x (c0): exact for
// attributes linear along the surface, unlike a plain average, whose error grows with the
// offset of the neighbours' weighted centroid. Written about that centroid ubar, the fit is
// c0 = abar - g . ubar with C g = cov(u, a), C the weighted covariance of the neighbours' (u, v);
// along an eigenvector of C whose eigenvalue is tiny (neighbours nearly on a line) the slope is
// undetermined, so each eigenvalue is damped by kSlopeDamping * lambda_max (Tikhonov): the slope
// fades smoothly to 0 there, i.e. to the weighted mean across the line, and is kept (to a factor
// lambda / (lambda + 1e-3 lambda_max)) everywhere else. The fit is invariant under the sign of
// the normal (it only turns the frame's u axis over).
//
// An earlier version switched to the plain weighted mean when the smallest eigenvalue of the
// uncentred 3x3 normal matrix fell below 1e-2 of its largest. That ratio mixes the constant term
// with the spread and is below 1e-2 wherever x sits in a thin, elongated gap of a random
// sampling (centred spread ratio ~0.07, a perfectly determined slope): the mean there is off by
// up to |grad a| times the centroid's offset, 0.5 x 0.045 = 0.023 on the colour ramp, one point
// in ~10^4, present or not by the chance of the particle configuration.
constexpr int kInterpolationNeighbors = 10;
// Dynamic sampling: the neighbours of the tangent ellipse, and the relaxation steps per round.
constexpr int kSplitNeighbors = 6;
// Rim samples (MeasureStretch): the neighbours whose angles around a sample are compared, and
// the largest angle between two consecutive ones that the interior leaves (a rim: ~180 degrees;
// a random sampling's 16 nearest leave more than 150 degrees at one sample in 200, the relaxed
// samples of a split round at far fewer).
constexpr int kSplitBoundaryNeighbors = 16;
constexpr int kSplitInputRimNeighbors = 32;
constexpr double kSplitRimGap = 5.0 * std::numbers::pi / 6.0;
// Splitting stops early where it does not converge: once the samples above the target are at
// most kSplitStallShare of all and more than kSplitStallRatio of those kSplitStallRounds rounds
// before. On the bunny at spacing 0.0005 the rounds after the 10th split 40-230 samples each, at
// its creases (the base's edge, the ear tips: each side's samples lie on its own tangent planes
// and the gap between the sides stays 1.6-1.7 spacings in space), down by ~1/3 per 4 rounds, up
// to kMaxSplitRounds; closed shapes and the bunny at 0.001 halve them every round or two until
// none is left.
constexpr double kSplitStallShare = 1e-3;
constexpr double kSplitStallRatio = 0.5;
constexpr int kSplitStallRounds = 4;
constexpr int kSplitRelaxIterations = 10;
constexpr double kSplitRelaxRadius = 1.0;
// How far from a split sample (in target spacings) its round's relaxation moves samples. At 2 the
// samples bunched near the splits (sphere test: NN mean 0.0358 for a target of 0.04, CV 0.065);
// at 4 NN mean 0.0371, CV 0.042.
constexpr double kSplitRelaxReach = 4.0;
constexpr double kSlopeDamping = 1e-3;

struct InterpolationWeights {
    std::array<std::uint32_t, kInterpolationNeighbors> index{};
    std::array<double, kInterpolationNeighbors> weight{};  // sum c_j a_j = the fitted a(x)
    int count = 0;
};

InterpolationWeights FitWeights(const Vec3f& x, const Vec3f& normal, std::span<const Vec3f> points,
                                std::span<const std::uint32_t> row, std::span<const float> dist2) {
    InterpolationWeights w;
    w.count = static_cast<int>(row.size());
    const double h2 = std::max(1e-30, static_cast<double>(dist2.back()));
    const double s = std::sqrt(h2);
    const LocalFrame frame = LocalFrame::FromNormal(x.cast<double>(), normal.cast<double>());
    std::array<Eigen::Vector2d, kInterpolationNeighbors> l;
    std::array<double, kInterpolationNeighbors> theta{};
    double theta_sum = 0.0;
    Eigen::Vector2d ubar = Eigen::Vector2d::Zero();
    for (int j = 0; j < w.count; ++j) {
        w.index[j] = row[j];
        const Vec3d local = frame.ToLocal(points[row[j]].cast<double>());
        l[j] = Eigen::Vector2d(local.x(), local.y()) / s;  // scaled to O(1)
        theta[j] = std::exp(-static_cast<double>(dist2[j]) / h2);
        theta_sum += theta[j];
        ubar += theta[j] * l[j];
    }
    ubar /= theta_sum;
    Eigen::Matrix2d C = Eigen::Matrix2d::Zero();
    for (int j = 0; j < w.count; ++j) C += theta[j] / theta_sum * (l[j] - ubar) * (l[j] - ubar).transpose();
    // c0 = sum_j theta_j / theta_sum (1 - (l_j - ubar) . C_damped^-1 ubar) a_j.
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(C);
    const double lambda_max = eig.eigenvalues()[1];
    Eigen::Vector2d z = Eigen::Vector2d::Zero();  // C_damped^-1 ubar
    if (eig.info() == Eigen::Success && lambda_max > 0)
        for (int k = 0; k < 2; ++k) {
            const Eigen::Vector2d e = eig.eigenvectors().col(k);
            z += e * (e.dot(ubar) / (std::max(0.0, eig.eigenvalues()[k]) + kSlopeDamping * lambda_max));
        }
    for (int j = 0; j < w.count; ++j) w.weight[j] = theta[j] / theta_sum * (1.0 - (l[j] - ubar).dot(z));
    return w;
}

// The fitted value at x, clamped to the attribute's range over the whole input [lo, hi] (a fit
// extrapolates where x lies beside all its neighbours, which is what keeps a ramp exact there;
// the clamp keeps colours valid).
template <typename Get>
double Interpolate(const InterpolationWeights& w, double lo, double hi, Get&& value) {
    double sum = 0.0;
    for (int j = 0; j < w.count; ++j) sum += w.weight[j] * value(w.index[j]);
    return std::clamp(sum, lo, hi);
}

// The output cloud's attributes for points first..size() (those before `first` are input points
// kept as they are, with their attributes already copied).
void InterpolateAttributes(const PointCloud& input, const KdTree& input_tree, std::size_t first, PointCloud& out) {
    const std::size_t m = out.size();
    if (input.has_colors()) out.colors.resize(m);
    for (const ExtraAttribute& e : input.extras) {
        if (out.FindExtra(e.name)) continue;
        out.extras.push_back({e.name, e.type, std::vector<double>(first)});
        std::copy(e.values.begin(), e.values.begin() + static_cast<std::ptrdiff_t>(first),
                  out.extras.back().values.begin());
    }
    for (ExtraAttribute& e : out.extras) e.values.resize(m);
    if (!input.has_colors() && input.extras.empty()) return;
    const int k = std::min<int>(kInterpolationNeighbors, static_cast<int>(input.size()));
    std::array<double, 4> color_lo{}, color_hi{};
    color_lo.fill(INFINITY);
    color_hi.fill(-INFINITY);
    for (const std::array<float, 4>& c : input.colors)
        for (int j = 0; j < 4; ++j) {
            color_lo[j] = std::min<double>(color_lo[j], c[j]);
            color_hi[j] = std::max<double>(color_hi[j], c[j]);
        }
    std::vector<std::array<double, 2>> extra_range;
    for (const ExtraAttribute& e : input.extras) {
        const auto [lo, hi] = std::minmax_element(e.values.begin(), e.values.end());
        extra_range.push_back({*lo, *hi});
    }
    tbb::parallel_for(tbb::blocked_range<std::size_t>(first, m, 256), [&](const auto& range) {
        std::vector<Neighbor> near;
        std::vector<std::uint32_t> row;
        std::vector<float> dist2;
        for (std::size_t p = range.begin(); p != range.end(); ++p) {
            input_tree.Knn(out.positions[p], k, &near);
            row.clear();
            dist2.clear();
            for (const Neighbor& nb : near) {
                row.push_back(nb.index);
                dist2.push_back(nb.dist2);
            }
            const InterpolationWeights w = FitWeights(out.positions[p], out.normals[p], input.positions, row, dist2);
            if (input.has_colors())
                for (int c = 0; c < 4; ++c)
                    out.colors[p][c] = static_cast<float>(Interpolate(w, color_lo[c], color_hi[c], [&](std::uint32_t i) {
                        return input.colors[i][c];
                    }));
            for (std::size_t a = 0; a < input.extras.size(); ++a) {
                const std::vector<double>& v = input.extras[a].values;
                out.extras[a].values[p] =
                    Interpolate(w, extra_range[a][0], extra_range[a][1], [&](std::uint32_t i) { return v[i]; });
            }
        }
    });
}

// Counts that depend on the input: the spacing's count (hexagonal lattice, area per point
// sqrt(3)/2 s^2) and the keep-input condition.
std::size_t OutputCount(const ResampleOptions& options, const ParticleEngine& engine, std::size_t n) {
    std::size_t count = options.target;
    if (options.target == 0) {
        const double lattice = engine.WeightedArea() / (std::sqrt(3.0) / 2.0 * options.spacing * options.spacing);
        const double total = options.keep_input ? std::max(lattice, static_cast<double>(n)) : lattice;
        if (!(total >= 1.0 && total <= static_cast<double>(kMaxResampleTarget))) {
            std::ostringstream msg;
            msg << "gives " << total << " points on this input (area " << engine.WeightedArea()
                << "); the count must lie in 1.." << static_cast<double>(kMaxResampleTarget);
            InvalidField("spacing", msg.str());
        }
        count = static_cast<std::size_t>(std::llround(total));
        if (options.keep_input && count <= n) {
            std::ostringstream msg;
            msg << "with keep_input must be below the input's own spacing: it adds no points to these "
                << n << " points";
            InvalidField("spacing", msg.str());
        }
    } else if (options.keep_input && count <= n) {
        InvalidField("target", "with keep_input must exceed the input's " + std::to_string(n) + " points, got " +
                                   std::to_string(count));
    }
    return count;
}

// Particle simulation (2.3): the new points; with keep_input the input repels them. The
// output: kept input points first, then the particles, attributes interpolated from the input.
void RunParticles(const PointCloud& input, const KdTree& tree, const KnnTable* knn,
                  std::span<const Vec3f> normals, std::span<const float> variation,
                  const ResampleOptions& options, ProgressTracker& tracker, PointCloud& out,
                  ResampleReport& report) {
    const std::size_t n = input.size();
    ParticleEngine::Shared shared;
    shared.tree = &tree;
    shared.knn = knn;
    const ParticleEngine engine(input, normals, variation, options.adaptive, shared);
    const std::size_t count = OutputCount(options, engine, n);
    ParticleParams params;
    params.seed = options.seed;
    params.iterations = options.iterations;
    params.gain = kResampleGain;
    params.fixed_input = options.keep_input;
    params.tolerance = options.relax_tolerance;
    params.cached_fits = options.cached_fits;
    params.spread = options.spread_disk ? ParticleParams::Spread::kDisk : ParticleParams::Spread::kJitter;
    params.count = options.keep_input ? count - n : count;
    std::vector<Vec3f> positions, particle_normals;
    ParticleStats stats;
    engine.Run(params, positions, particle_normals, tracker, &stats);
    report.iterations = stats.iterations;

    const std::size_t first = options.keep_input ? n : 0;
    out.positions.reserve(count);
    out.normals.reserve(count);
    if (options.keep_input) {
        out.positions = input.positions;
        out.normals.assign(normals.begin(), normals.end());
        out.colors = input.colors;
        for (const ExtraAttribute& e : input.extras) out.extras.push_back(e);
    }
    out.positions.insert(out.positions.end(), positions.begin(), positions.end());
    out.normals.insert(out.normals.end(), particle_normals.begin(), particle_normals.end());
    out.color_type = input.color_type;
    out.color_has_alpha = input.color_has_alpha;
    InterpolateAttributes(input, engine.tree(), first, out);
}

// Smoothing (notes 1.3): every input point onto the MLS surface, its attributes kept; the MLS
// normal turned to agree with the point's own normal; h from the data unless given.
void RunMls(const PointCloud& input, const KdTree& tree, std::span<const Vec3f> normals,
            const ResampleOptions& options, ProgressTracker& tracker, PointCloud& out,
            ResampleReport& report) {
    MlsOptions mo;
    mo.degree = options.mls_degree;
    mo.adaptive = options.adaptive;
    mo.h = static_cast<float>(options.mls_h);
    mo.scale_rule = MlsScaleRule::kNoise;
    const MlsSurface mls(input, tree, mo);
    report.mls_h = mls.h();
    if (mls.scale_choice()) report.noise = mls.scale_choice()->noise;
    tracker.Advance(0.1);
    double done = 0.0;
    const MlsSurface::Batch batch = mls.ProjectAll(input.positions, [&](double fraction) {
        tracker.Advance(0.8 * std::max(0.0, fraction - done));
        done = std::max(done, fraction);
        return !tracker.cancelled();
    });
    tracker.Check();
    report.mls_failed = batch.failed;
    out = input;
    out.normals.assign(normals.begin(), normals.end());
    for (std::size_t i = 0; i < input.size(); ++i) {
        const Vec3f& nrm = batch.normals[i];
        if (!(nrm.squaredNorm() > 0.5f) || !batch.positions[i].allFinite()) continue;  // not projected
        out.positions[i] = batch.positions[i];
        out.normals[i] = nrm.dot(normals[i]) < 0 ? Vec3f(-nrm) : nrm;
    }
    tracker.Advance(0.1);
}

// The largest angle between consecutive neighbours around a point, its neighbours (`row`)
// projected on the tangent plane `frame` (notes 1.2's boundary test: at a rim of the sampled
// surface the neighbours lie on one side, ~180 degrees left empty), and the unit direction of
// its middle in the frame's (u, v).
struct AngleGap {
    double angle = 0.0;
    Eigen::Vector2d middle = Eigen::Vector2d::Zero();
};

AngleGap LargestGap(const LocalFrame& frame, std::span<const Vec3f> points,
                    std::span<const std::uint32_t> row) {
    std::array<double, kSplitInputRimNeighbors> angle{};
    const int count = std::min<int>(kSplitInputRimNeighbors, static_cast<int>(row.size()));
    for (int j = 0; j < count; ++j) {
        const Vec3d l = frame.ToLocal(points[row[j]].cast<double>());
        angle[j] = std::atan2(l.y(), l.x());
    }
    AngleGap g;
    if (count == 0) return g;
    std::sort(angle.begin(), angle.begin() + count);
    g.angle = angle[0] + 2.0 * std::numbers::pi - angle[count - 1];
    double middle = angle[count - 1] + 0.5 * g.angle;
    for (int j = 1; j < count; ++j)
        if (angle[j] - angle[j - 1] > g.angle)
            g.angle = angle[j] - angle[j - 1], middle = angle[j - 1] + 0.5 * g.angle;
    g.middle = Eigen::Vector2d(std::cos(middle), std::sin(middle));
    return g;
}

// The stretch of one sample (notes 3.2.2): the tangent ellipse of its neighbours, as the
// spacing along the main axis, sqrt(2 lambda_max) of the second moments sum d d^T / k of the k
// nearest in the tangent plane (s^2 / 2 I for k = 6 on a hexagonal lattice of spacing s), and
// that axis.
//
// At a rim of the surface (a scan's edge, a hole) the neighbourhood is one-sided, and the 6
// nearest reach farther along the rim (a lattice row's edge sample has 4 neighbours at s, the
// 5th and 6th at sqrt(3) s: 1.53 s), so its ellipse stays above the target however often it is
// split: that kept the bunny splitting at its holes for all kMaxSplitRounds rounds. A sample is
// at a rim when its closest input sample is at one or next to one (`outward`, that rim's
// direction, non-zero; the input, which never moves, says where the surface ends, so a gap the
// densification has not filled yet is not taken for a rim) and its own kSplitBoundaryNeighbors
// nearest (`row`; a shorter row skips the test) leave a gap of more than kSplitRimGap on that side.
// It is judged by the interior side alone: the lattice's neighbours in the covered angle theta, 6
// theta / 2 pi + 1 of the nearest (4 at a straight rim: 1.12 s on the lattice), their ellipse
// mirrored across the rim (the cross term between along and across it dropped, as if the other side
// were there).
struct Stretch {
    float extent = 0.0f;
    Vec3f axis = Vec3f::Zero();
    std::uint8_t rim = 0;
};

Stretch MeasureStretch(std::span<const Vec3f> pos, std::size_t i, const Vec3f& normal,
                       const Vec3f& outward, std::span<const std::uint32_t> row) {
    const LocalFrame frame = LocalFrame::FromNormal(pos[i].cast<double>(), normal.cast<double>());
    const int k = std::min<int>(kSplitNeighbors, static_cast<int>(row.size()));
    std::array<Eigen::Vector2d, kSplitNeighbors> d;
    for (int j = 0; j < k; ++j) {
        const Vec3d l = frame.ToLocal(pos[row[j]].cast<double>());
        d[j] = Eigen::Vector2d(l.x(), l.y());
    }
    Stretch st;
    AngleGap gap;
    if (outward != Vec3f::Zero() && static_cast<int>(row.size()) >= kSplitBoundaryNeighbors) {
        gap = LargestGap(frame, pos, row);
        const Vec3d o = frame.DirToLocal(outward.cast<double>());
        st.rim = gap.angle > kSplitRimGap && gap.middle.dot(Eigen::Vector2d(o.x(), o.y())) > 0;
    }
    Eigen::Matrix2d C = Eigen::Matrix2d::Zero();
    if (!st.rim) {
        for (int j = 0; j < k; ++j) C += d[j] * d[j].transpose() / static_cast<double>(k);
    } else {
        const double covered = 2.0 * std::numbers::pi - gap.angle;
        const int kb = std::clamp(
            static_cast<int>(std::lround(6.0 * covered / (2.0 * std::numbers::pi))) + 1, 2, k);
        const Eigen::Vector2d out = gap.middle, along(-out.y(), out.x());
        double aa = 0.0, oo = 0.0;
        for (int j = 0; j < kb; ++j) {
            const double a = d[j].dot(along), b = d[j].dot(out);
            aa += a * a / kb;
            oo += b * b / kb;
        }
        C = aa * along * along.transpose() + oo * out * out.transpose();
    }
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(C);
    const Eigen::Vector2d e = eig.eigenvectors().col(1);
    st.extent = static_cast<float>(std::sqrt(2.0 * std::max(0.0, eig.eigenvalues()[1])));
    st.axis = (e.x() * frame.u + e.y() * frame.v).cast<float>();
    return st;
}

// The rims of the input (see MeasureStretch): for each input sample whose kSplitInputRimNeighbors
// nearest leave a gap above kSplitRimGap (at 32 neighbours a random sampling's interior does so
// at one sample in 10^7), the unit direction of the gap's middle; zero elsewhere. `near_rim`
// (optional): the same, extended to the samples next to a rim sample.
std::vector<Vec3f> InputRims(const KdTree& tree, std::span<const Vec3f> normals,
                             std::vector<Vec3f>* near_rim) {
    const std::span<const Vec3f> points = tree.points();
    const std::size_t n = points.size();
    std::vector<Vec3f> outward(n, Vec3f::Zero());
    if (near_rim) near_rim->assign(n, Vec3f::Zero());
    if (n <= static_cast<std::size_t>(kSplitInputRimNeighbors)) return outward;
    const KnnTable knn = tree.KnnAll(kSplitInputRimNeighbors);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const auto& range) {
        for (std::size_t i = range.begin(); i != range.end(); ++i) {
            const LocalFrame frame =
                LocalFrame::FromNormal(points[i].cast<double>(), normals[i].cast<double>());
            const AngleGap gap = LargestGap(frame, points, knn.Row(i));
            if (gap.angle > kSplitRimGap)
                outward[i] = (gap.middle.x() * frame.u + gap.middle.y() * frame.v)
                                 .normalized()
                                 .cast<float>();
        }
    });
    if (near_rim) {
        // The rim and the samples next to it (one of its kSplitNeighbors nearest is a rim sample,
        // whose direction it takes): a sample pushed past the rim can have one of those closest.
        near_rim->assign(outward.begin(), outward.end());
        for (std::size_t i = 0; i < n; ++i)
            if (outward[i] == Vec3f::Zero())
                for (const std::uint32_t j : knn.Row(i).first(kSplitNeighbors))
                    if (outward[j] != Vec3f::Zero()) {
                        (*near_rim)[i] = outward[j];
                        break;
                    }
    }
    return outward;
}

// Regions of `flagged` samples (sorted indices of m): groups linked where one is among the other's
// kSplitNeighbors nearest (union-find over the rows of `nn`).
std::size_t CountRegions(std::span<const std::uint32_t> flagged, const KnnTable& nn,
                         std::size_t m) {
    std::vector<std::uint32_t> parent(m, UINT32_MAX);
    for (const std::uint32_t i : flagged) parent[i] = i;
    const auto find = [&](std::uint32_t i) {
        while (parent[i] != i) i = parent[i] = parent[parent[i]];
        return i;
    };
    std::size_t regions = flagged.size();
    for (const std::uint32_t i : flagged)
        for (const std::uint32_t j :
             nn.Row(i).first(std::min<std::size_t>(kSplitNeighbors, nn.Row(i).size())))
            if (j != UINT32_MAX && parent[j] != UINT32_MAX) {
                const std::uint32_t a = find(i), b = find(j);
                if (a != b) parent[std::max(a, b)] = std::min(a, b), --regions;
            }
    return regions;
}

// Dynamic sampling (notes 3.2.2-3.2.3): rounds of measuring the local spacing, splitting every
// sample whose tangent ellipse is too long along its main axis into two on that axis, relaxing;
// then a final MLS projection and attributes from the zombies (the input, never moved).
void RunSplit(const PointCloud& input, const KdTree& input_tree, std::span<const Vec3f> normals,
              const ResampleOptions& options, ProgressTracker& tracker, PointCloud& out,
              ResampleReport& report) {
    ParticleEngine::Shared shared;
    shared.tree = &input_tree;
    const ParticleEngine engine(input, normals, {}, false, shared);
    const double area = engine.WeightedArea();
    double s = options.spacing;
    if (s == 0) s = std::sqrt(area / (std::sqrt(3.0) / 2.0 * static_cast<double>(options.target)));
    // Refused before it starts: the points a lattice of that spacing needs, with the factor 2
    // a split round can overshoot by.
    const double lattice = area / (std::sqrt(3.0) / 2.0 * s * s);
    if (!(2.0 * lattice <= static_cast<double>(kMaxResampleTarget))) {
        std::ostringstream msg;
        msg << "gives about " << lattice << " points on this input (area " << area << "); the split method needs "
            << "twice that to lie within " << static_cast<double>(kMaxResampleTarget);
        InvalidField(options.spacing != 0 ? "spacing" : "target", msg.str());
    }
    std::vector<Vec3f> pos(input.positions), nrm(normals.begin(), normals.end());
    std::vector<float> extent;
    std::vector<Vec3f> axis;
    std::vector<std::uint8_t> rim;
    std::vector<std::size_t> above;  // samples above the target, per round
    // Each sample's closest input sample (its normal's and rim direction's source).
    std::vector<std::uint32_t> home(pos.size());
    std::iota(home.begin(), home.end(), 0u);
    std::vector<Vec3f> near_rims;
    const std::vector<Vec3f> rims = InputRims(input_tree, normals, &near_rims);
    // Stretch (3.2.2) of every sample (MeasureStretch: the spacing along its tangent ellipse's
    // main axis and that axis; at a rim, of the interior side only) into extent, axis and rim;
    // returns the kSplitNeighbors-nearest table. The kSplitBoundaryNeighbors-row (whose first
    // columns are the table's row) only for samples whose closest input sample is at a rim.
    const auto measure = [&](const KdTree& tree) {
        const std::size_t m = pos.size();
        const KnnTable nn = tree.KnnAll(std::min<int>(kSplitNeighbors, static_cast<int>(m) - 1));
        const int kb = std::min<int>(kSplitBoundaryNeighbors, static_cast<int>(m) - 1);
        extent.assign(m, 0.0f);
        axis.assign(m, Vec3f::Zero());
        rim.assign(m, 0);
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, m, 1024), [&](const auto& range) {
            std::array<std::uint32_t, kSplitBoundaryNeighbors> row{};
            std::vector<Neighbor> scratch;
            for (std::size_t i = range.begin(); i != range.end(); ++i) {
                const Vec3f& outward = near_rims[home[i]];
                std::span<const std::uint32_t> r = nn.Row(i);
                if (outward != Vec3f::Zero() && kb == kSplitBoundaryNeighbors) {
                    tree.KnnRow(i, kb, row.data(), nullptr, scratch);
                    r = row;
                }
                const Stretch st = MeasureStretch(pos, i, nrm[i], outward, r);
                extent[i] = st.extent;
                axis[i] = st.axis;
                rim[i] = st.rim;
            }
        });
        return nn;
    };
    int round = 0;
    for (; round < kMaxSplitRounds; ++round) {
        tracker.Check();
        // Stretch (3.2.2): the tangent ellipse of each sample's neighbourhood.
        const std::size_t m = pos.size();
        const KdTree tree(pos);
        const KnnTable nn = measure(tree);
        std::vector<std::uint32_t> split;
        for (std::size_t i = 0; i < m; ++i)
            if (extent[i] > kSplitSlack * s) split.push_back(static_cast<std::uint32_t>(i));
        // Stop when every region meets the target; or when the regions left are a small share
        // of the samples (kSplitStallShare) that kSplitStallRounds rounds of splitting did not
        // halve: splitting does not converge there (the report counts them).
        above.push_back(split.size());
        report.above_target = split.size();
        const std::size_t r = above.size() - 1;
        if (split.empty() ||
            (r >= kSplitStallRounds &&
             static_cast<double>(split.size()) <= kSplitStallShare * static_cast<double>(m) &&
             static_cast<double>(split.size()) >
                 kSplitStallRatio * static_cast<double>(above[r - kSplitStallRounds]))) {
            report.above_target_regions = CountRegions(split, nn, m);
            break;
        }
        // Split (fig. 3.15): p -> p -+ a/4 e on the main axis, a the spacing along it.
        for (const std::uint32_t i : split) {
            const Vec3f off = (0.25f * extent[i]) * axis[i];
            pos.push_back(pos[i] + off);
            nrm.push_back(nrm[i]);
            home.push_back(home[i]);
            pos[i] -= off;
        }
        report.splits += split.size();
        // Relaxation (3.2.3): repulsion within the target spacing, kept on the surface, of the
        // samples within kSplitRelaxReach spacings of a split (a filter that "redistributes the
        // samples locally"): the rest, which met the spacing in an earlier round, stay put. On
        // the bunny at s = 0.001 the rounds after the first split 10-1,000 samples each, and
        // relaxing every sample in each round took 11.6 s of an 11.6 s job (then 2.2 s, NN CV
        // 0.066 -> 0.085). Moves near the input's rims stay within kRimMargin of them (Relax).
        std::vector<std::uint8_t> movable(pos.size(), 0);
        {
            const float reach = static_cast<float>(kSplitRelaxReach * s);
            const UniformGrid grid(pos, reach);
            for (std::size_t t = 0; t < split.size(); ++t)
                for (const std::size_t i : {std::size_t{split[t]}, m + t})
                    grid.ForEachWithin(pos[i], reach, [&](std::uint32_t j, const Vec3f&, float) { movable[j] = 1; });
        }
        engine.Relax(pos, kSplitRelaxRadius * s, kSplitRelaxIterations, &movable, rims);
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, pos.size(), 1024),
                          [&](const auto& range) {
                              for (std::size_t i = range.begin(); i != range.end(); ++i) {
                                  home[i] = engine.tree().Nearest(pos[i]).index;
                                  nrm[i] = normals[home[i]];
                              }
                          });
        tracker.Advance(0.7 / kMaxSplitRounds);
    }
    report.iterations = round;
    if (round == kMaxSplitRounds) {
        // Ran out of rounds: what the last round's splits left, measured once more.
        const KdTree tree(pos);
        const KnnTable nn = measure(tree);
        std::vector<std::uint32_t> left;
        for (std::size_t i = 0; i < pos.size(); ++i)
            if (extent[i] > kSplitSlack * s) left.push_back(static_cast<std::uint32_t>(i));
        report.above_target = left.size();
        report.above_target_regions = CountRegions(left, nn, pos.size());
    }
    report.rim_samples =
        static_cast<std::size_t>(std::count(rim.begin(), rim.end(), std::uint8_t{1}));
    report.max_spacing = extent.empty() ? 0.0 : *std::max_element(extent.begin(), extent.end());
    // Final MLS projection (as the particle engine's), normals like the closest input normal.
    const MlsSurface mls(input, engine.tree());
    const MlsSurface::Batch batch = mls.ProjectAll(pos);
    for (std::size_t p = 0; p < pos.size(); ++p)
        if (batch.normals[p].allFinite() && batch.normals[p].squaredNorm() > 0.5f && batch.positions[p].allFinite() &&
            (batch.positions[p] - pos[p]).norm() < s) {
            pos[p] = batch.positions[p];
            nrm[p] = batch.normals[p].dot(nrm[p]) < 0 ? Vec3f(-batch.normals[p]) : batch.normals[p];
        }
    tracker.Advance(0.1);
    out.positions = std::move(pos);
    out.normals = std::move(nrm);
    out.color_type = input.color_type;
    out.color_has_alpha = input.color_has_alpha;
    InterpolateAttributes(input, engine.tree(), 0, out);
    tracker.Advance(0.1);
}

}  // namespace

const char* ResampleMethodName(ResampleMethod method) {
    switch (method) {
        case ResampleMethod::kParticle: return "particle";
        case ResampleMethod::kMls: return "mls";
        case ResampleMethod::kSplit: return "split";
    }
    return "?";
}

std::optional<ResampleMethod> ParseResampleMethod(std::string_view name) {
    for (ResampleMethod m : kResampleMethods)
        if (name == ResampleMethodName(m)) return m;
    return std::nullopt;
}

// Validation: one check per field in the order of the job spec, then the combinations.
void ResampleOptions::Validate() const {
    if (std::find(kResampleMethods.begin(), kResampleMethods.end(), method) == kResampleMethods.end())
        InvalidField("method", "unknown method " + std::to_string(static_cast<int>(method)));
    if (method == ResampleMethod::kMls && (target > 0 || spacing != 0))
        InvalidField("target", "the mls method keeps the input's points; give neither target nor spacing");
    if (target > 0 && spacing != 0) InvalidField("target", "give target or spacing, not both");
    if (target == 0 && spacing == 0 && method != ResampleMethod::kMls) InvalidField("target", "give target or spacing");
    if (target > 0) CheckRange("target", static_cast<double>(target), 1.0, static_cast<double>(kMaxResampleTarget));
    if (spacing != 0) CheckPositive("spacing", spacing);
    CheckRange("iterations", iterations, 0, kMaxResampleIterations);
    CheckRange("relax_tolerance", relax_tolerance, 0.0, 1.0);
    CheckRange("mls_degree", mls_degree, kMinMlsDegree, kMaxMlsDegree);
    CheckAtLeast("mls_h", mls_h, 0.0);
    if (method == ResampleMethod::kMls && keep_input)
        InvalidField("keep_input", "the mls method moves every input point; it cannot keep them");
    if (method == ResampleMethod::kSplit && keep_input)
        InvalidField("keep_input", "the split method splits and relaxes the input's points; it cannot keep them");
}

std::array<double, 2> NearestNeighborSpacing(std::span<const Vec3f> points) {
    SURFEL_CHECK(points.size() >= 2);
    return NearestNeighborSpacing(KdTree(points));
}

std::array<double, 2> NearestNeighborSpacing(const KdTree& tree) {
    const std::span<const Vec3f> points = tree.points();
    SURFEL_CHECK(points.size() >= 2);
    // The grid's exact nearest distances (KthNeighborDistances), ~2x cheaper than KnnAll(1).
    const std::vector<float> nn = KthNeighborDistances(points, 1, &tree);
    double sum = 0.0, sum2 = 0.0;
    for (std::size_t i = 0; i < points.size(); ++i) {
        const double d = static_cast<double>(nn[i]);
        sum += d;
        sum2 += d * d;
    }
    const double count = static_cast<double>(points.size()), mean = sum / count;
    const double var = std::max(0.0, sum2 / count - mean * mean);
    return {mean, mean > 0 ? std::sqrt(var) / mean : 0.0};
}

ResampleResult Resample(const PointCloud& input, const ResampleOptions& options, const ProgressFn& progress) {
    options.Validate();
    const std::size_t n = input.size();
    if (n < kMinResampleInput)
        throw Error(ErrorCode::kInvalidArgument, "resample: the input has " + std::to_string(n) +
                                                     " points; a surface needs at least " +
                                                     std::to_string(kMinResampleInput));
    input.CheckConsistent();
    ResampleResult result;
    ResampleReport& report = result.report;
    report.method = ResampleMethodName(options.method);
    report.adaptive = options.adaptive;
    report.keep_input = options.keep_input;
    report.input_points = n;
    report.iterations = options.method == ResampleMethod::kParticle ? options.iterations : 0;  // split: its rounds
    ProgressTracker tracker(progress, 1.2, "resampling");
    const Stopwatch clock;

    // Oriented normals (notes 1.2) and, for the adaptive variant, the surface variation.
    // One kd-tree over the input for every method; where the normals are estimated, one
    // k = 16 table for them, their orientation graph and the particle engine (walk graph,
    // sampling density, adaptive variation).
    const KdTree tree(input.positions);
    KnnTable knn;
    std::vector<Vec3f> normals = input.normals;
    std::vector<float> variation;
    if (normals.empty() || (options.adaptive && options.method == ResampleMethod::kParticle)) {
        NormalOptions no;
        no.k = std::min<int>(16, static_cast<int>(n) - 1);
        no.orient_k = std::min<int>(10, static_cast<int>(n) - 1);
        no.orient = normals.empty();
        knn = tree.KnnAll(no.k);
        NormalResult nr = EstimateNormals(tree, knn, no);
        if (normals.empty()) {
            normals = std::move(nr.normals);
            report.normals_estimated = true;
        }
        variation = std::move(nr.surface_variation);
    }
    tracker.Advance(0.1);

    PointCloud& out = result.cloud;
    switch (options.method) {
        case ResampleMethod::kParticle:
            RunParticles(input, tree, knn.k ? &knn : nullptr, normals, variation, options, tracker,
                         out, report);
            break;
        case ResampleMethod::kMls:
            RunMls(input, tree, normals, options, tracker, out, report);
            break;
        case ResampleMethod::kSplit:
            RunSplit(input, tree, normals, options, tracker, out, report);
            break;
    }

    // Splat radius: the spacing eta of the output's own sampling density (notes 1.1.1).
    if (out.size() >= 2) {
        const KdTree out_tree(out.positions);  // one tree for the radii and the spacing figures
        out.radii = ComputeSamplingDensity(out_tree, std::min<int>(6, static_cast<int>(out.size()) - 1)).spacing;
        const std::array<double, 2> s = NearestNeighborSpacing(out_tree);
        report.spacing_mean = s[0];
        report.spacing_cv = s[1];
    } else {
        out.radii.assign(out.size(), input.radii.empty() ? 0.0f : input.radii.front());
    }
    tracker.Advance(0.1);
    report.time_ms = clock.ElapsedMs();
    report.output_points = out.size();

    if (options.measure_error && out.size() >= kMinResampleInput) {
        const Stopwatch error_clock;
        SurfaceErrorOptions eo;
        eo.max_samples = options.error_samples;
        eo.seed = options.seed;
        report.error = MeasureSurfaceError(input, out, eo);
        report.error_time_ms = error_clock.ElapsedMs();
    }
    return result;
}

}  // namespace surfel
