#include "surfel/boolean/boolean.h"

#include "surfel/boolean/classifier.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <atomic>
#include <exception>
#include <limits>
#include <memory>
#include <cmath>
#include <sstream>
#include <unordered_map>

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/spatial/kd_tree.h"

namespace surfel {
// ---------------------------------------------------------------------------------------------
// Names and options
// ---------------------------------------------------------------------------------------------

const char* BooleanOpName(BooleanOp op) {
    switch (op) {
        case BooleanOp::kUnion:
            return "union";
        case BooleanOp::kIntersection:
            return "intersection";
        case BooleanOp::kDifference:
            return "difference";
        case BooleanOp::kReverseDifference:
            return "reverse-difference";
    }
    return "unknown";
}

std::optional<BooleanOp> ParseBooleanOp(std::string_view name) {
    for (BooleanOp op : kBooleanOps)
        if (name == BooleanOpName(op)) return op;
    return std::nullopt;
}

void Similarity::Validate(const std::string& prefix) const {
    if (!rotation.allFinite()) InvalidField(prefix + ".rotation", "must be finite");
    const double off =
        (rotation.transpose() * rotation - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
    if (off > kRotationTolerance) {
        std::ostringstream msg;
        msg << "must be orthonormal (|R^T R - I| = " << off << " > " << kRotationTolerance << ")";
        InvalidField(prefix + ".rotation", msg.str());
    }
    const double det = rotation.determinant();
    if (std::abs(det - 1.0) > kRotationTolerance) {
        std::ostringstream msg;
        msg << "must be a rotation (det = " << det
            << ", a reflection would turn the solid inside out)";
        InvalidField(prefix + ".rotation", msg.str());
    }
    CheckFinite(prefix + ".translation", translation);
    CheckRange(prefix + ".scale", scale, kMinBooleanScale, kMaxBooleanScale);
}

void BooleanOptions::Validate() const {
    transform.Validate("transform");
    WithFieldPrefix("mls", [&] { mls.Validate(); });
    WithFieldPrefix("normals", [&] { normals.Validate(); });
    CheckRange("curve_band", curve_band, kMinCurveBand, kMaxCurveBand);
    CheckRange("max_newton_iterations", max_newton_iterations, kMinNewtonIterations,
               kMaxNewtonIterations);
    CheckRange("newton_tolerance", newton_tolerance, kMinNewtonTolerance, kMaxNewtonTolerance);
    CheckRange("max_refinement_rounds", max_refinement_rounds, 0, kMaxRefinementRounds);
    CheckRange("max_open_area", max_open_area, 0.0, kMaxOpenArea);
    CheckRange("coincident_tolerance", coincident_tolerance, 0.0, kMaxCoincidentTolerance);
    if (upsample_ratio != 0)
        CheckRange("upsample_ratio", upsample_ratio, kMinUpsampleRatio, kMaxUpsampleRatio);
    CheckAtLeast("blend_radius", blend_radius, 0.0);
    CheckRange("blend_iterations", blend_iterations, kMinBlendIterations, kMaxBlendIterations);
}

namespace {

constexpr double kPi = 3.14159265358979323846;

// ---------------------------------------------------------------------------------------------
// One input: its samples with outward normals, kd-tree, spacing, MLS surface and placement.
// ---------------------------------------------------------------------------------------------

struct Side {
    std::string name;                   // "a" or "b", for messages
    const PointCloud* cloud = nullptr;  // the input, or *own when normals were estimated
    std::shared_ptr<PointCloud> own;
    const PointCloud* input = nullptr;  // as given (its radii)
    // Shared with the other side when both inputs are the same cloud (SharePrepared).
    std::shared_ptr<const KdTree> tree;
    std::shared_ptr<const SamplingDensity> density;  // eta_i in the input's own frame
    std::shared_ptr<const MlsSurface> mls;
    bool normals_estimated = false;
    // Placement: world = s R x + t.
    Eigen::Matrix3f R = Eigen::Matrix3f::Identity();
    Vec3f t = Vec3f::Zero();
    float s = 1.0f;
    bool identity = true;
    float max_spacing_world = 0.0f;

    Vec3f ToLocal(const Vec3f& x) const {
        return identity ? x : Vec3f(R.transpose() * (x - t) / s);
    }
    Vec3f ToWorld(const Vec3f& p) const { return identity ? p : Vec3f(s * (R * p) + t); }
    Vec3f NormalToWorld(const Vec3f& n) const { return identity ? n : Vec3f(R * n); }
    Vec3f Position(std::uint32_t i) const { return ToWorld(cloud->positions[i]); }
    Vec3f Normal(std::uint32_t i) const { return NormalToWorld(cloud->normals[i]); }
    float Spacing(std::uint32_t i) const { return s * density->spacing[i]; }
    std::size_t size() const { return cloud->size(); }

    // MLS projection of a world point; world position and normal.
    std::optional<MlsPoint> Project(const Vec3f& x) const {
        auto y = mls->Project(ToLocal(x));
        if (!y) return std::nullopt;
        y->position = ToWorld(y->position);
        y->normal = NormalToWorld(y->normal).normalized();
        return y;
    }
};

// The checks of one input that need no work: enough points, finite positions.
void CheckInput(const std::string& name, const PointCloud& input) {
    if (input.size() < kMinBooleanInput) {
        std::ostringstream msg;
        msg << "needs at least " << kMinBooleanInput << " points to bound a volume, got "
            << input.size();
        InvalidField(name, msg.str());
    }
    for (const Vec3f& p : input.positions)
        if (!p.allFinite()) InvalidField(name, "has a non-finite position");
}

void Place(Side& side, const BooleanOptions& options, bool placed) {
    if (placed) {
        const Similarity& T = options.transform;
        side.R = T.rotation.cast<float>();
        side.t = T.translation.cast<float>();
        side.s = static_cast<float>(T.scale);
        side.identity = T.rotation.isIdentity(0.0) && T.translation.isZero(0.0) && T.scale == 1.0;
    }
    float mx = 0;
    for (float e : side.density->spacing) mx = std::max(mx, e);
    side.max_spacing_world = side.s * mx;
}

void PrepareSide(Side& side, const PointCloud& input, const BooleanOptions& options, bool placed) {
    CheckInput(side.name, input);
    const auto tree = std::make_shared<KdTree>(input.positions);
    side.tree = tree;
    side.cloud = &input;
    side.input = &input;
    if (!input.has_normals()) {
        NormalOptions no = options.normals;
        no.orient = true;
        side.own = std::make_shared<PointCloud>();
        side.own->positions = input.positions;
        side.own->normals = EstimateNormals(*tree, no).normals;
        side.cloud = side.own.get();
        side.normals_estimated = true;
    }
    side.density = std::make_shared<const SamplingDensity>(ComputeSamplingDensity(*tree, 6));
    Place(side, options, placed);
    MlsOptions mo = options.mls;
    if (mo.h > 0) {
        mo.h /= side.s;  // options.mls.h is in world units
    } else if (!mo.adaptive && mo.scale_rule == MlsScaleRule::kSpacing) {
        // The spacing rule's h (2 x the median spacing, MlsSurface's default) from the spacing
        // just computed: the same value, one neighbour search less.
        mo.h = 2.0f * MedianSpacing(*side.density);
    }
    side.mls = std::make_shared<const MlsSurface>(*side.cloud, *tree, mo);
}

// Whether B can take A's prepared samples (kd-tree, normals, spacing, MLS surface) as they are:
// the same positions and the same normals (or none on both), and an MLS scale that does not
// depend on the placement (derived from the spacing, or B not scaled). B ∪ a moved copy of
// itself (the notes' Figure 3.3) then prepares one input, not two.
bool SameSolid(const PointCloud& a, const PointCloud& b, const BooleanOptions& options) {
    if (a.positions != b.positions || a.has_normals() != b.has_normals()) return false;
    if (a.has_normals() && a.normals != b.normals) return false;
    return options.mls.h == 0 || options.transform.scale == 1.0;
}

// B from A's prepared data (SameSolid): only the name, the input (its radii) and the placement
// are B's own.
void SharePrepared(Side& b, const Side& a, const PointCloud& input, const BooleanOptions& options) {
    b.tree = a.tree;
    b.own = a.own;
    b.cloud = a.own ? a.own.get() : &input;
    b.input = &input;
    b.density = a.density;
    b.mls = a.mls;
    b.normals_estimated = a.normals_estimated;
    Place(b, options, true);
}

// Both inputs prepared: concurrently (each preparation has serial parts, such as the normal
// orientation's spanning tree), or once when B is the same cloud as A. An error names A's input
// first, as a serial preparation would.
void PrepareSides(Side& A, const PointCloud& a, Side& B, const PointCloud& b,
                  const BooleanOptions& options) {
    CheckInput(A.name, a);
    CheckInput(B.name, b);
    if (SameSolid(a, b, options)) {
        PrepareSide(A, a, options, false);
        SharePrepared(B, A, b, options);
        return;
    }
    std::exception_ptr error_a, error_b;
    tbb::parallel_invoke(
        [&] {
            try {
                PrepareSide(A, a, options, false);
            } catch (...) {
                error_a = std::current_exception();
            }
        },
        [&] {
            try {
                PrepareSide(B, b, options, true);
            } catch (...) {
                error_b = std::current_exception();
            }
        });
    if (error_a) std::rethrow_exception(error_a);
    if (error_b) std::rethrow_exception(error_b);
}

// ---------------------------------------------------------------------------------------------
// Does the input bound a volume? On a closed surface the vector area vanishes (divergence
// theorem: the integral of n dA over a closed surface is 0); on one with holes it is the holes'
// vector area. Estimated as sum_i eta_i^2 n_i over the samples (eta_i^2 = 1 / rho_i, the area a
// sample stands for, notes 1.1.1) relative to sum_i eta_i^2.
// ---------------------------------------------------------------------------------------------

void CheckBoundsVolume(const Side& side, double max_open_area) {
    if (max_open_area <= 0) return;
    Vec3d flux = Vec3d::Zero();
    double area = 0;
    for (std::uint32_t i = 0; i < side.size(); ++i) {
        const double a = double{side.density->spacing[i]} * side.density->spacing[i];
        flux += a * side.cloud->normals[i].cast<double>();
        area += a;
    }
    const double open = area > 0 ? flux.norm() / area : 1.0;
    if (open > max_open_area) {
        std::ostringstream msg;
        msg << "does not bound a volume: its outward normals do not close (|sum a_i n_i| / sum a_i "
               "= "
            << open
            << ", the share of its area missing as holes; limit max_open_area = " << max_open_area
            << ")";
        InvalidField(side.name, msg.str());
    }
}

// ---------------------------------------------------------------------------------------------
// Classification Omega (3.1.1, eq. 3.1).
// ---------------------------------------------------------------------------------------------

// Omega of one query: outside, inside, or (a degenerate case the notes leave open) on the other
// surface, within coincident_tolerance spacings of its MLS projection, with the two normals
// agreeing (a shared face of two solids on the same side) or opposing (solids touching).
enum OmegaValue : std::uint8_t { kOutside = 0, kInside = 1, kOnSame = 2, kOnOpposite = 3 };

struct Omega {
    std::uint8_t value = kOutside;
    float clear = 0;  // a lower bound of the distance to the surface (world units)
    bool used_mls = false;
};

// Omega_P(x) for a world point x with outward normal n_x: closest sample p and its normal; the
// MLS projection where x lies within the spacing eta_p of p.
Omega Classify(const Side& side, const Vec3f& x, const Vec3f& nx, double coincident) {
    const Vec3f xl = side.ToLocal(x);
    const Neighbor nb = side.tree->Nearest(xl);
    const Vec3f& p = side.tree->points()[nb.index];
    const Vec3f& np = side.cloud->normals[nb.index];
    const float d = std::sqrt(nb.dist2), eta = side.density->spacing[nb.index];
    Omega o;
    if (d > eta) {
        o.value = (xl - p).dot(np) < 0 ? kInside : kOutside;
        o.clear = side.s * (d - eta);
        return o;
    }
    o.used_mls = true;
    if (auto y = side.mls->Project(xl)) {
        const float sd = (xl - y->position).dot(y->normal);
        if (std::abs(sd) < coincident * eta)
            o.value = side.NormalToWorld(y->normal).dot(nx) > 0 ? kOnSame : kOnOpposite;
        else
            o.value = sd < 0 ? kInside : kOutside;
    } else {
        o.value = (xl - p).dot(np) < 0 ? kInside : kOutside;
    }
    return o;
}

struct ClassifyStats {
    std::size_t queries = 0, saved = 0, mls = 0;
};

// 30-bit Morton code of a point in a box, for a coherent query order.
std::uint32_t Morton(const Vec3f& p, const BoundingBox& box) {
    const Vec3f ext = box.Extent().cwiseMax(Vec3f::Constant(1e-30f));
    std::uint32_t code = 0;
    std::uint32_t c[3];
    for (int a = 0; a < 3; ++a)
        c[a] = static_cast<std::uint32_t>(std::clamp((p[a] - box.min[a]) / ext[a], 0.0f, 1.0f) *
                                          1023.0f);
    for (int bit = 9; bit >= 0; --bit)
        for (int a = 0; a < 3; ++a) code = (code << 1) | ((c[a] >> bit) & 1u);
    return code;
}

// Omega_other at every sample of `self` (world positions). In Morton order, in fixed chunks;
// inside a chunk the last kSpheres coherence spheres (radius ||x - p|| - eta_p) answer queries
// that fall inside them. inside[i] and clear[i] (lower bound of the distance to the other
// surface) per sample. Deterministic: chunks do not depend on the thread count.
void ClassifyAll(const Side& self, const Side& other, const BooleanOptions& options,
                 std::vector<std::uint8_t>& inside, std::vector<float>& clear, ClassifyStats& stats,
                 ProgressTracker& tracker) {
    const std::size_t n = self.size();
    std::vector<Vec3f> x(n);
    for (std::uint32_t i = 0; i < n; ++i) x[i] = self.Position(i);
    BoundingBox box;
    for (const Vec3f& p : x) box.Extend(p);
    std::vector<std::uint64_t> key(n);
    for (std::uint32_t i = 0; i < n; ++i)
        key[i] = (static_cast<std::uint64_t>(Morton(x[i], box)) << 32) | i;
    std::sort(key.begin(), key.end());
    inside.assign(n, 0);
    clear.assign(n, 0.0f);
    constexpr std::size_t kChunk = 512;
    const std::size_t chunks = (n + kChunk - 1) / kChunk;
    std::atomic<std::size_t> saved{0}, mls{0};
    tbb::parallel_for(std::size_t{0}, chunks, [&](std::size_t c) {
        const bool coherence = options.coherence;
        CoherenceCache cache;
        std::size_t my_saved = 0, my_mls = 0;
        const std::size_t end = std::min(n, (c + 1) * kChunk);
        for (std::size_t k = c * kChunk; k < end; ++k) {
            const std::uint32_t i = static_cast<std::uint32_t>(key[k] & 0xffffffffu);
            if (coherence) {
                if (const auto found = cache.Find(x[i])) {
                    inside[i] = static_cast<std::uint8_t>(found->side);
                    clear[i] = found->clear;
                    ++my_saved;
                    continue;
                }
            }
            const Omega o = Classify(other, x[i], self.Normal(i), options.coincident_tolerance);
            inside[i] = o.value;
            clear[i] = o.clear;
            my_mls += o.used_mls;
            if (coherence) cache.Add(x[i], {static_cast<SolidSide>(o.value), o.clear});
        }
        saved += my_saved;
        mls += my_mls;
        tracker.Advance(static_cast<double>(end - c * kChunk));
    });
    stats.queries += n;
    stats.saved += saved;
    stats.mls += mls;
}

// ---------------------------------------------------------------------------------------------
// Intersection curve (3.1.2).
// ---------------------------------------------------------------------------------------------

struct CurveSample {
    Vec3f q;
    Vec3f na, nb;   // outward normals of S_A and S_B at q (world)
    float eta = 0;  // local spacing: the finer side's
    int iterations = 0;
};

// The point of the line of the two tangent planes (q1, n1), (q2, n2) closest to q1 and q2
// (minimises ||r - q1||^2 + ||r - q2||^2 on the line); nullopt for near-parallel planes.
std::optional<Vec3d> TangentLinePoint(const Vec3d& q1, const Vec3d& n1, const Vec3d& q2,
                                      const Vec3d& n2) {
    const double c = n1.dot(n2), det = 1.0 - c * c;
    if (det < 1e-6) return std::nullopt;
    const Vec3d m = 0.5 * (q1 + q2);
    const double b1 = n1.dot(q1 - m), b2 = n2.dot(q2 - m);
    const double a = (b1 - c * b2) / det, b = (b2 - c * b1) / det;
    return m + a * n1 + b * n2;
}

float LocalSpacing(const Side& side, const Vec3f& x) {
    return side.Spacing(side.tree->Nearest(side.ToLocal(x)).index);
}

// Newton-type iteration from (q1, n1) on S_A and (q2, n2) on S_B: r on the tangent-plane line,
// re-projected onto both MLS surfaces, until r lies on both within tol. nullopt if it does not
// converge, a plane pair is degenerate, a projection fails, or r wanders off farther than
// `reach` from its start.
std::optional<CurveSample> Newton(const Side& A, const Side& B, Vec3f q1, Vec3f n1, Vec3f q2,
                                  Vec3f n2, const BooleanOptions& options) {
    const Vec3f start = 0.5f * (q1 + q2);
    const float eta0 = std::min(LocalSpacing(A, start), LocalSpacing(B, start));
    const float reach = 4.0f * eta0 + (q1 - q2).norm();
    const double tol = options.newton_tolerance * eta0;
    for (int it = 1; it <= options.max_newton_iterations; ++it) {
        const auto r = TangentLinePoint(q1.cast<double>(), n1.cast<double>(), q2.cast<double>(),
                                        n2.cast<double>());
        if (!r || !r->allFinite()) return std::nullopt;
        const Vec3f rf = r->cast<float>();
        if ((rf - start).norm() > reach) return std::nullopt;
        const auto p1 = A.Project(rf);
        const auto p2 = B.Project(rf);
        if (!p1 || !p2) return std::nullopt;
        q1 = p1->position, n1 = p1->normal, q2 = p2->position, n2 = p2->normal;
        if ((q1 - rf).norm() < tol && (q2 - rf).norm() < tol) {
            CurveSample s;
            s.q = rf;
            s.na = n1;
            s.nb = n2;
            s.eta = std::min(LocalSpacing(A, rf), LocalSpacing(B, rf));
            s.iterations = it;
            return s;
        }
    }
    return std::nullopt;
}

// Newton from a start point that lies on neither surface: its projections start the iteration.
std::optional<CurveSample> NewtonFrom(const Side& A, const Side& B, const Vec3f& x,
                                      const BooleanOptions& options) {
    const auto p1 = A.Project(x);
    const auto p2 = B.Project(x);
    if (!p1 || !p2) return std::nullopt;
    return Newton(A, B, p1->position, p1->normal, p2->position, p2->normal, options);
}

// Curve samples kept at least half their local spacing apart, in arrival order.
class CurveSet {
  public:
    explicit CurveSet(float cell) : cell_(std::max(cell, 1e-30f)) {}

    bool TryAdd(const CurveSample& s) {
        const float min_dist = 0.5f * s.eta;
        const int reach = static_cast<int>(std::ceil(min_dist / cell_));
        const auto c = CellOf(s.q);
        for (int dx = -reach; dx <= reach; ++dx)
            for (int dy = -reach; dy <= reach; ++dy)
                for (int dz = -reach; dz <= reach; ++dz) {
                    auto it = cells_.find(Key(c[0] + dx, c[1] + dy, c[2] + dz));
                    if (it == cells_.end()) continue;
                    for (std::uint32_t j : it->second)
                        if ((samples_[j].q - s.q).squaredNorm() < min_dist * min_dist) return false;
                }
        cells_[Key(c[0], c[1], c[2])].push_back(static_cast<std::uint32_t>(samples_.size()));
        samples_.push_back(s);
        return true;
    }
    const std::vector<CurveSample>& samples() const { return samples_; }

  private:
    std::array<std::int64_t, 3> CellOf(const Vec3f& p) const {
        return {static_cast<std::int64_t>(std::floor(p.x() / cell_)),
                static_cast<std::int64_t>(std::floor(p.y() / cell_)),
                static_cast<std::int64_t>(std::floor(p.z() / cell_))};
    }
    static std::uint64_t Key(std::int64_t x, std::int64_t y, std::int64_t z) {
        return (static_cast<std::uint64_t>(x & 0x1fffff) << 42) |
               (static_cast<std::uint64_t>(y & 0x1fffff) << 21) |
               static_cast<std::uint64_t>(z & 0x1fffff);
    }
    float cell_;
    std::unordered_map<std::uint64_t, std::vector<std::uint32_t>> cells_;
    std::vector<CurveSample> samples_;
};

struct CurveStats {
    std::size_t seeds = 0, refined = 0, failures = 0;
    double iterations = 0;
    std::size_t converged = 0;
};

// Kept samples of `self` whose MLS distance to the other surface is below band local spacings.
std::vector<std::uint32_t> NearOther(const Side& self, const Side& other,
                                     const std::vector<std::uint8_t>& kept,
                                     const std::vector<float>& clear, double band) {
    const std::size_t n = self.size();
    std::vector<std::uint8_t> near(n, 0);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024),
                      [&](const tbb::blocked_range<std::size_t>& r) {
                          for (std::size_t i = r.begin(); i != r.end(); ++i) {
                              if (!kept[i]) continue;
                              const float eta_self = self.Spacing(static_cast<std::uint32_t>(i));
                              if (clear[i] > band * std::max(eta_self, other.max_spacing_world))
                                  continue;
                              const Vec3f x = self.Position(static_cast<std::uint32_t>(i));
                              const float eta = std::max(eta_self, LocalSpacing(other, x));
                              const auto y = other.Project(x);
                              near[i] = y && (y->position - x).norm() < band * eta;
                          }
                      });
    std::vector<std::uint32_t> out;
    for (std::uint32_t i = 0; i < n; ++i)
        if (near[i]) out.push_back(i);
    return out;
}

std::vector<CurveSample> SampleCurve(const Side& A, const Side& B,
                                     const std::vector<std::uint8_t>& kept_a,
                                     const std::vector<std::uint8_t>& kept_b,
                                     const std::vector<float>& clear_a,
                                     const std::vector<float>& clear_b,
                                     const BooleanOptions& options, CurveStats& stats,
                                     ProgressTracker& tracker) {
    const auto ca = NearOther(A, B, kept_a, clear_a, options.curve_band);
    const auto cb = NearOther(B, A, kept_b, clear_b, options.curve_band);
    tracker.Check();
    if (ca.empty() || cb.empty()) return {};
    // Closest pairs, from both sides, each pair once.
    std::vector<Vec3f> pa(ca.size()), pb(cb.size());
    for (std::size_t i = 0; i < ca.size(); ++i) pa[i] = A.Position(ca[i]);
    for (std::size_t i = 0; i < cb.size(); ++i) pb[i] = B.Position(cb[i]);
    const KdTree ta(pa), tb(pb);
    std::vector<std::uint64_t> pairs;
    for (std::uint32_t i = 0; i < ca.size(); ++i)
        pairs.push_back((std::uint64_t{i} << 32) | tb.Nearest(pa[i]).index);
    for (std::uint32_t j = 0; j < cb.size(); ++j)
        pairs.push_back((std::uint64_t{ta.Nearest(pb[j]).index} << 32) | j);
    std::sort(pairs.begin(), pairs.end());
    pairs.erase(std::unique(pairs.begin(), pairs.end()), pairs.end());
    stats.seeds = pairs.size();

    std::vector<std::optional<CurveSample>> found(pairs.size());
    tbb::parallel_for(std::size_t{0}, pairs.size(), [&](std::size_t k) {
        const std::uint32_t i = ca[pairs[k] >> 32], j = cb[pairs[k] & 0xffffffffu];
        found[k] = Newton(A, B, A.Position(i), A.Normal(i), B.Position(j), B.Normal(j), options);
    });
    // The hash cell of the spacing test: half the median local spacing of the converged samples.
    std::vector<float> half_eta;
    for (const auto& f : found)
        if (f) half_eta.push_back(0.5f * f->eta);
    if (half_eta.empty()) {
        stats.failures += found.size();
        return {};
    }
    std::nth_element(half_eta.begin(), half_eta.begin() + half_eta.size() / 2, half_eta.end());
    CurveSet set(half_eta[half_eta.size() / 2]);
    auto account = [&](const std::optional<CurveSample>& f) {
        if (!f) {
            ++stats.failures;
            return false;
        }
        stats.iterations += f->iterations;
        ++stats.converged;
        return set.TryAdd(*f);
    };
    for (const auto& f : found) account(f);
    tracker.Check();

    // Adaptive refinement (Figure 3.5): between neighbours farther apart than the local spacing
    // the midpoint starts a new iteration; where a sample has no neighbour within 3 spacings on
    // one side along the curve tangent, a start one spacing ahead continues the curve.
    const std::size_t cap = 4 * (A.size() + B.size());
    for (int round = 0; round < options.max_refinement_rounds; ++round) {
        const auto& cur = set.samples();
        std::vector<Vec3f> pos(cur.size());
        for (std::size_t i = 0; i < cur.size(); ++i) pos[i] = cur[i].q;
        const KdTree tree(pos);
        std::vector<std::array<std::optional<Vec3f>, 2>> starts(cur.size());
        tbb::parallel_for(std::size_t{0}, cur.size(), [&](std::size_t i) {
            std::vector<Neighbor> nb;
            const CurveSample& s = cur[i];
            const Vec3f tangent = s.na.cross(s.nb).normalized();
            if (!tangent.allFinite()) return;
            tree.Radius(s.q, 3.0f * s.eta, &nb);
            for (int side = 0; side < 2; ++side) {
                const Vec3f dir = side == 0 ? tangent : Vec3f(-tangent);
                float best = std::numeric_limits<float>::max();
                std::uint32_t bj = UINT32_MAX;
                for (const Neighbor& m : nb) {
                    if (m.index == i) continue;
                    const Vec3f d = cur[m.index].q - s.q;
                    if (d.dot(dir) > 0.5f * std::sqrt(m.dist2) && m.dist2 < best)
                        best = m.dist2, bj = m.index;
                }
                if (bj == UINT32_MAX)
                    starts[i][side] = s.q + s.eta * dir;
                else if (std::sqrt(best) > s.eta && i < bj)
                    starts[i][side] = 0.5f * (s.q + cur[bj].q);
            }
        });
        std::vector<Vec3f> flat;
        for (std::size_t i = 0; i < starts.size(); ++i)
            for (const auto& st : starts[i])
                if (st) flat.push_back(*st);
        if (flat.empty()) break;
        std::vector<std::optional<CurveSample>> res(flat.size());
        tbb::parallel_for(std::size_t{0}, flat.size(),
                          [&](std::size_t k) { res[k] = NewtonFrom(A, B, flat[k], options); });
        std::size_t added = 0;
        for (const auto& f : res) added += account(f);
        stats.refined += added;
        tracker.Check();
        if (added == 0 || set.samples().size() > cap) break;
    }
    return set.samples();
}

// ---------------------------------------------------------------------------------------------
// Output assembly.
// ---------------------------------------------------------------------------------------------

struct Output {
    PointCloud cloud;
    std::vector<double> crease, cnx, cny, cnz, source;

    void Add(const Vec3f& p, const Vec3f& n, float radius, int src,
             const Vec3f& n2 = Vec3f::Zero()) {
        cloud.positions.push_back(p);
        cloud.normals.push_back(n);
        cloud.radii.push_back(radius);
        crease.push_back(src == 2 ? 1.0 : 0.0);
        cnx.push_back(n2.x());
        cny.push_back(n2.y());
        cnz.push_back(n2.z());
        source.push_back(src);
    }
    PointCloud Finish() {
        cloud.extras.push_back({kCreaseAttribute, ScalarType::kUInt8, std::move(crease)});
        cloud.extras.push_back({kCreaseNormalX, ScalarType::kFloat32, std::move(cnx)});
        cloud.extras.push_back({kCreaseNormalY, ScalarType::kFloat32, std::move(cny)});
        cloud.extras.push_back({kCreaseNormalZ, ScalarType::kFloat32, std::move(cnz)});
        cloud.extras.push_back({kSourceAttribute, ScalarType::kUInt8, std::move(source)});
        cloud.CheckConsistent();
        return std::move(cloud);
    }
};

float Radius(const Side& side, std::uint32_t i) {
    return side.input->has_radii() ? side.s * side.input->radii[i] : side.Spacing(i);
}

void AddSide(Output& out, const Side& side, const std::vector<std::uint8_t>& keep, bool flip,
             int src) {
    for (std::uint32_t i = 0; i < side.size(); ++i) {
        if (!keep[i]) continue;
        const Vec3f n = side.Normal(i);
        out.Add(side.Position(i), flip ? Vec3f(-n) : n, Radius(side, i), src);
    }
}

// Table 3.1 for one sample of A (of_a) or B with Omega value v. On a coincident face
// (regularised CSG): a shared face with the solids on the same side stays once (A's copy) in the
// union and the intersection and goes in both differences; a face where the solids touch goes in
// the union and the intersection and stays on the minuend's side of a difference.
bool Keep(std::uint8_t v, bool of_a, BooleanOp op) { return TableKeeps(static_cast<SolidSide>(v), of_a, op); }

}  // namespace

bool TableKeeps(SolidSide side, bool of_a, BooleanOp op) {
    const std::uint8_t v = static_cast<std::uint8_t>(side);
    bool want_inside = false;
    switch (op) {
        case BooleanOp::kUnion:
            want_inside = false;
            break;
        case BooleanOp::kIntersection:
            want_inside = true;
            break;
        case BooleanOp::kDifference:
            want_inside = !of_a;
            break;
        case BooleanOp::kReverseDifference:
            want_inside = of_a;
            break;
    }
    switch (v) {
        case kOutside:
            return !want_inside;
        case kInside:
            return want_inside;
        case kOnSame:
            return of_a && (op == BooleanOp::kUnion || op == BooleanOp::kIntersection);
        case kOnOpposite:
            return of_a ? op == BooleanOp::kDifference : op == BooleanOp::kReverseDifference;
    }
    return false;
}

namespace {

// Up-sampling of the coarser input near the curve (3.1.2, by the splitting of 3.2.2): a kept
// sample of `self` within 2 of its spacings eta of a curve sample where the other input is more
// than options.upsample_ratio times finer is replaced by an n x n grid over the square of side
// eta it stands for in its tangent plane (n = round(eta / eta_other), at most
// kMaxUpsampleFactor), each point MLS-projected onto its own surface and kept where Table 3.1
// keeps it. Returns the new samples (world position, outward normal of the input, radius).
struct NewSample {
    Vec3f p, n;
    float radius;
};

// The nearest of `tree`'s points within `radius` of q (ties by the smaller index, as
// KdTree::Nearest); index UINT32_MAX when there is none. `scratch` is reused.
Neighbor NearestWithin(const KdTree& tree, const Vec3f& q, float radius, std::vector<Neighbor>& scratch) {
    tree.Radius(q, radius, &scratch);
    Neighbor best{UINT32_MAX, std::numeric_limits<float>::infinity()};
    for (const Neighbor& c : scratch)
        if (c.dist2 < best.dist2 || (c.dist2 == best.dist2 && c.index < best.index)) best = c;
    return best;
}

std::vector<NewSample> Upsample(const Side& self, const Side& other, bool of_a, BooleanOp op,
                                std::vector<std::uint8_t>& keep,
                                const std::vector<CurveSample>& curve,
                                const BooleanOptions& options, std::size_t& replaced) {
    replaced = 0;
    if (options.upsample_ratio <= 0 || curve.empty()) return {};
    std::vector<Vec3f> cq(curve.size());
    std::vector<float> eta_other(curve.size());
    for (std::size_t j = 0; j < curve.size(); ++j) {
        cq[j] = curve[j].q;
        eta_other[j] = LocalSpacing(other, curve[j].q);
    }
    const KdTree ctree(cq);
    const std::size_t n = self.size();
    std::vector<std::vector<NewSample>> added(n);
    std::vector<std::uint8_t> split(n, 0);
    tbb::parallel_for(
        tbb::blocked_range<std::size_t>(0, n, 256), [&](const tbb::blocked_range<std::size_t>& r) {
            std::vector<Neighbor> near;
            for (std::size_t i = r.begin(); i != r.end(); ++i) {
                if (!keep[i]) continue;
                const std::uint32_t ii = static_cast<std::uint32_t>(i);
                const Vec3f x = self.Position(ii);
                const float eta = self.Spacing(ii);
                // The nearest curve sample within 2 eta (ties by index, as Nearest): the same
                // answer as an unbounded Nearest wherever it passes the test below, and cheap for
                // the many samples far from the curve (an unbounded search from there visits
                // most of the curve's tree: 5,400 instructions a query, 17 % of sphere - box).
                // (FLANN keeps a point only when strictly inside the radius: a hair more.)
                const Neighbor c = NearestWithin(ctree, x, 2.0001f * eta, near);
                if (c.index == UINT32_MAX || c.dist2 > 4.0f * eta * eta ||
                    !(eta > options.upsample_ratio * eta_other[c.index]))
                    continue;
                const int m = std::clamp(static_cast<int>(std::lround(eta / eta_other[c.index])), 2,
                                         kMaxUpsampleFactor);
                const Vec3f nx = self.Normal(ii);
                const Vec3f u = nx.unitOrthogonal(), v = nx.cross(u);
                for (int a = 0; a < m; ++a)
                    for (int b = 0; b < m; ++b) {
                        const float du = eta * ((a + 0.5f) / m - 0.5f),
                                    dv = eta * ((b + 0.5f) / m - 0.5f);
                        const auto y = self.Project(x + du * u + dv * v);
                        if (!y) continue;
                        const Vec3f ny = y->normal.dot(nx) < 0 ? Vec3f(-y->normal) : y->normal;
                        const Omega o =
                            Classify(other, y->position, ny, options.coincident_tolerance);
                        if (Keep(o.value, of_a, op)) added[i].push_back({y->position, ny, eta / m});
                    }
                split[i] = 1;
            }
        });
    std::vector<NewSample> out;
    for (std::size_t i = 0; i < n; ++i) {
        if (!split[i]) continue;
        keep[i] = 0;
        ++replaced;
        out.insert(out.end(), added[i].begin(), added[i].end());
    }
    return out;
}

BoundingBox WorldBounds(const Side& side) {
    const BoundingBox local = side.cloud->Bounds();
    BoundingBox box;
    for (int c = 0; c < 8; ++c) {
        const Vec3f corner((c & 1) ? local.max.x() : local.min.x(),
                           (c & 2) ? local.max.y() : local.min.y(),
                           (c & 4) ? local.max.z() : local.min.z());
        box.Extend(side.ToWorld(corner));
    }
    return box;
}

}  // namespace

BooleanResult Boolean(const PointCloud& a, const PointCloud& b, BooleanOp op,
                      const BooleanOptions& options, const ProgressFn& progress) {
    const Stopwatch watch;
    options.Validate();
    a.CheckConsistent();
    b.CheckConsistent();
    BooleanResult result;
    BooleanReport& rep = result.report;
    rep.op = BooleanOpName(op);
    rep.blend_radius = options.blend_radius;
    rep.input_points_a = a.size();
    rep.input_points_b = b.size();

    Side A, B;
    A.name = "a";
    B.name = "b";
    PrepareSides(A, a, B, b, options);
    rep.normals_estimated_a = A.normals_estimated;
    rep.normals_estimated_b = B.normals_estimated;
    CheckBoundsVolume(A, options.max_open_area);
    CheckBoundsVolume(B, options.max_open_area);

    // A subtracted solid's normals turn over (which samples stay is Keep's Table 3.1).
    const bool flip_a = op == BooleanOp::kReverseDifference, flip_b = op == BooleanOp::kDifference;

    Output out;
    const BoundingBox ba = WorldBounds(A), bb = WorldBounds(B);
    const bool overlap =
        (ba.min.array() <= bb.max.array()).all() && (bb.min.array() <= ba.max.array()).all();
    if (!overlap) {
        // Disjoint solids: Omega_B = 0 on all of A and Omega_A = 0 on all of B.
        rep.overlap = false;
        rep.notes.push_back("the inputs' bounding boxes do not overlap: the trivial answer (" +
                            rep.op + " = " +
                            (op == BooleanOp::kUnion          ? "both inputs"
                             : op == BooleanOp::kIntersection ? "empty"
                             : op == BooleanOp::kDifference   ? "a"
                                                              : "b") +
                            ")");
        const bool keep_a = Keep(kOutside, true, op), keep_b = Keep(kOutside, false, op);
        const std::vector<std::uint8_t> all_a(A.size(), keep_a ? 1 : 0), all_b(B.size(), keep_b ? 1 : 0);
        AddSide(out, A, all_a, flip_a, 0);
        AddSide(out, B, all_b, flip_b, 1);
        rep.kept_a = keep_a ? A.size() : 0;
        rep.kept_b = keep_b ? B.size() : 0;
        result.cloud = out.Finish();
        rep.time_ms = watch.ElapsedMs();
        return result;
    }

    ProgressTracker tracker(progress, static_cast<double>(A.size() + B.size()) + 1.0, "boolean");
    std::vector<std::uint8_t> in_a, in_b;  // Omega_B on A's samples, Omega_A on B's (OmegaValue)
    std::vector<float> clear_a, clear_b;
    ClassifyStats cs;
    ClassifyAll(A, B, options, in_a, clear_a, cs, tracker);
    ClassifyAll(B, A, options, in_b, clear_b, cs, tracker);
    rep.classification_queries = cs.queries;
    rep.queries_saved = cs.saved;
    rep.queries_saved_share = cs.queries ? static_cast<double>(cs.saved) / cs.queries : 0.0;
    rep.mls_classifications = cs.mls;

    std::vector<std::uint8_t> keep_a(A.size()), keep_b(B.size());
    for (std::size_t i = 0; i < A.size(); ++i) keep_a[i] = Keep(in_a[i], true, op);
    for (std::size_t i = 0; i < B.size(); ++i) keep_b[i] = Keep(in_b[i], false, op);
    rep.kept_a = static_cast<std::size_t>(std::count(keep_a.begin(), keep_a.end(), 1));
    rep.kept_b = static_cast<std::size_t>(std::count(keep_b.begin(), keep_b.end(), 1));

    CurveStats st;
    const auto curve = SampleCurve(A, B, keep_a, keep_b, clear_a, clear_b, options, st, tracker);
    rep.curve_samples = curve.size();
    rep.curve_seeds = st.seeds;
    rep.curve_refined = st.refined;
    rep.newton_failures = st.failures;
    rep.mean_newton_iterations = st.converged ? st.iterations / st.converged : 0.0;
    if (rep.kept_a + rep.kept_b > 0 && curve.empty())
        rep.notes.push_back("the surfaces do not intersect: no intersection curve");

    const auto add_a = Upsample(A, B, true, op, keep_a, curve, options, rep.upsampled_a);
    const auto add_b = Upsample(B, A, false, op, keep_b, curve, options, rep.upsampled_b);
    rep.added_a = add_a.size();
    rep.added_b = add_b.size();
    rep.kept_a -= rep.upsampled_a;
    rep.kept_b -= rep.upsampled_b;
    AddSide(out, A, keep_a, flip_a, 0);
    for (const NewSample& s : add_a) out.Add(s.p, flip_a ? Vec3f(-s.n) : s.n, s.radius, 0);
    AddSide(out, B, keep_b, flip_b, 1);
    for (const NewSample& s : add_b) out.Add(s.p, flip_b ? Vec3f(-s.n) : s.n, s.radius, 1);
    for (const CurveSample& s : curve)
        out.Add(s.q, flip_a ? Vec3f(-s.na) : s.na, s.eta, 2, flip_b ? Vec3f(-s.nb) : s.nb);
    if (out.cloud.empty()) rep.notes.push_back("the result is empty");
    result.cloud = out.Finish();
    if (options.blend_radius > 0.0) {
        rep.blend = BlendCreases(result.cloud, options.blend_radius, options.blend_iterations, &tracker);
        if (curve.empty()) rep.notes.push_back("no intersection curve: nothing to blend");
        else if (rep.blend.moved == 0 && 2 * rep.blend.knife_edges > curve.size())
            rep.notes.push_back("not blended: " + std::to_string(rep.blend.knife_edges) + " of " +
                                std::to_string(curve.size()) +
                                " crease pairs are knife edges (normals over 120 degrees apart); the creases stay sharp");
    }
    tracker.Advance(1.0);
    rep.time_ms = watch.ElapsedMs();
    return result;
}

}  // namespace surfel

namespace surfel {

// ---------------------------------------------------------------------------------------------
// The public classifier: one Side, as Boolean() prepares it.
// ---------------------------------------------------------------------------------------------

struct SolidClassifier::Impl {
    Side side;
    double coincident = 0;
};

SolidClassifier::SolidClassifier(const PointCloud& cloud, const BooleanOptions& options, bool placed,
                                 std::string name)
    : impl_(std::make_unique<Impl>()) {
    options.Validate();
    cloud.CheckConsistent();
    impl_->side.name = std::move(name);
    impl_->coincident = options.coincident_tolerance;
    PrepareSide(impl_->side, cloud, options, placed);
    CheckBoundsVolume(impl_->side, options.max_open_area);
}

SolidClassifier::~SolidClassifier() = default;

SolidAnswer SolidClassifier::Classify(const Vec3f& x, const Vec3f& nx) const {
    const Omega o = surfel::Classify(impl_->side, x, nx, impl_->coincident);
    return {static_cast<SolidSide>(o.value), o.clear};
}

PointCloud SolidClassifier::WorldCloud() const {
    const Side& side = impl_->side;
    PointCloud out;
    out.positions.resize(side.size());
    out.normals.resize(side.size());
    for (std::uint32_t i = 0; i < side.size(); ++i) {
        out.positions[i] = side.Position(i);
        out.normals[i] = side.Normal(i).normalized();
    }
    if (side.input->has_radii()) {
        out.radii = side.input->radii;
        for (float& r : out.radii) r *= side.s;
    }
    out.colors = side.input->colors;
    return out;
}

BoundingBox SolidClassifier::WorldBounds() const { return surfel::WorldBounds(impl_->side); }

bool SolidClassifier::normals_estimated() const { return impl_->side.normals_estimated; }

std::optional<SolidAnswer> CoherenceCache::Find(const Vec3f& x) const {
    for (int j = 0; j < count_; ++j) {
        const Sphere& s = ring_[(head_ - 1 - j + kSpheres) % kSpheres];
        const float dist = (x - s.c).norm();
        if (dist < s.answer.clear) return SolidAnswer{s.answer.side, s.answer.clear - dist};
    }
    return std::nullopt;
}

void CoherenceCache::Add(const Vec3f& x, const SolidAnswer& answer) {
    if (!(answer.clear > 0)) return;
    ring_[head_] = {x, answer};
    head_ = (head_ + 1) % kSpheres;
    count_ = std::min(count_ + 1, kSpheres);
}

}  // namespace surfel
