#pragma once
/// \file
/// The HTTP/JSON front: surfel.v1 mapped as gRPC-JSON transcoding maps it (google.api.http paths,
/// `:cancel` custom method, proto3 JSON, errors as a google.rpc.Status-shaped body with the HTTP
/// status of google/rpc/code.proto), Server-Sent Events for job events, CORS, and the web page's
/// static files. Every route translates and calls Operations, as the gRPC front does.
/// docs/http.md lists the routes and says why cpp-httplib.

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "operations.h"

namespace surfel::server {

struct HttpOptions {
    std::string host = "127.0.0.1";
    int port = 8080;  ///< 0 picks a free one (port() tells)
    std::vector<std::string>
        cors_origins;      ///< origins allowed cross-origin; "*" = any; empty = none
    std::string web_root;  ///< the page's files, served at /; empty = no page
    std::string three_root =
        "/usr/share/javascript/three";     ///< Debian's libjs-three, served at /three/
    std::size_t threads = 16;              ///< connection threads (each SSE stream holds one)
    int sse_keepalive_ms = 15000;          ///< a comment line on an idle event stream this often
    std::size_t max_spec_bytes = 1 << 20;  ///< largest JobSpec body
    /// HTTPS: the server's certificate chain and key (PEM files); both or neither.
    std::string tls_cert, tls_key;
    /// Mutual TLS: clients must present a certificate signed by this CA (PEM); needs tls_cert.
    std::string tls_client_ca;
    /// Lifetime of a signed event-stream URL (POST /v1/jobs/{id}:eventsUrl), ms.
    std::int64_t events_url_ttl_ms = 60'000;
};

class HttpFront {
  public:
    /// `ops` must outlive this front; so must its JobManager.
    HttpFront(Operations& ops, HttpOptions options);
    /// Stop().
    ~HttpFront();
    HttpFront(const HttpFront&) = delete;
    HttpFront& operator=(const HttpFront&) = delete;

    /// Binds and starts serving on a thread of its own; throws Error(kUnavailable) when the
    /// address cannot be bound, Error(kInvalidArgument) when the TLS files do not load.
    void Start();
    /// The bound port (after Start).
    int port() const;
    /// Ends the event streams, stops listening and joins the connection threads.
    void Stop();

  private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

/// google/rpc/code.proto's HTTP mapping of a gRPC status code (OK 200, INVALID_ARGUMENT 400,
/// NOT_FOUND 404, RESOURCE_EXHAUSTED 429, UNAUTHENTICATED 401, DEADLINE_EXCEEDED 504, ...).
int HttpStatusFromCode(int grpc_code);

}  // namespace surfel::server
