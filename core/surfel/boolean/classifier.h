#pragma once
/// \file
/// Inside/outside classification of one point-sampled solid (course notes, Pauly 3.1.1, eq. 3.1
/// and Table 3.1), as Boolean() uses it, for callers that classify points of their own: the CSG
/// render (surfel/render/csg_render.h) asks it at every ray hit.

#include <memory>
#include <optional>
#include <string>

#include "surfel/base/point_cloud.h"
#include "surfel/boolean/boolean.h"

namespace surfel {

/// Omega_P(x): where x lies relative to the solid. kOnSame / kOnOpposite: within
/// BooleanOptions::coincident_tolerance spacings of the MLS surface, the query's normal agreeing
/// with / opposing the surface's (a shared face, or solids touching).
enum class SolidSide : std::uint8_t { kOutside = 0, kInside = 1, kOnSame = 2, kOnOpposite = 3 };

/// Table 3.1 with the coincident cases of BooleanOptions::coincident_tolerance: whether a point
/// of A (of_a) or of B with classification `side` against the other solid lies on the boundary of
/// `op`'s result.
bool TableKeeps(SolidSide side, bool of_a, BooleanOp op);

/// One classified query.
struct SolidAnswer {
    SolidSide side = SolidSide::kOutside;
    /// A lower bound of the distance from the query to the solid's surface (world units): Omega is
    /// constant within it (the coherence sphere of 3.1.1); 0 near the surface.
    float clear = 0.0f;
};

/// Omega_P of one solid. Thread-safe (every method is const).
class SolidClassifier {
public:
    /// `cloud`: the solid's samples, placed by options.transform when `placed` (B), else as given
    /// (A); kept by reference. Normals are estimated and oriented outward when absent
    /// (options.normals). Throws Error(kInvalidArgument) naming `name` ("b: ...") as Boolean()
    /// does: fewer than kMinBooleanInput points, a non-finite position, a surface that does not
    /// bound a volume (options.max_open_area); bad options by BooleanOptions::Validate().
    SolidClassifier(const PointCloud& cloud, const BooleanOptions& options, bool placed, std::string name);
    ~SolidClassifier();
    SolidClassifier(const SolidClassifier&) = delete;
    SolidClassifier& operator=(const SolidClassifier&) = delete;

    /// Eq. 3.1 at the world point x, for a query with outward unit normal nx (nx decides only the
    /// coincident cases): the closest sample p and its normal, outside iff (x − p)·n_p > 0; within
    /// the spacing eta_p of p, by the MLS projection of x and its normal instead.
    SolidAnswer Classify(const Vec3f& x, const Vec3f& nx) const;

    /// The samples in world coordinates: positions placed, unit outward normals (estimated where
    /// the input has none), radii times the scale, colours as given.
    PointCloud WorldCloud() const;
    /// The world bounding box of the samples.
    BoundingBox WorldBounds() const;
    bool normals_estimated() const;

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

/// The coherence spheres of 3.1.1: the last kSpheres classified queries with their clear
/// distances; a query inside one of them takes its answer without a search. Not thread-safe:
/// one per thread (or per tile), in a fixed query order for a deterministic result.
class CoherenceCache {
public:
    static constexpr int kSpheres = 8;
    /// The answer of the most recent sphere that contains x (clear reduced by the distance).
    std::optional<SolidAnswer> Find(const Vec3f& x) const;
    /// Remembers a classified query (only when answer.clear > 0).
    void Add(const Vec3f& x, const SolidAnswer& answer);
    void Clear() { count_ = head_ = 0; }

private:
    struct Sphere {
        Vec3f c;
        SolidAnswer answer;
    };
    Sphere ring_[kSpheres];
    int count_ = 0, head_ = 0;
};

}  // namespace surfel
