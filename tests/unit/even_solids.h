#pragma once
// Evenly sampled analytic solids with exact outward normals, shared by the boolean and the CSG
// render tests (evenly spaced, so that "no holes within 2 spacings" measures the algorithm, not
// the gaps of a random sampling).

#include <cmath>
#include <cstddef>

#include "surfel/base/point_cloud.h"

namespace surfel::test {

// A Fibonacci sphere of radius `scale`, exact outward normals.
inline PointCloud EvenSphere(std::size_t n, double scale = 1.0) {
    PointCloud c;
    const double golden = 3.14159265358979323846 * (3.0 - std::sqrt(5.0));
    for (std::size_t i = 0; i < n; ++i) {
        const double z = 1.0 - (2.0 * i + 1.0) / n, r = std::sqrt(1.0 - z * z), phi = golden * i;
        const Vec3d u(r * std::cos(phi), r * std::sin(phi), z);
        c.positions.push_back((scale * u).cast<float>());
        c.normals.push_back(u.cast<float>());
    }
    return c;
}
// The cube [-scale, scale]^3, an m x m grid of cell centres on each face, face normals.
inline PointCloud EvenBox(int m, double scale = 1.0) {
    PointCloud c;
    for (int axis = 0; axis < 3; ++axis)
        for (int sign = -1; sign <= 1; sign += 2)
            for (int i = 0; i < m; ++i)
                for (int j = 0; j < m; ++j) {
                    Vec3d p, n = Vec3d::Zero();
                    p[axis] = sign * scale;
                    p[(axis + 1) % 3] = scale * (2.0 * (i + 0.5) / m - 1.0);
                    p[(axis + 2) % 3] = scale * (2.0 * (j + 0.5) / m - 1.0);
                    n[axis] = sign;
                    c.positions.push_back(p.cast<float>());
                    c.normals.push_back(n.cast<float>());
                }
    return c;
}

}  // namespace surfel::test
