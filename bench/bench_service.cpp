// Service benchmarks (issue 6): a real surfel-server on loopback, driven by the client library.
//   upload throughput of a large binary PLY (MB/s), round-trip latency of a tiny render
//   (submit -> result bytes), and jobs/s under 1, 4 and 16 concurrent clients.
// Run: build/bin/bench_service [--points N] [--seconds S]   (prints a markdown table)
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <string>
#include <thread>
#include <vector>

#include "server_process.h"
#include "service_client.h"
#include "surfel/base/shapes.h"
#include "surfel/io/ply.h"

using Clock = std::chrono::steady_clock;
namespace fs = std::filesystem;

int main(int argc, char** argv) {
    std::size_t points = 4'000'000;
    double seconds = 5;
    for (int i = 1; i + 1 < argc; i += 2) {
        if (std::string(argv[i]) == "--points") points = std::stoul(argv[i + 1]);
        if (std::string(argv[i]) == "--seconds") seconds = std::stod(argv[i + 1]);
    }
    const fs::path dir = fs::temp_directory_path() / ("surfel-bench-service-" + std::to_string(getpid()));
    fs::create_directories(dir);
    surfel::ShapeOptions o;
    o.points = points;
    o.normals = true;
    const std::string big = (dir / "big.ply").string();
    surfel::WritePly(surfel::SampleShape(surfel::Shape::kTorus, o), big);
    o.points = 2000;
    const std::string tiny = (dir / "tiny.ply").string();
    surfel::WritePly(surfel::SampleShape(surfel::Shape::kSphere, o), tiny);
    const double mb = double(fs::file_size(big)) / (1 << 20);

    surfel::testing::ServerProcess server((dir / "data").string(), {"--max-queued", "100000"});
    surfel::client::ServiceClient c(server.target());

    std::printf("| measure | value |\n|---|---:|\n");
    auto t0 = Clock::now();
    const auto cloud = c.UploadFile(big);
    double s = std::chrono::duration<double>(Clock::now() - t0).count();
    std::printf("| upload %.1f MiB binary PLY (%zu points; hash + parse + store included) | %.0f MiB/s (%.2f s) |\n", mb,
                std::size_t(cloud.points()), mb / s, s);
    t0 = Clock::now();
    c.UploadFile(big);
    s = std::chrono::duration<double>(Clock::now() - t0).count();
    std::printf("| the same file again (client hashes it, server has it: nothing sent) | %.2f s |\n", s);

    const std::string id = c.UploadFile(tiny).id();
    std::atomic<int> seq{0};
    auto tiny_render = [&](surfel::client::ServiceClient& client) {
        surfel::v1::JobSpec spec;
        auto* r = spec.mutable_render();
        r->set_cloud_id(id);
        r->set_width(16);
        r->set_height(16);
        r->mutable_background()->set_x(seq++ * 1e-9);  // distinct jobs: no reuse of stored results
        const auto out = client.Watch(client.Submit(spec).id(), true, false);
        if (out.state != surfel::v1::SUCCEEDED) std::fprintf(stderr, "job failed: %s\n", out.status_message.c_str());
    };
    std::vector<double> lat;
    for (int i = 0; i < 50; ++i) {
        const auto a = Clock::now();
        tiny_render(c);
        lat.push_back(std::chrono::duration<double, std::milli>(Clock::now() - a).count());
    }
    std::sort(lat.begin(), lat.end());
    std::printf("| round trip of a 16x16 render of 2,000 points (submit, watch, result), median / p90 | %.2f / %.2f ms |\n",
                lat[lat.size() / 2], lat[lat.size() * 9 / 10]);

    for (int clients : {1, 4, 16}) {
        std::atomic<int> done{0};
        std::atomic<bool> stop{false};
        std::vector<std::thread> threads;
        const auto start = Clock::now();
        for (int t = 0; t < clients; ++t)
            threads.emplace_back([&] {
                surfel::client::ServiceClient client(server.target());
                while (!stop) {
                    tiny_render(client);
                    ++done;
                }
            });
        std::this_thread::sleep_for(std::chrono::duration<double>(seconds));
        stop = true;
        for (auto& t : threads) t.join();
        const double el = std::chrono::duration<double>(Clock::now() - start).count();
        std::printf("| jobs/s, %d concurrent client%s (tiny renders) | %.0f |\n", clients, clients > 1 ? "s" : "",
                    done / el);
    }
    server.Kill(SIGTERM);
    fs::remove_all(dir);
}
