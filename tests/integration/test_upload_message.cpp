// ParseUploadMessage (server/upload_reactor.h): the server reads an Upload message's chunk from
// gRPC's slices without copying it, and must read exactly the UploadRequest that protobuf's own
// parse of the whole message gives (or refuse exactly what protobuf refuses), wherever gRPC cut
// the message into slices and in whatever order the client wrote the fields.
#include <gtest/gtest.h>

#include <random>
#include <string>
#include <vector>

#include "surfel/v1/surfel.pb.h"
#include "upload_reactor.h"
#include "upload_source.h"

namespace surfel {
namespace {

using server::ParseUploadMessage;

// `bytes` as a ByteBuffer cut before each offset in `cuts` (ascending).
grpc::ByteBuffer Cut(const std::string& bytes, const std::vector<std::size_t>& cuts) {
    std::vector<grpc::Slice> slices;
    std::size_t at = 0;
    for (std::size_t c : cuts) {
        if (c <= at || c >= bytes.size()) continue;
        slices.emplace_back(bytes.data() + at, c - at);
        at = c;
    }
    slices.emplace_back(bytes.data() + at, bytes.size() - at);
    return grpc::ByteBuffer(slices.data(), slices.size());
}

// What the server reads from `buffer`, as one message (data joined), or nullopt when refused.
std::optional<v1::UploadRequest> Read(const grpc::ByteBuffer& buffer) {
    v1::UploadRequest fields;
    std::vector<grpc::Slice> data;
    std::size_t size = 12345;
    if (!ParseUploadMessage(buffer, &fields, &data, &size)) return std::nullopt;
    EXPECT_TRUE(fields.data().empty());
    std::string joined;
    for (const grpc::Slice& s : data)
        joined.append(reinterpret_cast<const char*>(s.begin()), s.size());
    EXPECT_EQ(joined.size(), size);
    fields.set_data(joined);
    return fields;
}

// The server's reading of `bytes` cut at `cuts` agrees with protobuf's parse of them.
void ExpectAsProtobuf(const std::string& bytes, const std::vector<std::size_t>& cuts) {
    v1::UploadRequest expected;
    const bool ok = expected.ParseFromString(bytes);
    const std::optional<v1::UploadRequest> got = Read(Cut(bytes, cuts));
    ASSERT_EQ(got.has_value(), ok);
    if (ok) EXPECT_EQ(got->SerializeAsString(), expected.SerializeAsString());
}

std::string Bytes(std::size_t n, unsigned seed) {
    std::mt19937 rng(seed);
    std::string s(n, '\0');
    for (char& c : s) c = static_cast<char>(rng());
    return s;
}

v1::UploadRequest Request(std::size_t n, bool first) {
    v1::UploadRequest r;
    r.set_upload_id("fa0123_-x");
    if (first) {
        r.set_filename("scan.ply");
        r.set_total_size(96000201);
    }
    r.set_write_offset(first ? 0 : 1 << 20);
    r.set_finish_write(!first);
    r.set_data(Bytes(n, static_cast<unsigned>(n)));
    return r;
}

TEST(ParseUploadMessage, ReadsProtobufsMessageWhereverGrpcCutIt) {
    for (const std::size_t n : {std::size_t{0}, std::size_t{1}, std::size_t{127}, std::size_t{128},
                                std::size_t{20000}, std::size_t{256} << 10}) {
        for (const bool first : {true, false}) {
            SCOPED_TRACE("n=" + std::to_string(n) + (first ? " first" : " later"));
            const std::string bytes = Request(n, first).SerializeAsString();
            ExpectAsProtobuf(bytes, {});
            // A cut at each of the first 64 bytes (inside tags, varints, the strings), in the
            // data, and 16 KiB pieces (HTTP/2 frames).
            for (std::size_t c = 1; c < std::min<std::size_t>(bytes.size(), 64); ++c)
                ExpectAsProtobuf(bytes, {c});
            std::vector<std::size_t> frames;
            for (std::size_t c = 16384; c < bytes.size(); c += 16384) frames.push_back(c);
            ExpectAsProtobuf(bytes, frames);
            std::vector<std::size_t> every;
            if (bytes.size() < 300)
                for (std::size_t c = 1; c < bytes.size(); ++c) every.push_back(c);
            ExpectAsProtobuf(bytes, every);
        }
    }
}

TEST(ParseUploadMessage, ReadsTheClientsMessagesWithDataLast) {
    for (const std::size_t n : {std::size_t{0}, std::size_t{5}, std::size_t{256} << 10}) {
        v1::UploadRequest r = Request(n, true);
        const std::string data = r.data();
        r.clear_data();
        std::vector<grpc::Slice> slices;
        ASSERT_TRUE(client::UploadMessage(r, grpc::Slice(data)).Dump(&slices).ok());
        const grpc::ByteBuffer buffer(slices.data(), slices.size());
        const std::optional<v1::UploadRequest> got = Read(buffer);
        ASSERT_TRUE(got.has_value());
        r.set_data(data);
        EXPECT_EQ(got->SerializeAsString(), r.SerializeAsString());
    }
}

TEST(ParseUploadMessage, DataTwiceUnknownFieldsAndGroupsAsProtobuf) {
    const v1::UploadRequest a = Request(300, true), b = Request(77, false);
    ExpectAsProtobuf(a.SerializeAsString() + b.SerializeAsString(),
                     {5, 40, 400});  // the later data wins
    std::string unknown = a.SerializeAsString();
    unknown += std::string("\x38\x96\x01", 3);                          // field 7, varint 150
    unknown += std::string("\x42\x03xyz", 5);                           // field 8, 3 bytes
    unknown += std::string("\x4d\x01\x02\x03\x04", 5);                  // field 9, fixed32
    unknown += std::string("\x51\x01\x02\x03\x04\x05\x06\x07\x08", 9);  // field 10, fixed64
    ExpectAsProtobuf(unknown, {});
    ExpectAsProtobuf(unknown, {unknown.size() - 3});
    ExpectAsProtobuf(a.SerializeAsString() + std::string("\x5b\x60\x01\x5c", 4), {});  // group 11
    ExpectAsProtobuf(std::string("\x22\x02", 2) + "ab" + a.SerializeAsString(), {1});  // data first
}

TEST(ParseUploadMessage, RefusesWhatProtobufRefuses) {
    const std::string good = Request(1000, true).SerializeAsString();
    for (std::size_t len = 0; len < good.size(); len += (len < 64 ? 1 : 97))  // every truncation
        ExpectAsProtobuf(good.substr(0, len), {len / 2});
    v1::UploadRequest bad_utf8 = Request(10, true);
    bad_utf8.set_upload_id("ok");
    std::string bytes = bad_utf8.SerializeAsString();
    bytes[bytes.find("ok")] = '\xff';  // upload_id is a proto3 string: UTF-8 only
    ExpectAsProtobuf(bytes, {});
    ExpectAsProtobuf(std::string("\x00\x01", 2), {});                  // field 0
    ExpectAsProtobuf(std::string("\x22\xff\xff\xff\xff\x0f", 6), {});  // a length past the end
    ExpectAsProtobuf(std::string("\x18\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff\x01", 12),
                     {});  // 11-byte varint
}

// Mutated messages (random bytes changed, cut at random): the same answer as protobuf's.
TEST(ParseUploadMessage, AgreesWithProtobufOnMutatedMessages) {
    std::mt19937 rng(19);
    for (int i = 0; i < 3000; ++i) {
        std::string bytes = Request(rng() % 600, rng() % 2).SerializeAsString();
        const int flips = 1 + static_cast<int>(rng() % 3);
        for (int f = 0; f < flips; ++f) bytes[rng() % bytes.size()] = static_cast<char>(rng());
        if (rng() % 4 == 0) bytes.resize(rng() % bytes.size());
        std::vector<std::size_t> cuts;
        for (std::size_t c = 1 + rng() % 7; c < bytes.size(); c += 1 + rng() % 50)
            cuts.push_back(c);
        SCOPED_TRACE(i);
        ExpectAsProtobuf(bytes, cuts);
    }
}

}  // namespace
}  // namespace surfel
