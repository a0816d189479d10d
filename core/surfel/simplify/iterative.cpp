// Iterative simplification by point-pair contraction (course notes, Pauly 2.2): quadric error
// metric over the k-nearest-neighbour graph, priority queue with lazy updates.

#include <algorithm>
#include <cmath>
#include <limits>
#include <queue>

#include "surfel/base/error.h"
#include "surfel/simplify/simplify_internal.h"
#include "surfel/spatial/kd_tree.h"

namespace surfel::detail {
namespace {

/// Sum of squared distances to a set of planes n.x = d: x^T A x - 2 b^T x + c.
struct Quadric {
    Eigen::Matrix3d a = Eigen::Matrix3d::Zero();
    Eigen::Vector3d b = Eigen::Vector3d::Zero();
    double c = 0.0;
    double planes = 0.0;

    void AddPlane(const Eigen::Vector3d& n, const Eigen::Vector3d& p) {
        const double d = n.dot(p);
        a.noalias() += n * n.transpose();
        b += d * n;
        c += d * d;
        planes += 1.0;
    }
    Quadric& operator+=(const Quadric& o) {
        a += o.a;
        b += o.b;
        c += o.c;
        planes += o.planes;
        return *this;
    }
    double Evaluate(const Eigen::Vector3d& x) const { return std::max(0.0, x.dot(a * x) - 2.0 * b.dot(x) + c); }
    /// Minimiser, taken around `m` with a truncated pseudo-inverse: directions the planes do not
    /// constrain (a flat region constrains only the normal) stay at m.
    Eigen::Vector3d Minimize(const Eigen::Vector3d& m) const {
        Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver;
        solver.computeDirect(a);
        const Eigen::Vector3d lambda = solver.eigenvalues();
        const Eigen::Matrix3d& v = solver.eigenvectors();
        const double limit = std::max(lambda.maxCoeff(), 0.0) * 1e-3;
        const Eigen::Vector3d r = v.transpose() * (b - a * m);
        Eigen::Vector3d step = Eigen::Vector3d::Zero();
        for (int i = 0; i < 3; ++i)
            if (lambda[i] > limit && lambda[i] > 0) step += v.col(i) * (r[i] / lambda[i]);
        return m + step;
    }
};

struct Candidate {
    double cost;
    std::uint32_t u, v;
    std::uint32_t stamp_u, stamp_v;
    bool operator>(const Candidate& o) const {
        if (cost != o.cost) return cost > o.cost;
        if (u != o.u) return u > o.u;
        return v > o.v;
    }
};

// Weight of the tie-breaking term: on flat regions every quadric cost is 0, and contracting the
// shortest pair first keeps the sampling even there; small enough not to compete with the
// quadric wherever the surface bends. Chosen by measurement (bench_core, surface error Δavg on
// bunny_scans_merged and person_scan at 1 % and 10 %): 1e-4 -> 1e-3 lowered Δavg at 1 % from
// 2.12e-3 to 1.60e-3 (bunny) and at 10 % from 1.20e-3 to 0.70e-3 (person). 1e-2 and 1e-1 were
// no better there and lost the crease adaptivity (test IterativeIsCurvatureAdaptiveByItsQuadrics).
// Re-measured with the current error metric (session 4; bunny 1 %, 10 %, person 1 %, 10 %):
// 3e-4: 2.127e-3, 1.988e-4, 2.175e-3, 8.18e-4; 1e-3: 2.125e-3, 1.994e-4, 2.139e-3, 8.49e-4;
// 3e-3: 2.157e-3, 1.975e-4, 2.160e-3, 1.116e-3; 1e-2: 2.184e-3, 1.985e-4, 2.156e-3, 1.153e-3;
// 1e-1: 2.331e-3, 2.069e-4, 2.101e-3, 1.135e-3. 1e-3 stays (no setting is best everywhere).
constexpr double kLengthWeight = 1e-3;

}  // namespace

Clustering IterativeSimplification(std::span<const Vec3f> points, std::span<const Vec3f> normals,
                                   const SimplifyOptions& options, std::vector<Vec3f>& positions,
                                   ProgressTracker& progress) {
    const std::size_t n = points.size();
    const int k = std::max(1, std::min<int>(options.neighbors, static_cast<int>(n) - 1));
    const KdTree tree(points);
    const KnnTable knn = tree.KnnAll(k);

    // Symmetric neighbour graph.
    std::vector<std::vector<std::uint32_t>> adj(n);
    for (std::uint32_t i = 0; i < n; ++i)
        for (const std::uint32_t j : knn.Row(i)) {
            adj[i].push_back(j);
            adj[j].push_back(i);
        }
    for (auto& a : adj) {
        std::sort(a.begin(), a.end());
        a.erase(std::unique(a.begin(), a.end()), a.end());
    }

    // Quadrics: one tangent plane per edge, spanned by e_i = p - p_i and b_i = e_i x n.
    std::vector<Quadric> quadric(n);
    std::vector<Eigen::Vector3d> pos(n);
    for (std::uint32_t i = 0; i < n; ++i) pos[i] = points[i].cast<double>();
    for (std::uint32_t i = 0; i < n; ++i) {
        const Eigen::Vector3d ni = normals[i].cast<double>();
        for (const std::uint32_t j : adj[i]) {
            const Eigen::Vector3d e = pos[i] - pos[j];
            Eigen::Vector3d plane = e.cross(e.cross(ni));
            const double len = plane.norm();
            plane = len > 1e-300 ? Eigen::Vector3d(plane / len) : ni;
            if (plane.dot(ni) < 0) plane = -plane;
            quadric[i].AddPlane(plane, pos[i]);
        }
        if (adj[i].empty()) quadric[i].AddPlane(ni, pos[i]);
    }
    progress.Advance(0.1);

    std::vector<std::uint32_t> stamp(n, 0), parent(n);
    std::vector<char> alive(n, 1);
    for (std::uint32_t i = 0; i < n; ++i) parent[i] = i;
    std::priority_queue<Candidate, std::vector<Candidate>, std::greater<>> queue;
    const double bound2 = options.error > 0 ? options.error * options.error : std::numeric_limits<double>::infinity();

    auto evaluate = [&](std::uint32_t u, std::uint32_t v, Eigen::Vector3d* where, double* rms2) {
        Quadric q = quadric[u];
        q += quadric[v];
        const Eigen::Vector3d mid = 0.5 * (pos[u] + pos[v]), e = pos[v] - pos[u];
        Eigen::Vector3d x = q.Minimize(mid);
        if ((x - mid).squaredNorm() > e.squaredNorm()) {
            // Nearly parallel planes let the optimum run far away (scan lines, thin strips): take
            // the best point of the segment instead (Garland & Heckbert's fallback).
            const double a2 = e.dot(q.a * e), b1 = 2.0 * (pos[u].dot(q.a * e) - q.b.dot(e));
            const double t = a2 > 0 ? std::clamp(-b1 / (2.0 * a2), 0.0, 1.0) : 0.5;
            x = pos[u] + t * e;
        }
        const double err = q.Evaluate(x);
        if (where) *where = x;
        if (rms2) *rms2 = err / std::max(1.0, q.planes);
        return err + kLengthWeight * q.planes * (pos[u] - pos[v]).squaredNorm();
    };
    auto push = [&](std::uint32_t u, std::uint32_t v) {
        if (u > v) std::swap(u, v);
        queue.push({evaluate(u, v, nullptr, nullptr), u, v, stamp[u], stamp[v]});
    };
    for (std::uint32_t i = 0; i < n; ++i)
        for (const std::uint32_t j : adj[i])
            if (i < j) push(i, j);
    progress.Advance(0.1);

    std::size_t count = n;
    const std::size_t target = options.target;
    const double total = target ? static_cast<double>(n - std::min(n, target)) : static_cast<double>(n);
    std::size_t since = 0;
    std::vector<std::uint32_t> merged;
    while (count > target && count > 1) {
        if (queue.empty()) {
            if (target == 0) break;  // error-bounded: no admissible contraction left
            // Components ran out of pairs before the target: reconnect the survivors.
            std::vector<Vec3f> live;
            std::vector<std::uint32_t> ids;
            for (std::uint32_t i = 0; i < n; ++i)
                if (alive[i]) {
                    live.push_back(pos[i].cast<float>());
                    ids.push_back(i);
                }
            const KdTree live_tree(live);
            const KnnTable live_knn = live_tree.KnnAll(std::min<int>(k, static_cast<int>(live.size()) - 1));
            for (std::uint32_t a = 0; a < live.size(); ++a)
                for (const std::uint32_t b : live_knn.Row(a)) {
                    const std::uint32_t u = ids[a], v = ids[b];
                    if (std::find(adj[u].begin(), adj[u].end(), v) == adj[u].end()) {
                        adj[u].push_back(v);
                        adj[v].push_back(u);
                    }
                    push(u, v);
                }
            continue;
        }
        const Candidate top = queue.top();
        queue.pop();
        const std::uint32_t u = top.u, v = top.v;
        if (!alive[u] || !alive[v] || stamp[u] != top.stamp_u || stamp[v] != top.stamp_v) continue;
        Eigen::Vector3d x;
        double rms2 = 0.0;
        evaluate(u, v, &x, &rms2);
        if (rms2 > bound2) continue;  // this pair would exceed the error bound: never contract it
        // Contract v into u.
        pos[u] = x;
        quadric[u] += quadric[v];
        alive[v] = 0;
        parent[v] = u;
        ++stamp[u];
        merged.clear();
        for (const std::uint32_t w : adj[u])
            if (w != v) merged.push_back(w);
        for (const std::uint32_t w : adj[v]) {
            if (w == u) continue;
            merged.push_back(w);
            auto& aw = adj[w];
            aw.erase(std::remove(aw.begin(), aw.end(), v), aw.end());
            if (std::find(aw.begin(), aw.end(), u) == aw.end()) aw.push_back(u);
        }
        std::sort(merged.begin(), merged.end());
        merged.erase(std::unique(merged.begin(), merged.end()), merged.end());
        adj[u] = merged;
        std::vector<std::uint32_t>().swap(adj[v]);
        for (const std::uint32_t w : adj[u]) push(u, w);
        --count;
        if (++since == 8192) {
            progress.Advance(0.8 * 8192.0 / std::max(1.0, total));
            since = 0;
        }
    }

    // Clusters: follow each point's contraction chain to its surviving representative.
    Clustering out;
    out.label.resize(n);
    for (std::uint32_t i = 0; i < n; ++i) {
        std::uint32_t r = i;
        while (parent[r] != r) r = parent[r];
        std::uint32_t j = i;
        while (parent[j] != r && parent[j] != j) {
            const std::uint32_t next = parent[j];
            parent[j] = r;
            j = next;
        }
        out.label[i] = r;
    }
    out.count = Compact(out.label);
    positions.assign(out.count, Vec3f::Zero());
    for (std::uint32_t i = 0; i < n; ++i)
        if (alive[i]) positions[out.label[i]] = pos[i].cast<float>();
    return out;
}

}  // namespace surfel::detail
