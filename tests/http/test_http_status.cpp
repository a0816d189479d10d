// google/rpc/code.proto's HTTP mapping, every code (the HTTP front answers errors with these).
#include <grpcpp/support/status.h>
#include <gtest/gtest.h>

#include "http_front.h"

namespace surfel::server {
namespace {

TEST(HttpStatusFromCode, FollowsGoogleRpcCodeProto) {
    const struct {
        grpc::StatusCode code;
        int http;
    } table[] = {
        {grpc::StatusCode::OK, 200},
        {grpc::StatusCode::CANCELLED, 499},
        {grpc::StatusCode::UNKNOWN, 500},
        {grpc::StatusCode::INVALID_ARGUMENT, 400},
        {grpc::StatusCode::DEADLINE_EXCEEDED, 504},
        {grpc::StatusCode::NOT_FOUND, 404},
        {grpc::StatusCode::ALREADY_EXISTS, 409},
        {grpc::StatusCode::PERMISSION_DENIED, 403},
        {grpc::StatusCode::RESOURCE_EXHAUSTED, 429},
        {grpc::StatusCode::FAILED_PRECONDITION, 400},
        {grpc::StatusCode::ABORTED, 409},
        {grpc::StatusCode::OUT_OF_RANGE, 400},
        {grpc::StatusCode::UNIMPLEMENTED, 501},
        {grpc::StatusCode::INTERNAL, 500},
        {grpc::StatusCode::UNAVAILABLE, 503},
        {grpc::StatusCode::DATA_LOSS, 500},
        {grpc::StatusCode::UNAUTHENTICATED, 401},
    };
    for (const auto& row : table)
        EXPECT_EQ(HttpStatusFromCode(row.code), row.http) << "gRPC code " << row.code;
    EXPECT_EQ(HttpStatusFromCode(99), 500);  // not a code: a bug, reported as INTERNAL
}

}  // namespace
}  // namespace surfel::server
