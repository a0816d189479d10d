#pragma once
// The first version of iterative simplification (notes 2.2), kept as the reference the flat,
// indexed-heap implementation is tested against: quadric per point over the symmetric k-NN graph,
// std::priority_queue of all pairs with stamps (lazy deletion), adjacency as sorted vectors.
// Target mode only. Returns the surviving points' positions, in the order of their smallest
// member (the numbering of Simplify's output).

#include <Eigen/Core>
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <array>
#include <map>
#include <queue>
#include <vector>

#include "surfel/simplify/simplify_internal.h"
#include "surfel/spatial/kd_tree.h"

namespace surfel::reference {

inline std::vector<Vec3f> IterativeSimplify(std::span<const Vec3f> points, std::span<const Vec3f> normals,
                                            std::size_t target, int k, double length_weight) {
    struct Quadric {
        Eigen::Matrix3d a = Eigen::Matrix3d::Zero();
        Eigen::Vector3d b = Eigen::Vector3d::Zero();
        double c = 0.0, planes = 0.0;
        void AddPlane(const Eigen::Vector3d& n, const Eigen::Vector3d& p) {
            const double d = n.dot(p);
            a.noalias() += n * n.transpose();
            b += d * n;
            c += d * d;
            planes += 1.0;
        }
        void Add(const Quadric& o) {
            a += o.a;
            b += o.b;
            c += o.c;
            planes += o.planes;
        }
        // The products and dots as the implementation writes them out (detail::Dot3,
        // SymmetricTimes: Eigen's sums on SSE2, the same on every target).
        std::array<double, 6> Upper() const { return {a(0, 0), a(0, 1), a(0, 2), a(1, 1), a(1, 2), a(2, 2)}; }
        Eigen::Vector3d Times(const Eigen::Vector3d& y) const { return detail::SymmetricTimes(Upper().data(), y); }
        double Evaluate(const Eigen::Vector3d& x) const {
            return std::max(0.0, detail::Dot3(x, Times(x)) - 2.0 * detail::Dot3(b, x) + c);
        }
        // The minimiser is the implementation's (its numerics are not what this reference checks).
        Eigen::Vector3d Minimize(const Eigen::Vector3d& m) const { return detail::MinimizeQuadric(a, b, m); }
    };
    struct Candidate {
        double cost;
        std::uint32_t u, v, stamp_u, stamp_v;
        bool operator>(const Candidate& o) const {
            if (cost != o.cost) return cost > o.cost;
            if (u != o.u) return u > o.u;
            return v > o.v;
        }
    };
    const std::size_t n = points.size();
    const KnnTable knn = KdTree(points).KnnAll(k);
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
    std::vector<Quadric> q(n);
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
            q[i].AddPlane(plane, pos[i]);
        }
    }
    std::vector<std::uint32_t> stamp(n, 0), parent(n);
    std::vector<char> alive(n, 1);
    for (std::uint32_t i = 0; i < n; ++i) parent[i] = i;
    std::priority_queue<Candidate, std::vector<Candidate>, std::greater<>> queue;
    auto evaluate = [&](std::uint32_t u, std::uint32_t v, Eigen::Vector3d* where) {
        Quadric s = q[u];
        s.Add(q[v]);
        const Eigen::Vector3d mid = 0.5 * (pos[u] + pos[v]), e = pos[v] - pos[u];
        Eigen::Vector3d x = s.Minimize(mid);
        if ((x - mid).squaredNorm() > e.squaredNorm()) {
            const Eigen::Vector3d ae = s.Times(e);
            const double a2 = detail::Dot3(e, ae), b1 = 2.0 * (detail::Dot3(pos[u], ae) - detail::Dot3(s.b, e));
            const double t = a2 > 0 ? std::clamp(-b1 / (2.0 * a2), 0.0, 1.0) : 0.5;
            x = pos[u] + t * e;
        }
        if (where) *where = x;
        return s.Evaluate(x) + length_weight * s.planes * (pos[u] - pos[v]).squaredNorm();
    };
    auto push = [&](std::uint32_t u, std::uint32_t v) {
        if (u > v) std::swap(u, v);
        queue.push({evaluate(u, v, nullptr), u, v, stamp[u], stamp[v]});
    };
    for (std::uint32_t i = 0; i < n; ++i)
        for (const std::uint32_t j : adj[i])
            if (i < j) push(i, j);
    std::size_t count = n;
    while (count > target && !queue.empty()) {
        const Candidate top = queue.top();
        queue.pop();
        const std::uint32_t u = top.u, v = top.v;
        if (!alive[u] || !alive[v] || stamp[u] != top.stamp_u || stamp[v] != top.stamp_v) continue;
        Eigen::Vector3d x;
        evaluate(u, v, &x);
        pos[u] = x;
        q[u].Add(q[v]);
        alive[v] = 0;
        parent[v] = u;
        ++stamp[u];
        std::vector<std::uint32_t> merged;
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
        adj[v].clear();
        for (const std::uint32_t w : adj[u]) push(u, w);
        --count;
    }
    // Survivors numbered by their cluster's smallest member.
    std::map<std::uint32_t, std::uint32_t> smallest;  // root -> smallest member
    for (std::uint32_t i = 0; i < n; ++i) {
        std::uint32_t r = i;
        while (parent[r] != r) r = parent[r];
        smallest.emplace(r, i);  // i ascends: the first seen is the smallest
    }
    std::vector<std::pair<std::uint32_t, std::uint32_t>> order;
    for (const auto& [root, low] : smallest) order.emplace_back(low, root);
    std::sort(order.begin(), order.end());
    std::vector<Vec3f> out;
    for (const auto& [low, root] : order) out.push_back(pos[root].cast<float>());
    return out;
}

}  // namespace surfel::reference
