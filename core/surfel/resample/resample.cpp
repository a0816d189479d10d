#include "surfel/resample/resample.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <sstream>
#include <string>

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/resample/particle_engine.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/poly_fit.h"

namespace surfel {
namespace {

// Interpolation filter (notes 3.2.3): the attributes of a new sample from the original samples,
// which never move (the notes' zombies). A Gaussian-weighted linear fit a(u, v) = c0 + c1 u + c2 v
// over the k nearest originals in the tangent plane at x, evaluated at x (c0): exact for
// attributes linear along the surface, unlike a plain average, whose error grows with the
// offset of the neighbours' weighted centroid. The weighted mean where the neighbours are
// (nearly) collinear (kMinConditioning).
constexpr int kInterpolationNeighbors = 10;
// Smallest eigenvalue ratio of the fit's normal matrix (in units of the k-th distance): below
// it the neighbours are too close to a line for a stable slope, and the weighted mean is used.
constexpr double kMinConditioning = 1e-2;

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
    const LocalFrame frame = LocalFrame::FromNormal(x.cast<double>(), normal.cast<double>());
    // Rows past `count` stay zero with zero weight.
    Eigen::Matrix<double, kInterpolationNeighbors, 3> A = Eigen::Matrix<double, kInterpolationNeighbors, 3>::Zero();
    Eigen::Matrix<double, kInterpolationNeighbors, 1> theta = Eigen::Matrix<double, kInterpolationNeighbors, 1>::Zero();
    double theta_sum = 0.0;
    for (int j = 0; j < w.count; ++j) {
        w.index[j] = row[j];
        const Vec3d l = frame.ToLocal(points[row[j]].cast<double>());
        const double s = std::sqrt(h2);
        A.row(j) << 1.0, l.x() / s, l.y() / s;  // scaled to O(1)
        theta[j] = std::exp(-static_cast<double>(dist2[j]) / h2);
        theta_sum += theta[j];
    }
    // Weighted least squares: c = (A^T W A)^-1 A^T W a; the first row of that operator gives the
    // weights of the values.
    const Eigen::Matrix3d M = A.transpose() * theta.asDiagonal() * A;
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(M);
    if (eig.info() == Eigen::Success && eig.eigenvalues()[0] > kMinConditioning * eig.eigenvalues()[2]) {
        const Eigen::Vector3d e0 = M.ldlt().solve(Eigen::Vector3d::UnitX());
        for (int j = 0; j < w.count; ++j) w.weight[j] = theta[j] * A.row(j).dot(e0);
    } else {
        for (int j = 0; j < w.count; ++j) w.weight[j] = theta[j] / theta_sum;
    }
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

}  // namespace

const char* ResampleMethodName(ResampleMethod method) {
    switch (method) {
        case ResampleMethod::kParticle: return "particle";
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
    if (target > 0 && spacing != 0) InvalidField("target", "give target or spacing, not both");
    if (target == 0 && spacing == 0) InvalidField("target", "give target or spacing");
    if (target > 0) CheckRange("target", static_cast<double>(target), 1.0, static_cast<double>(kMaxResampleTarget));
    if (spacing != 0) CheckPositive("spacing", spacing);
    CheckRange("iterations", iterations, 0, kMaxResampleIterations);
}

std::array<double, 2> NearestNeighborSpacing(std::span<const Vec3f> points) {
    SURFEL_CHECK(points.size() >= 2);
    const KdTree tree(points);
    const KnnTable nn = tree.KnnAll(1);
    double sum = 0.0, sum2 = 0.0;
    for (std::size_t i = 0; i < points.size(); ++i) {
        const double d = std::sqrt(static_cast<double>(nn.Dist2(i)[0]));
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
    report.iterations = options.iterations;
    ProgressTracker tracker(progress, 1.2, "resampling");
    const Stopwatch clock;

    // Oriented normals (notes 1.2) and, for the adaptive variant, the surface variation.
    std::vector<Vec3f> normals = input.normals;
    std::vector<float> variation;
    if (normals.empty() || options.adaptive) {
        const KdTree tree(input.positions);
        NormalOptions no;
        no.k = std::min<int>(16, static_cast<int>(n) - 1);
        no.orient_k = std::min<int>(10, static_cast<int>(n) - 1);
        no.orient = normals.empty();
        NormalResult nr = EstimateNormals(tree, no);
        if (normals.empty()) {
            normals = std::move(nr.normals);
            report.normals_estimated = true;
        }
        variation = std::move(nr.surface_variation);
    }
    tracker.Advance(0.1);

    // Particle simulation (2.3): the new points; with keep_input the input repels them.
    const ParticleEngine engine(input, normals, variation, options.adaptive);
    const std::size_t count = OutputCount(options, engine, n);
    ParticleParams params;
    params.seed = options.seed;
    params.iterations = options.iterations;
    params.fixed_input = options.keep_input;
    params.count = options.keep_input ? count - n : count;
    std::vector<Vec3f> positions, particle_normals;
    engine.Run(params, positions, particle_normals, tracker);

    // The output: kept input points first, then the particles.
    PointCloud& out = result.cloud;
    const std::size_t first = options.keep_input ? n : 0;
    out.positions.reserve(count);
    out.normals.reserve(count);
    if (options.keep_input) {
        out.positions = input.positions;
        out.normals = normals;
        out.colors = input.colors;
        for (const ExtraAttribute& e : input.extras) out.extras.push_back(e);
    }
    out.positions.insert(out.positions.end(), positions.begin(), positions.end());
    out.normals.insert(out.normals.end(), particle_normals.begin(), particle_normals.end());
    out.color_type = input.color_type;
    out.color_has_alpha = input.color_has_alpha;
    InterpolateAttributes(input, engine.tree(), first, out);

    // Splat radius: the spacing eta of the output's own sampling density (notes 1.1.1).
    if (out.size() >= 2) {
        out.radii = ComputeSamplingDensity(out.positions, std::min<int>(6, static_cast<int>(out.size()) - 1)).spacing;
        const std::array<double, 2> s = NearestNeighborSpacing(out.positions);
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
