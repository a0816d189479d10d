#include "surfel/io/ply.h"

#include <algorithm>
#include <bit>
#include <charconv>
#include <cmath>
#include <cstring>
#include <limits>
#include <numeric>
#include <optional>
#include <sstream>
#include <system_error>
#include <thread>

#include "surfel/base/error.h"
#include "surfel/io/file_bytes.h"
#include "surfel/io/text_internal.h"

namespace surfel {
namespace {

using io_internal::AppendFloatAscii;
using io_internal::Fail;
using io_internal::Quote;
using io_internal::Tokenize;

// ---- Header model ---------------------------------------------------------------------------

struct Property {
    std::string name;
    bool is_list = false;
    ScalarType type = ScalarType::kFloat32;        // value type; item type for a list
    ScalarType count_type = ScalarType::kUInt8;    // only for lists

    bool operator==(const Property&) const = default;
};

struct Element {
    std::string name;
    std::uint64_t count = 0;
    int header_line = 0;
    std::vector<Property> props;

    bool HasLists() const {
        return std::any_of(props.begin(), props.end(), [](const Property& p) { return p.is_list; });
    }
    // Size of one record without lists' items (the full size when there are no lists).
    std::size_t FixedSize() const {
        std::size_t s = 0;
        for (const auto& p : props) s += ScalarSize(p.is_list ? p.count_type : p.type);
        return s;
    }
    int Find(std::string_view n) const {
        for (std::size_t i = 0; i < props.size(); ++i)
            if (props[i].name == n && !props[i].is_list) return static_cast<int>(i);
        return -1;
    }
};

struct Header {
    PlyFormat format = PlyFormat::kAscii;
    std::vector<Element> elements;
    std::vector<std::string> comments;
    std::size_t body_offset = 0;
    int body_line = 1;  // 1-based line number where the body starts (for ascii messages)
};

std::optional<ScalarType> ParseScalarType(std::string_view s) {
    static constexpr std::pair<std::string_view, ScalarType> kTypes[] = {
        {"char", ScalarType::kInt8},      {"int8", ScalarType::kInt8},
        {"uchar", ScalarType::kUInt8},    {"uint8", ScalarType::kUInt8},
        {"short", ScalarType::kInt16},    {"int16", ScalarType::kInt16},
        {"ushort", ScalarType::kUInt16},  {"uint16", ScalarType::kUInt16},
        {"int", ScalarType::kInt32},      {"int32", ScalarType::kInt32},
        {"uint", ScalarType::kUInt32},    {"uint32", ScalarType::kUInt32},
        {"float", ScalarType::kFloat32},  {"float32", ScalarType::kFloat32},
        {"double", ScalarType::kFloat64}, {"float64", ScalarType::kFloat64},
    };
    for (const auto& [name, type] : kTypes)
        if (name == s) return type;
    return std::nullopt;
}

bool IsFloatType(ScalarType t) { return t == ScalarType::kFloat32 || t == ScalarType::kFloat64; }

Header ParseHeader(std::string_view data, std::string_view file, const PlyReadOptions& opt) {
    Header h;
    std::size_t pos = 0;
    int line_no = 0;
    bool have_format = false;
    auto next_line = [&](std::string_view* line) {
        if (pos >= data.size()) return false;
        std::size_t end = data.find('\n', pos);
        if (end == std::string_view::npos) end = data.size();
        if (end > opt.max_header_bytes)
            Fail(file, "header is larger than " + std::to_string(opt.max_header_bytes) +
                           " bytes (no end_header within the limit)");
        *line = data.substr(pos, end - pos);
        if (!line->empty() && line->back() == '\r') line->remove_suffix(1);
        pos = std::min(end + 1, data.size() + 1);
        ++line_no;
        return true;
    };
    std::string_view line;
    if (!next_line(&line) || line != "ply") Fail(file, "not a PLY file (the first line must be 'ply')");
    for (;;) {
        if (!next_line(&line)) Fail(file, "header ends without 'end_header' (after line " + std::to_string(line_no) + ")");
        const std::string where = "header line " + std::to_string(line_no) + ": ";
        auto tok = Tokenize(line);
        if (tok.empty()) continue;
        const std::string_view kw = tok[0];
        if (kw == "comment" || kw == "obj_info") {
            std::string_view rest = line.substr(std::min(line.size(), kw.size() + 1));
            h.comments.emplace_back(rest);
        } else if (kw == "format") {
            if (have_format) Fail(file, where + "second 'format' line");
            if (tok.size() != 3) Fail(file, where + "expected 'format <ascii|binary_little_endian|binary_big_endian> 1.0'");
            if (tok[1] == "ascii") h.format = PlyFormat::kAscii;
            else if (tok[1] == "binary_little_endian") h.format = PlyFormat::kBinaryLittleEndian;
            else if (tok[1] == "binary_big_endian") h.format = PlyFormat::kBinaryBigEndian;
            else Fail(file, where + "unknown format " + Quote(tok[1]) + " (expected ascii, binary_little_endian or binary_big_endian)");
            if (tok[2] != "1.0" && tok[2] != "1") Fail(file, where + "unsupported PLY version " + Quote(tok[2]) + " (expected 1.0)");
            have_format = true;
        } else if (kw == "element") {
            if (!have_format) Fail(file, where + "'element' before the 'format' line");
            if (tok.size() != 3) Fail(file, where + "expected 'element <name> <count>'");
            Element e;
            e.name = std::string(tok[1]);
            e.header_line = line_no;
            auto [p, ec] = std::from_chars(tok[2].data(), tok[2].data() + tok[2].size(), e.count);
            if (ec != std::errc() || p != tok[2].data() + tok[2].size())
                Fail(file, where + "element " + Quote(e.name) + " has an invalid count " + Quote(tok[2]));
            for (const auto& other : h.elements)
                if (other.name == e.name) Fail(file, where + "element " + Quote(e.name) + " declared twice");
            const std::uint64_t limit = e.name == "vertex" ? opt.max_points
                                        : e.name == "face" ? opt.max_faces
                                                           : opt.max_elements;
            if (e.count > limit)
                throw Error(ErrorCode::kResourceExhausted,
                            std::string(file) + ": " + where + "element '" + e.name + "' has " +
                                std::to_string(e.count) + " records, over the limit of " +
                                std::to_string(limit));
            h.elements.push_back(std::move(e));
        } else if (kw == "property") {
            if (h.elements.empty()) Fail(file, where + "'property' before any 'element'");
            Element& e = h.elements.back();
            Property p;
            if (tok.size() >= 2 && tok[1] == "list") {
                if (tok.size() != 5) Fail(file, where + "expected 'property list <count type> <item type> <name>'");
                auto ct = ParseScalarType(tok[2]);
                auto it = ParseScalarType(tok[3]);
                if (!ct) Fail(file, where + "unknown type " + Quote(tok[2]) + " for the count of list " + Quote(tok[4]));
                if (!it) Fail(file, where + "unknown type " + Quote(tok[3]) + " for the items of list " + Quote(tok[4]));
                if (IsFloatType(*ct)) Fail(file, where + "list " + Quote(tok[4]) + " has a floating-point count type");
                p.is_list = true;
                p.count_type = *ct;
                p.type = *it;
                p.name = std::string(tok[4]);
            } else {
                if (tok.size() != 3) Fail(file, where + "expected 'property <type> <name>'");
                auto t = ParseScalarType(tok[1]);
                if (!t) Fail(file, where + "unknown type " + Quote(tok[1]) + " for property " + Quote(tok[2]));
                p.type = *t;
                p.name = std::string(tok[2]);
            }
            for (const auto& q : e.props)
                if (q.name == p.name) Fail(file, where + "property " + Quote(p.name) + " declared twice in element '" + e.name + "'");
            e.props.push_back(std::move(p));
        } else if (kw == "end_header") {
            if (tok.size() != 1) Fail(file, where + "unexpected text after 'end_header'");
            break;
        } else {
            Fail(file, where + "unknown keyword " + Quote(kw) +
                           " (expected comment, obj_info, format, element, property or end_header)");
        }
    }
    if (!have_format) Fail(file, "header has no 'format' line");
    h.body_offset = std::min(pos, data.size());
    h.body_line = line_no + 1;
    return h;
}

// ---- Destinations for values ------------------------------------------------------------------

// Where the values of one property go: a float or double column with a stride, or nowhere.
struct Sink {
    float* f = nullptr;
    double* d = nullptr;
    std::size_t stride = 1;
    float divisor = 1.0f;  // 255 for uchar colours
    bool active() const { return f || d; }
    void Put(std::size_t i, double v) const {
        if (f) f[i * stride] = static_cast<float>(v) / divisor;
        else if (d) d[i * stride] = v;
    }
};

// ---- Binary loads -------------------------------------------------------------------------------

template <typename T>
T LoadRaw(const char* p, bool swap) {
    T v;
    std::memcpy(&v, p, sizeof(T));
    if constexpr (sizeof(T) > 1) {
        if (swap) {
            using U = std::conditional_t<sizeof(T) == 2, std::uint16_t,
                                         std::conditional_t<sizeof(T) == 4, std::uint32_t, std::uint64_t>>;
            U u;
            std::memcpy(&u, &v, sizeof(T));
            if constexpr (sizeof(T) == 2) u = __builtin_bswap16(u);
            else if constexpr (sizeof(T) == 4) u = __builtin_bswap32(u);
            else u = __builtin_bswap64(u);
            std::memcpy(&v, &u, sizeof(T));
        }
    }
    return v;
}

double LoadAsDouble(const char* p, ScalarType t, bool swap) {
    switch (t) {
        case ScalarType::kInt8: return LoadRaw<std::int8_t>(p, swap);
        case ScalarType::kUInt8: return LoadRaw<std::uint8_t>(p, swap);
        case ScalarType::kInt16: return LoadRaw<std::int16_t>(p, swap);
        case ScalarType::kUInt16: return LoadRaw<std::uint16_t>(p, swap);
        case ScalarType::kInt32: return LoadRaw<std::int32_t>(p, swap);
        case ScalarType::kUInt32: return LoadRaw<std::uint32_t>(p, swap);
        case ScalarType::kFloat32: return LoadRaw<float>(p, swap);
        case ScalarType::kFloat64: return LoadRaw<double>(p, swap);
    }
    return 0.0;
}

// Column extraction for fixed-size records: the hot loop of binary reading.
template <typename T>
void ExtractColumnT(const char* base, std::size_t rec, std::size_t n, std::size_t off, bool swap, const Sink& s) {
    if (s.f) {
        const float div = s.divisor;
        if (div == 1.0f) {
            for (std::size_t i = 0; i < n; ++i) s.f[i * s.stride] = static_cast<float>(LoadRaw<T>(base + i * rec + off, swap));
        } else {
            for (std::size_t i = 0; i < n; ++i) s.f[i * s.stride] = static_cast<float>(LoadRaw<T>(base + i * rec + off, swap)) / div;
        }
    } else {
        for (std::size_t i = 0; i < n; ++i) s.d[i * s.stride] = static_cast<double>(LoadRaw<T>(base + i * rec + off, swap));
    }
}

void ExtractColumn(ScalarType t, const char* base, std::size_t rec, std::size_t n, std::size_t off, bool swap, const Sink& s) {
    switch (t) {
        case ScalarType::kInt8: return ExtractColumnT<std::int8_t>(base, rec, n, off, swap, s);
        case ScalarType::kUInt8: return ExtractColumnT<std::uint8_t>(base, rec, n, off, swap, s);
        case ScalarType::kInt16: return ExtractColumnT<std::int16_t>(base, rec, n, off, swap, s);
        case ScalarType::kUInt16: return ExtractColumnT<std::uint16_t>(base, rec, n, off, swap, s);
        case ScalarType::kInt32: return ExtractColumnT<std::int32_t>(base, rec, n, off, swap, s);
        case ScalarType::kUInt32: return ExtractColumnT<std::uint32_t>(base, rec, n, off, swap, s);
        case ScalarType::kFloat32: return ExtractColumnT<float>(base, rec, n, off, swap, s);
        case ScalarType::kFloat64: return ExtractColumnT<double>(base, rec, n, off, swap, s);
    }
}

// ---- ASCII values -------------------------------------------------------------------------------

// Parses one ascii token as a value of type t; false when it is not one (or out of range).
bool ParseAsciiValue(std::string_view tok, ScalarType t, double* out) {
    const char* b = tok.data();
    const char* e = tok.data() + tok.size();
    if (t == ScalarType::kFloat32) {
        float v;
        auto [p, ec] = std::from_chars(b, e, v);
        if (ec != std::errc() || p != e) return false;
        *out = v;
        return true;
    }
    if (t == ScalarType::kFloat64) {
        double v;
        auto [p, ec] = std::from_chars(b, e, v);
        if (ec != std::errc() || p != e) return false;
        *out = v;
        return true;
    }
    if (b != e && *b == '+') ++b;
    std::int64_t v;
    auto [p, ec] = std::from_chars(b, e, v);
    if (ec != std::errc() || p != e) return false;
    std::int64_t lo = 0, hi = 0;
    switch (t) {
        case ScalarType::kInt8: lo = -128; hi = 127; break;
        case ScalarType::kUInt8: lo = 0; hi = 255; break;
        case ScalarType::kInt16: lo = -32768; hi = 32767; break;
        case ScalarType::kUInt16: lo = 0; hi = 65535; break;
        case ScalarType::kInt32: lo = INT32_MIN; hi = INT32_MAX; break;
        case ScalarType::kUInt32: lo = 0; hi = UINT32_MAX; break;
        default: break;
    }
    if (v < lo || v > hi) return false;
    *out = static_cast<double>(v);
    return true;
}

// ---- Body reading -------------------------------------------------------------------------------

struct FaceSink {
    std::vector<std::array<std::uint32_t, 3>>* triangles = nullptr;
    int list_index = -1;  // property index of vertex_indices / vertex_index
    std::uint64_t polygons = 0;
};

void AddPolygon(std::string_view file, const Element& e, std::uint64_t i, const std::vector<std::uint32_t>& poly,
                FaceSink* faces) {
    if (poly.size() < 3)
        Fail(file, "element '" + e.name + "' " + std::to_string(i) + ": a face needs at least 3 vertices, has " + std::to_string(poly.size()));
    ++faces->polygons;
    for (std::size_t j = 1; j + 1 < poly.size(); ++j) faces->triangles->push_back({poly[0], poly[j], poly[j + 1]});
}

// Record `i` of an ascii element `e`, the text of data line `ln` (not blank): sinks[k] receives
// scalar property k at index `slot`, `faces` the face list; `poly` and `toks` are scratch. What is
// wrong fails naming the line, the element and record, and the field. The whole-file parse and
// the upload's scan (PlyPositionScan) both read records with it.
void ParseAsciiRecord(std::string_view file, const Element& e, std::uint64_t i, std::size_t slot, int ln,
                      std::string_view line, const std::vector<Sink>& sinks, FaceSink* faces,
                      std::vector<std::uint32_t>& poly, std::vector<std::string_view>& toks) {
    toks = Tokenize(line);
    std::size_t t = 0;
    auto where = [&](const Property& p) {
        return "line " + std::to_string(ln) + ": " + e.name + " " + std::to_string(i) + ", field '" + p.name + "': ";
    };
    for (std::size_t k = 0; k < e.props.size(); ++k) {
        const Property& p = e.props[k];
        double v = 0.0;
        if (!p.is_list) {
            if (t >= toks.size()) Fail(file, where(p) + "missing value (the line has " + std::to_string(toks.size()) + " values)");
            if (!ParseAsciiValue(toks[t], p.type, &v))
                Fail(file, where(p) + Quote(toks[t]) + " is not a valid " + ScalarTypeName(p.type));
            ++t;
            if (sinks.size() > k && sinks[k].active()) sinks[k].Put(slot, v);
            continue;
        }
        if (t >= toks.size()) Fail(file, where(p) + "missing list length");
        if (!ParseAsciiValue(toks[t], p.count_type, &v) || v < 0)
            Fail(file, where(p) + Quote(toks[t]) + " is not a valid list length");
        ++t;
        const std::uint64_t m = static_cast<std::uint64_t>(v);
        if (m > toks.size() - t)
            Fail(file, where(p) + "list declares " + std::to_string(m) + " items but the line has " + std::to_string(toks.size() - t));
        const bool keep = faces && static_cast<int>(k) == faces->list_index;
        if (keep) poly.clear();
        for (std::uint64_t j = 0; j < m; ++j, ++t) {
            if (!ParseAsciiValue(toks[t], p.type, &v))
                Fail(file, where(p) + Quote(toks[t]) + " is not a valid " + ScalarTypeName(p.type));
            if (keep) poly.push_back(v < 0 || v > 4294967295.0 ? UINT32_MAX : static_cast<std::uint32_t>(v));
        }
        if (keep) AddPolygon(file, e, i, poly, faces);
    }
    if (t != toks.size())
        Fail(file, "line " + std::to_string(ln) + ": " + e.name + " " + std::to_string(i) + " has " +
                        std::to_string(toks.size()) + " values, expected " + std::to_string(t));
}

// Records of a fixed-size binary element read per block: about 64 KiB of them.
std::uint64_t BlockRecords(const Element& e) {
    const std::size_t rec = e.FixedSize();
    return rec > 0 ? std::max<std::uint64_t>(1, (64u << 10) / rec) : e.count;
}

// The positions of a fixed-size binary vertex element handed over one block at a time instead
// of stored (InspectPly): the count, the bounds and the first coordinate that is not finite,
// in a block-sized scratch array (no array of every position: 12 bytes a point never touched).
struct PositionStream {
    std::vector<Vec3f> scratch;  // one block of positions; the x, y, z sinks point into it
    BoundingBox bounds;
    std::uint64_t first_bad = UINT64_MAX;  // the lowest vertex index with a non-finite coordinate
    Vec3f bad_value = Vec3f::Zero();

    void Take(std::size_t m, std::uint64_t first) {
        if (first_bad != UINT64_MAX) return;  // refused anyway: the message names the first one
        const Vec3f* p = scratch.data();
        // A local box, the same Extend in the same order as PointCloud::Bounds (the same bits):
        // kept in registers, where the member would be stored back for every point (it may alias
        // the scratch floats), which took half of the check's time.
        BoundingBox box = bounds;
        for (std::size_t i = 0; i < m; ++i) {
            if (!p[i].allFinite()) {
                first_bad = first + i;
                bad_value = p[i];
                break;
            }
            box.Extend(p[i]);
        }
        bounds = box;
    }

    // Appends `later`, which streamed the records after this one's (the same bits as one stream:
    // the lower index of a non-finite coordinate wins, and cwiseMin / cwiseMax keep the earlier
    // of equal values, as Extend does record by record).
    void Merge(const PositionStream& later) {
        if (first_bad != UINT64_MAX) return;
        if (later.first_bad != UINT64_MAX) {
            first_bad = later.first_bad;
            bad_value = later.bad_value;
            return;
        }
        bounds.min = bounds.min.cwiseMin(later.bounds.min);
        bounds.max = bounds.max.cwiseMax(later.bounds.max);
    }
};

// PositionStream::Take of `m` whole records from `p` whose x, y and z are float32 in the machine's
// byte order at byte offsets `at` (multiples of 4, `rec` too), without the scratch block: lane-wise
// minima and maxima of the records' floats, 16 bytes at a time (a record of r floats repeats its
// pattern every lcm(r, 4) floats), then each lane folded into its axis. Extend's bits whenever
// the block's extremes are not zeros (equal floats other than +0 and -0 have equal bits, so the
// order of the comparisons cannot show) and every coordinate is finite; otherwise it returns
// false and changes nothing: the caller takes the records the ordinary way.
bool TakeFloatRecords(const char* p, std::size_t m, std::size_t rec, const std::size_t at[3], BoundingBox* bounds) {
    typedef float V4f __attribute__((vector_size(16)));
    typedef std::int32_t V4i __attribute__((vector_size(16)));
    constexpr int kMaxVectors = 16;
    const std::size_t r = rec / 4;
    const std::size_t floats = std::lcm<std::size_t>(r, 4);  // one period of the pattern
    const std::size_t vectors = floats / 4, per_period = floats / r;
    if (vectors > kMaxVectors) return false;
    int axis_of[4 * kMaxVectors];  // the axis of each float of a period, -1 for the others
    for (std::size_t l = 0; l < floats; ++l) {
        const std::size_t f = l % r;
        axis_of[l] = f == at[0] / 4 ? 0 : f == at[1] / 4 ? 1 : f == at[2] / 4 ? 2 : -1;
    }
    const float inf = std::numeric_limits<float>::infinity();
    V4f lo[kMaxVectors], hi[kMaxVectors];
    V4i bad[kMaxVectors];
    for (std::size_t v = 0; v < vectors; ++v) {
        lo[v] = V4f{inf, inf, inf, inf};
        hi[v] = -lo[v];
        bad[v] = V4i{0, 0, 0, 0};
    }
    const std::size_t periods = m / per_period;
    const V4i exponent = {0x7f800000, 0x7f800000, 0x7f800000, 0x7f800000};
    for (std::size_t g = 0; g < periods; ++g) {
        const char* q = p + g * floats * 4;
        for (std::size_t v = 0; v < vectors; ++v) {
            V4f x;
            V4i bits;
            std::memcpy(&x, q + 16 * v, 16);
            std::memcpy(&bits, q + 16 * v, 16);
            lo[v] = x < lo[v] ? x : lo[v];
            hi[v] = x > hi[v] ? x : hi[v];
            bad[v] |= (bits & exponent) == exponent;  // inf or nan
        }
    }
    Vec3f box_lo = Vec3f::Constant(inf), box_hi = Vec3f::Constant(-inf);
    for (std::size_t l = 0; l < floats; ++l) {
        const int a = axis_of[l];
        if (a < 0) continue;
        if (bad[l / 4][l % 4]) return false;
        box_lo[a] = std::min(box_lo[a], lo[l / 4][l % 4]);
        box_hi[a] = std::max(box_hi[a], hi[l / 4][l % 4]);
    }
    for (std::size_t i = periods * per_period; i < m; ++i) {  // the records after the last period
        for (int a = 0; a < 3; ++a) {
            float x;
            std::memcpy(&x, p + i * rec + at[a], 4);
            if (!std::isfinite(x)) return false;
            box_lo[a] = std::min(box_lo[a], x);
            box_hi[a] = std::max(box_hi[a], x);
        }
    }
    for (int a = 0; a < 3; ++a)
        if (m > 0 && (box_lo[a] == 0.0f || box_hi[a] == 0.0f)) return false;
    if (m > 0) {
        bounds->min = bounds->min.cwiseMin(box_lo);
        bounds->max = bounds->max.cwiseMax(box_hi);
    }
    return true;
}

// Records of an ascii vertex element a PlyPositionScan folds per block (48 KiB of positions).
constexpr std::uint64_t kAsciiBlock = 4096;

// A streamed element of at least this many blocks (4 MiB) is read in two halves, the second on a
// thread of its own (the upload check runs after the last byte, while the client waits): a fixed
// split, so the answer never depends on the number of cores.
constexpr std::uint64_t kSplitBlocks = 64;

// Where the x, y and z of a fixed-size binary vertex element lie in the file: what a
// PlyPositionScan streamed, and what the whole-file parse must find again to take its result.
struct PositionLayout {
    PlyFormat format = PlyFormat::kAscii;
    std::uint64_t offset = 0;  // of the vertex element's first record
    std::uint64_t count = 0;
    std::size_t record = 0;
    std::size_t at[3] = {0, 0, 0};  // byte offsets of x, y, z in a record
    ScalarType type[3] = {ScalarType::kFloat32, ScalarType::kFloat32, ScalarType::kFloat32};

    bool operator==(const PositionLayout&) const = default;

    // Whether TakeFloatRecords can take the records: float x, y, z on 4-byte offsets of records
    // of a multiple of 4 bytes, in the machine's byte order (`swap` false).
    bool PlainFloats(bool swap) const {
        bool plain = !swap && record % 4 == 0;
        for (int a = 0; a < 3; ++a) plain = plain && type[a] == ScalarType::kFloat32 && at[a] % 4 == 0;
        return plain;
    }

    // `vertex` of `h` starting at `offset`.
    static PositionLayout Of(const Header& h, const Element& vertex, std::uint64_t offset) {
        PositionLayout l;
        l.format = h.format;
        l.offset = offset;
        l.count = vertex.count;
        l.record = vertex.FixedSize();
        const int axes[3] = {vertex.Find("x"), vertex.Find("y"), vertex.Find("z")};
        std::size_t off = 0;
        for (std::size_t k = 0; k < vertex.props.size(); ++k) {
            for (int a = 0; a < 3; ++a)
                if (axes[a] == static_cast<int>(k)) {
                    l.at[a] = off;
                    l.type[a] = vertex.props[k].type;
                }
            off += ScalarSize(vertex.props[k].is_list ? vertex.props[k].count_type : vertex.props[k].type);
        }
        return l;
    }
};


class BodyReader {
public:
    BodyReader(std::string_view data, std::string_view file, const Header& h)
        : data_(data), file_(file), h_(h), pos_(h.body_offset), line_(h.body_line),
          swap_((h.format == PlyFormat::kBinaryBigEndian) == (std::endian::native == std::endian::little)) {}

    std::size_t remaining() const { return data_.size() - pos_; }
    std::size_t position() const { return pos_; }

    // Upper bound on how many records of `e` the remaining data can hold (to size arrays safely).
    std::uint64_t MaxRecords(const Element& e) const {
        if (h_.format == PlyFormat::kAscii) {
            // The lines from here to the end, counted once, at the first call (at a line's start:
            // the body's, or after the records a PlyPositionScan read); the rest derive from it.
            if (!counted_) {
                counted_ = true;
                count_line_ = line_;
                if (pos_ <= data_.size())
                    lines_ = 1 + static_cast<std::uint64_t>(std::count(data_.begin() + pos_, data_.end(), '\n'));
            }
            const std::uint64_t consumed = static_cast<std::uint64_t>(line_ - count_line_);
            return std::min<std::uint64_t>(e.count, lines_ - std::min(consumed, lines_));
        }
        const std::size_t fs = e.FixedSize();
        if (fs == 0) return e.count;
        return std::min<std::uint64_t>(e.count, remaining() / fs);
    }

    // Reads all records of `e`; sinks[i] receives scalar property i. `faces` handles the list.
    // `capacity` is MaxRecords(e) at the element's start: the sinks hold that many records, and
    // a record at or past it cannot be complete in the remaining data.
    // `stream` (only for a fixed-size binary element): every active sink points into its scratch
    // block, which ReadFixedBinary hands over block by block.
    // `scanned` (with `stream`): the element's positions as a PlyPositionScan folded them in while
    // the file arrived; they are taken instead of read (after the same truncation check).
    void Read(const Element& e, const std::vector<Sink>& sinks, FaceSink* faces, std::uint64_t capacity,
              PositionStream* stream = nullptr, const PositionStream* scanned = nullptr) {
        if (h_.format != PlyFormat::kAscii && !e.HasLists()) return ReadFixedBinary(e, sinks, stream, scanned);
        std::vector<std::uint32_t> poly;
        for (std::uint64_t i = 0; i < e.count; ++i) {
            // An ascii record needs a line of its own, so running out is found (and reported) by
            // ReadAsciiRecord before any value is stored; a binary record may be cut off midway.
            if (i >= capacity && h_.format != PlyFormat::kAscii) Truncated(e, i);
            if (h_.format == PlyFormat::kAscii) ReadAsciiRecord(e, i, sinks, faces, poly);
            else ReadBinaryRecord(e, i, sinks, faces, poly);
        }
    }

    // Past the records of an ascii element that a PlyPositionScan read: to byte `pos` (the start
    // of the line after them), the next line being number `line`.
    void SkipAscii(std::size_t pos, int line) {
        pos_ = pos;
        line_ = line;
    }

    void Finish() {
        if (h_.format == PlyFormat::kAscii) {
            for (std::size_t p = pos_; p < data_.size(); ++p) {
                const char c = data_[p];
                if (c == '\n') ++line_;
                else if (c != ' ' && c != '\t' && c != '\r')
                    Fail(file_, "line " + std::to_string(line_) + ": unexpected data after the last element (the header's counts do not match the data)");
            }
        } else if (remaining() > 0) {
            // Some writers end binary files with a newline; anything else is a count mismatch.
            for (std::size_t p = pos_; p < data_.size(); ++p)
                if (data_[p] != '\n' && data_[p] != '\r' && data_[p] != ' ' && data_[p] != '\0')
                    Fail(file_, std::to_string(remaining()) + " bytes of unexpected data after the last element (byte offset " + std::to_string(pos_) + "; the header's counts do not match the data)");
        }
    }

private:
    [[noreturn]] void Truncated(const Element& e, std::uint64_t i) const {
        Fail(file_, "truncated data: element '" + e.name + "' declares " + std::to_string(e.count) +
                        " records but the file ends in record " + std::to_string(i) + " (byte offset " +
                        std::to_string(data_.size()) + ")");
    }

    void ReadFixedBinary(const Element& e, const std::vector<Sink>& sinks, PositionStream* stream,
                         const PositionStream* scanned) {
        const std::size_t rec = e.FixedSize();
        const std::uint64_t n = e.count;
        if (rec > 0 && n > remaining() / rec) Truncated(e, remaining() / rec);
        const std::uint64_t block = BlockRecords(e);
        if (stream && scanned) {
            stream->bounds = scanned->bounds;
            stream->first_bad = scanned->first_bad;
            stream->bad_value = scanned->bad_value;
        } else if (stream && rec > 0 && n / block >= kSplitBlocks) {
            // The second half into a scratch block of its own: the sinks point into `stream`'s.
            const std::uint64_t mid = n / block / 2 * block;
            PositionStream second;
            second.scratch.resize(stream->scratch.size());
            const float* from = stream->scratch.front().data();
            float* to = second.scratch.front().data();
            std::vector<Sink> second_sinks = sinks;
            for (Sink& s : second_sinks)
                if (s.f) s.f = to + (s.f - from);
            const auto read_second = [&] { ReadBlocks(e, second_sinks, mid, n, &second); };
            struct Joiner {  // joined on every way out (a joinable std::thread must not be destroyed)
                std::thread thread;
                ~Joiner() {
                    if (thread.joinable()) thread.join();
                }
            } second_half;
            try {
                second_half.thread = std::thread(read_second);
            } catch (const std::system_error&) {  // no thread to be had: both halves here
            }
            ReadBlocks(e, sinks, 0, mid, stream);
            if (second_half.thread.joinable()) second_half.thread.join();
            else read_second();
            stream->Merge(second);
        } else {
            ReadBlocks(e, sinks, 0, n, stream);
        }
        pos_ += rec * n;
    }

    // Records [first, last) of a fixed-size binary element (first a multiple of the block).
    void ReadBlocks(const Element& e, const std::vector<Sink>& sinks, std::uint64_t first, std::uint64_t last,
                    PositionStream* stream) const {
        const std::size_t rec = e.FixedSize();
        const std::uint64_t n = last;
        const char* base = data_.data() + pos_;
        // Block by block (about 64 KiB of records each), every column of a block while it is in
        // the cache: one pass over the bytes instead of one per property.
        const std::uint64_t block = BlockRecords(e);  // `stream`'s scratch holds one
        // A streamed element with float x, y, z in the machine's byte order: TakeFloatRecords.
        const PositionLayout layout = stream ? PositionLayout::Of(h_, e, 0) : PositionLayout{};
        const bool plain = stream && layout.PlainFloats(swap_);
        for (std::uint64_t b = first; rec > 0 && b < n; b += block) {
            const std::size_t m = static_cast<std::size_t>(std::min(block, n - b));
            if (plain && stream->first_bad == UINT64_MAX && TakeFloatRecords(base + b * rec, m, rec, layout.at, &stream->bounds))
                continue;
            std::size_t off = 0;
            for (std::size_t k = 0; k < e.props.size(); ++k) {
                if (sinks.size() > k && sinks[k].active()) {
                    Sink s = sinks[k];
                    if (!stream) {  // a streamed block is filled from its start
                        if (s.f) s.f += b * s.stride;
                        else s.d += b * s.stride;
                    }
                    ExtractColumn(e.props[k].type, base + b * rec, rec, m, off, swap_, s);
                }
                off += ScalarSize(e.props[k].type);
            }
            if (stream) stream->Take(m, b);
        }
    }

    void ReadBinaryRecord(const Element& e, std::uint64_t i, const std::vector<Sink>& sinks, FaceSink* faces,
                          std::vector<std::uint32_t>& poly) {
        for (std::size_t k = 0; k < e.props.size(); ++k) {
            const Property& p = e.props[k];
            if (!p.is_list) {
                const int sz = ScalarSize(p.type);
                if (remaining() < static_cast<std::size_t>(sz)) Truncated(e, i);
                if (sinks.size() > k && sinks[k].active()) sinks[k].Put(i, LoadAsDouble(data_.data() + pos_, p.type, swap_));
                pos_ += sz;
                continue;
            }
            const int csz = ScalarSize(p.count_type);
            if (remaining() < static_cast<std::size_t>(csz)) Truncated(e, i);
            const double cnt = LoadAsDouble(data_.data() + pos_, p.count_type, swap_);
            pos_ += csz;
            if (cnt < 0) Fail(file_, "element '" + e.name + "' " + std::to_string(i) + ": list '" + p.name + "' has a negative length");
            const std::uint64_t m = static_cast<std::uint64_t>(cnt);
            const std::size_t isz = ScalarSize(p.type);
            if (m > remaining() / isz) Truncated(e, i);
            if (faces && static_cast<int>(k) == faces->list_index) {
                poly.clear();
                for (std::uint64_t j = 0; j < m; ++j) {
                    const double v = LoadAsDouble(data_.data() + pos_ + j * isz, p.type, swap_);
                    poly.push_back(v < 0 || v > 4294967295.0 ? UINT32_MAX : static_cast<std::uint32_t>(v));
                }
                AddPolygon(file_, e, i, poly, faces);
            }
            pos_ += m * isz;
        }
    }

    void ReadAsciiRecord(const Element& e, std::uint64_t i, const std::vector<Sink>& sinks, FaceSink* faces,
                         std::vector<std::uint32_t>& poly) {
        std::string_view line;
        for (;;) {  // next non-blank line
            if (pos_ >= data_.size())
                Fail(file_, "line " + std::to_string(line_) + ": unexpected end of file: element '" + e.name + "' declares " +
                                std::to_string(e.count) + " records, found " + std::to_string(i));
            std::size_t end = data_.find('\n', pos_);
            if (end == std::string_view::npos) end = data_.size();
            line = data_.substr(pos_, end - pos_);
            pos_ = end + 1;
            ++line_;
            if (line.find_first_not_of(" \t\r") != std::string_view::npos) break;
        }
        ParseAsciiRecord(file_, e, i, static_cast<std::size_t>(i), line_ - 1, line, sinks, faces, poly, toks_);
    }

    std::string_view data_;
    std::string_view file_;
    const Header& h_;
    std::size_t pos_;
    int line_;
    bool swap_;
    mutable bool counted_ = false;      // MaxRecords of an ascii body: lines_ counted
    mutable int count_line_ = 0;        // line_ when they were
    mutable std::uint64_t lines_ = 0;   // lines from there to the end
    std::vector<std::string_view> toks_;
};

}  // namespace

const char* PlyFormatName(PlyFormat format) {
    switch (format) {
        case PlyFormat::kAscii: return "ascii";
        case PlyFormat::kBinaryLittleEndian: return "binary_little_endian";
        case PlyFormat::kBinaryBigEndian: return "binary_big_endian";
    }
    return "?";
}


struct PlyPositionScan::State {
    PlyReadOptions options;
    std::uint64_t bytes = 0;  // appended so far
    enum class Phase { kHeader, kBody, kOff } phase = Phase::kHeader;
    std::string head;            // the bytes so far, until the header has been parsed
    std::size_t line_start = 0;  // of the first line of `head` not yet looked at
    PositionLayout layout;
    bool swap = false;
    bool plain_floats = false;  // TakeFloatRecords can take the records
    std::string carry;         // the start of a record (ascii: a line) cut off by the end of an Append
    std::uint64_t folded = 0;  // vertex records in `stream`
    PositionStream stream;     // its scratch holds one block
    // An ascii vertex element (the first element): its records are read line by line as the
    // whole-file parse reads them (ParseAsciiRecord); the first error turns the scan off, and the
    // whole-file parse then finds it again and names it.
    Element vertex;                   // as the header declares it
    std::vector<Sink> sinks;          // x, y, z into the scratch block
    std::uint64_t parsed = 0;         // records read (folded, or in the scratch block)
    int line_no = 0;                  // the number of the next line (as BodyReader's)
    std::uint64_t ascii_end = 0;      // once complete: the offset after the last record's line
    std::vector<std::uint32_t> poly;  // scratch of ParseAsciiRecord
    std::vector<std::string_view> toks;
    // A longer line turns the scan off (a vertex record is a few dozen bytes; the whole-file
    // parse reads any line).
    static constexpr std::size_t kMaxLine = 64u << 10;

    void Append(std::string_view piece) {
        const std::uint64_t at = bytes;
        bytes += piece.size();
        if (phase == Phase::kOff) return;
        if (phase == Phase::kBody) return Body(piece, at);
        head.append(piece);
        // The header ends at the first line whose first word is end_header (as ParseHeader
        // reads it); it is parsed once that line's newline has arrived, never twice.
        for (;;) {
            const std::size_t nl = head.find('\n', line_start);
            if (nl == std::string::npos) {
                if (head.size() > options.max_header_bytes) Off();  // the parse refuses it
                return;
            }
            std::string_view line(head.data() + line_start, nl - line_start);
            if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
            line_start = nl + 1;
            const auto tok = Tokenize(line);
            if (!tok.empty() && tok[0] == "end_header") break;
            if (line_start > options.max_header_bytes) return Off();
        }
        std::string all = std::move(head);
        head = {};
        try {
            Start(all);
        } catch (...) {  // a header the whole-file parse refuses (or no memory): it decides
            return Off();
        }
    }

    void Start(std::string_view all) {
        const Header h = ParseHeader(all, "", options);
        if (h.body_offset != line_start) return Off();
        if (h.format == PlyFormat::kAscii) return StartAscii(h, all);
        std::uint64_t offset = h.body_offset;
        for (const Element& e : h.elements) {
            if (e.HasLists()) return Off();  // the vertex records' offset depends on the data
            if (e.name == "vertex") {
                if (e.Find("x") < 0 || e.Find("y") < 0 || e.Find("z") < 0) return Off();
                layout = PositionLayout::Of(h, e, offset);
                swap = (h.format == PlyFormat::kBinaryBigEndian) == (std::endian::native == std::endian::little);
                plain_floats = layout.PlainFloats(swap);
                stream.scratch.resize(static_cast<std::size_t>(std::max<std::uint64_t>(1, std::min(BlockRecords(e), e.count))));
                phase = Phase::kBody;
                return Body(all.substr(h.body_offset), h.body_offset);
            }
            offset += e.FixedSize() * e.count;
        }
        Off();  // no vertex element
    }

    void StartAscii(const Header& h, std::string_view all) {
        if (h.elements.empty() || h.elements.front().name != "vertex") return Off();
        vertex = h.elements.front();
        const int axes[3] = {vertex.Find("x"), vertex.Find("y"), vertex.Find("z")};
        if (axes[0] < 0 || axes[1] < 0 || axes[2] < 0) return Off();
        layout = PositionLayout::Of(h, vertex, h.body_offset);
        line_no = h.body_line;
        stream.scratch.resize(static_cast<std::size_t>(std::max<std::uint64_t>(1, std::min<std::uint64_t>(kAsciiBlock, vertex.count))));
        sinks.assign(vertex.props.size(), Sink{});
        for (int a = 0; a < 3; ++a) sinks[axes[a]] = Sink{stream.scratch.front().data() + a, nullptr, 3, 1.0f};
        ascii_end = h.body_offset;
        phase = Phase::kBody;
        return AsciiBody(all.substr(h.body_offset));
    }

    // The next bytes of an ascii body: whole lines are read as records, the last partial one kept.
    void AsciiBody(std::string_view piece) {
        while (parsed < vertex.count && !piece.empty()) {
            const std::size_t nl = piece.find('\n');
            if (nl == std::string_view::npos) {
                if (carry.size() + piece.size() > kMaxLine) return Off();
                carry.append(piece);
                return;
            }
            std::string_view text = piece.substr(0, nl);
            if (!carry.empty()) {
                if (carry.size() + nl > kMaxLine) return Off();
                carry.append(text);
                text = carry;
            }
            piece.remove_prefix(nl + 1);
            ascii_end += text.size() + 1;
            ++line_no;
            if (text.find_first_not_of(" \t\r") != std::string_view::npos) {
                const std::size_t slot = static_cast<std::size_t>(parsed - folded);
                ParseAsciiRecord("", vertex, parsed, slot, line_no - 1, text, sinks, nullptr, poly, toks);
                ++parsed;
                if (slot + 1 == stream.scratch.size() || parsed == vertex.count) {
                    stream.Take(slot + 1, folded);
                    folded = parsed;
                }
            }
            carry.clear();
        }
    }

    // `piece` is the file's bytes from offset `at`.
    void Body(std::string_view piece, std::uint64_t at) {
        if (layout.format == PlyFormat::kAscii) return AsciiBody(piece);
        const std::uint64_t begin = std::max(at, layout.offset);
        const std::uint64_t end = std::min<std::uint64_t>(at + piece.size(), layout.offset + layout.record * layout.count);
        if (begin >= end) return;
        const char* p = piece.data() + (begin - at);
        std::size_t n = static_cast<std::size_t>(end - begin);
        if (!carry.empty()) {
            const std::size_t take = std::min(n, layout.record - carry.size());
            carry.append(p, take);
            p += take;
            n -= take;
            if (carry.size() < layout.record) return;
            Fold(carry.data(), 1);
            carry.clear();
        }
        const std::size_t whole = n / layout.record;
        Fold(p, whole);
        p += whole * layout.record;
        carry.assign(p, n - whole * layout.record);
    }

    // `m` whole records from `p`: the columns into the scratch block, then as ReadBlocks does.
    void Fold(const char* p, std::size_t m) {
        const std::size_t block = stream.scratch.size();
        float* base = stream.scratch.front().data();
        for (std::size_t b = 0; b < m; b += block) {
            const std::size_t k = std::min(block, m - b);
            if (plain_floats && stream.first_bad == UINT64_MAX &&
                TakeFloatRecords(p + b * layout.record, k, layout.record, layout.at, &stream.bounds)) {
                folded += k;
                continue;
            }
            if (stream.first_bad == UINT64_MAX)  // refused anyway, and Take would keep nothing
                for (int a = 0; a < 3; ++a)
                    ExtractColumn(layout.type[a], p + b * layout.record, layout.record, k, layout.at[a], swap,
                                  Sink{base + a, nullptr, 3, 1.0f});
            stream.Take(k, folded);
            folded += k;
        }
    }

    void Off() {
        phase = Phase::kOff;
        head = {};
        carry = {};
        stream.scratch = {};
        sinks = {};
        toks = {};
    }

    bool complete() const { return phase == Phase::kBody && folded == layout.count; }
};

namespace {

// "vertex 7, field 'y': coordinate is not finite (nan)"
std::string NonFiniteMessage(std::uint64_t i, const Vec3f& p) {
    const int axis = !std::isfinite(p.x()) ? 0 : !std::isfinite(p.y()) ? 1 : 2;
    std::ostringstream os;
    os << "vertex " << i << ", field '" << "xyz"[axis] << "': coordinate is not finite (" << p[axis] << ")";
    return os.str();
}

// ParsePly, and InspectPly when `summary` is given: then only the positions are read
// (positions_only), and those of a fixed-size binary vertex element are not even kept but
// streamed through a block (PositionStream); the checks, their order and messages are the same.
// `scan` (with `summary`): the positions as a PlyPositionScan of these bytes folded them in.
PointCloud ParsePlyImpl(std::string_view data, std::string_view file, const PlyReadOptions& options,
                        PlyHeaderInfo* info, PlySummary* summary, const PlyPositionScan::State* scan = nullptr) {
    const Header h = ParseHeader(data, file, options);
    const Element* vertex = nullptr;
    for (const auto& e : h.elements)
        if (e.name == "vertex") vertex = &e;
    if (!vertex) Fail(file, "no 'vertex' element in the header");
    for (const char* axis : {"x", "y", "z"})
        if (vertex->Find(axis) < 0)
            Fail(file, "header line " + std::to_string(vertex->header_line) + ": element 'vertex' has no property '" + axis + "'");

    PointCloud cloud;
    std::vector<std::string> attributes;  // cloud.AttributeNames() of the full parse
    const bool keep = !options.positions_only && !summary;
    const bool streaming = summary && h.format != PlyFormat::kAscii && !vertex->HasLists();
    // An ascii vertex element a PlyPositionScan of exactly these bytes read whole, with the layout
    // and properties found here: its positions are taken, its lines not read again.
    const bool ascii_scanned = summary && scan && h.format == PlyFormat::kAscii && scan->complete() &&
                               scan->bytes == data.size() && scan->layout.format == PlyFormat::kAscii &&
                               &h.elements.front() == vertex &&
                               scan->layout == PositionLayout::Of(h, *vertex, h.body_offset) &&
                               scan->vertex.props == vertex->props;
    PositionStream stream;
    std::uint64_t vertex_count = 0;
    BodyReader body(data, file, h);
    for (const auto& e : h.elements) {
        std::vector<Sink> sinks(e.props.size());
        FaceSink faces;
        const bool skipped = ascii_scanned && &e == vertex;  // all its records are in the scan
        const std::uint64_t capacity = skipped ? e.count : body.MaxRecords(e);
        if (&e == vertex) {
            const std::uint64_t n = capacity;
            // Which property feeds which attribute is decided here, whether or not the values
            // are kept (positions_only): `claimed` marks the properties of the named attributes,
            // the rest become extras; `attributes` lists them as AttributeNames() would.
            std::vector<bool> claimed(e.props.size(), false);
            auto idx = [&](const char* name) { return e.Find(name); };
            auto bind_vec3 = [&](std::vector<Vec3f>& dst, const char* a, const char* b, const char* c, bool store) {
                const int ia = idx(a), ib = idx(b), ic = idx(c);
                if (ia < 0 || ib < 0 || ic < 0) return false;
                claimed[ia] = claimed[ib] = claimed[ic] = true;
                if (!store) return true;
                dst.resize(n);
                if (n == 0) return true;  // no records, no sinks (and no element to point into)
                float* base = dst.front().data();
                sinks[ia] = {base + 0, nullptr, 3, 1.0f};
                sinks[ib] = {base + 1, nullptr, 3, 1.0f};
                sinks[ic] = {base + 2, nullptr, 3, 1.0f};
                return true;
            };
            if (streaming || skipped) {  // the sinks point into one block; ReadFixedBinary fills it block by block
                const int ix = idx("x"), iy = idx("y"), iz = idx("z");
                claimed[ix] = claimed[iy] = claimed[iz] = true;
                if (streaming && n > 0) {
                    stream.scratch.resize(static_cast<std::size_t>(std::min(BlockRecords(e), n)));
                    float* base = stream.scratch.front().data();
                    sinks[ix] = {base + 0, nullptr, 3, 1.0f};
                    sinks[iy] = {base + 1, nullptr, 3, 1.0f};
                    sinks[iz] = {base + 2, nullptr, 3, 1.0f};
                }
            } else {
                bind_vec3(cloud.positions, "x", "y", "z", true);
            }
            if (bind_vec3(cloud.normals, "nx", "ny", "nz", keep) && n > 0) attributes.emplace_back("normals");
            const int ir = idx("red"), ig = idx("green"), ib = idx("blue"), ia = idx("alpha");
            if (ir >= 0 && ig >= 0 && ib >= 0) {
                const ScalarType ct = e.props[ir].type;
                const bool ok = (ct == ScalarType::kUInt8 || IsFloatType(ct)) && e.props[ig].type == ct &&
                                e.props[ib].type == ct && (ia < 0 || e.props[ia].type == ct);
                if (ok) {
                    claimed[ir] = claimed[ig] = claimed[ib] = true;
                    if (ia >= 0) claimed[ia] = true;
                    if (n > 0) attributes.emplace_back(ia >= 0 ? "colors(rgba)" : "colors(rgb)");
                }
                if (ok && keep) {
                    cloud.color_type = ct == ScalarType::kUInt8 ? ScalarType::kUInt8 : ScalarType::kFloat32;
                    cloud.color_has_alpha = ia >= 0;
                    cloud.colors.assign(n, {0.f, 0.f, 0.f, 1.f});
                    const float div = ct == ScalarType::kUInt8 ? 255.0f : 1.0f;
                    if (n > 0) {  // no records, no sinks (and no element to point into)
                        float* base = cloud.colors.front().data();
                        sinks[ir] = {base + 0, nullptr, 4, div};
                        sinks[ig] = {base + 1, nullptr, 4, div};
                        sinks[ib] = {base + 2, nullptr, 4, div};
                        if (ia >= 0) sinks[ia] = {base + 3, nullptr, 4, div};
                    }
                }
            }
            if (const int irad = idx("radius"); irad >= 0) {
                claimed[irad] = true;
                if (n > 0) attributes.emplace_back("radius");
                if (keep) {
                    cloud.radii.resize(n);
                    sinks[irad] = {cloud.radii.data(), nullptr, 1, 1.0f};
                }
            }
            std::size_t extra_count = 0;
            for (std::size_t k = 0; k < e.props.size(); ++k)
                if (!claimed[k] && !e.props[k].is_list) ++extra_count;
            cloud.extras.reserve(keep ? extra_count : 0);  // stable addresses for the sinks below
            for (std::size_t k = 0; k < e.props.size(); ++k) {
                if (claimed[k] || e.props[k].is_list) continue;
                attributes.push_back(e.props[k].name);
                if (!keep) continue;
                cloud.extras.push_back({e.props[k].name, e.props[k].type, std::vector<double>(n)});
                sinks[k] = {nullptr, cloud.extras.back().values.data(), 1, 1.0f};
            }
        } else if (e.name == "face") {
            for (std::size_t k = 0; k < e.props.size(); ++k)
                if (e.props[k].is_list && (e.props[k].name == "vertex_indices" || e.props[k].name == "vertex_index"))
                    faces.list_index = static_cast<int>(k);
            if (faces.list_index >= 0) {
                if (IsFloatType(e.props[faces.list_index].type))
                    Fail(file, "header line " + std::to_string(e.header_line) + ": face list '" + e.props[faces.list_index].name + "' has a floating-point item type");
                cloud.triangles.reserve(capacity);
                faces.triangles = &cloud.triangles;
            }
        }
        const bool streamed = streaming && &e == vertex;
        // The scan's result only for exactly these bytes and this layout (else: read them here).
        const bool scanned = streamed && scan && scan->complete() && scan->bytes == data.size() &&
                             scan->layout == PositionLayout::Of(h, e, body.position());
        if (skipped) {
            body.SkipAscii(static_cast<std::size_t>(scan->ascii_end), scan->line_no);
            stream.bounds = scan->stream.bounds;
            stream.first_bad = scan->stream.first_bad;
            stream.bad_value = scan->stream.bad_value;
            vertex_count = e.count;
            continue;
        }
        body.Read(e, sinks, faces.triangles ? &faces : nullptr, capacity, streamed ? &stream : nullptr,
                  scanned ? &scan->stream : nullptr);
        if (streamed) vertex_count = e.count;  // ReadFixedBinary refused a file too short for them
        if (faces.triangles && info) info->face_count = faces.polygons;
    }
    body.Finish();
    if (!streaming && !ascii_scanned) vertex_count = cloud.positions.size();

    // Validation of values (after all elements: a face element may precede the vertices).
    if (stream.first_bad != UINT64_MAX) Fail(file, NonFiniteMessage(stream.first_bad, stream.bad_value));
    for (std::size_t i = 0; i < cloud.positions.size(); ++i)
        if (!cloud.positions[i].allFinite()) Fail(file, NonFiniteMessage(i, cloud.positions[i]));
    for (std::size_t f = 0; f < cloud.triangles.size(); ++f)
        for (std::uint32_t v : cloud.triangles[f])
            if (v >= vertex_count)
                Fail(file, "face triangle " + std::to_string(f) + ": vertex index " +
                               (v == UINT32_MAX ? std::string("out of range") : std::to_string(v)) + " is not below the vertex count " +
                               std::to_string(vertex_count));
    if (summary) {
        summary->points = vertex_count;
        summary->bounds = streaming || ascii_scanned ? stream.bounds : cloud.Bounds();
        summary->attributes = attributes;
    }
    if (info) {
        info->attributes = std::move(attributes);
        info->format = h.format;
        info->comments = h.comments;
        info->elements.clear();
        for (const auto& e : h.elements) {
            PlyHeaderInfo::Element ie{e.name, e.count, {}};
            for (const auto& p : e.props)
                ie.properties.push_back(p.is_list ? std::string("list ") + ScalarTypeName(p.count_type) + " " + ScalarTypeName(p.type) + " " + p.name
                                                  : std::string(ScalarTypeName(p.type)) + " " + p.name);
            info->elements.push_back(std::move(ie));
        }
    }
    cloud.CheckConsistent();
    return cloud;
}

}  // namespace

PointCloud ParsePly(std::string_view data, std::string_view file, const PlyReadOptions& options, PlyHeaderInfo* info) {
    return ParsePlyImpl(data, file, options, info, nullptr);
}

PlySummary InspectPly(std::string_view data, std::string_view file, const PlyReadOptions& options) {
    return InspectPly(data, file, options, nullptr);
}

PlySummary InspectPly(std::string_view data, std::string_view file, const PlyReadOptions& options,
                      const PlyPositionScan* scan) {
    PlySummary summary;
    ParsePlyImpl(data, file, options, nullptr, &summary, scan ? scan->state_.get() : nullptr);
    return summary;
}

PlyPositionScan::PlyPositionScan(const PlyReadOptions& options) : state_(std::make_unique<State>()) {
    state_->options = options;
}

PlyPositionScan::~PlyPositionScan() = default;

void PlyPositionScan::Append(std::string_view bytes) noexcept {
    try {
        state_->Append(bytes);
    } catch (...) {  // an ascii record's error, or no memory for the scan: the whole-file pass reads
                     // the positions (and names the error)
        state_->Off();
    }
}

std::uint64_t PlyPositionScan::bytes() const { return state_->bytes; }

bool PlyPositionScan::complete() const { return state_->complete(); }

// ---- Writing ---------------------------------------------------------------------------------------

namespace {

template <typename T>
void AppendRaw(std::string& out, T v) {
    char b[sizeof(T)];
    std::memcpy(b, &v, sizeof(T));
    out.append(b, sizeof(T));
}

void AppendBinary(std::string& out, ScalarType t, double v) {
    switch (t) {
        case ScalarType::kInt8: return AppendRaw<std::int8_t>(out, static_cast<std::int8_t>(v));
        case ScalarType::kUInt8: return AppendRaw<std::uint8_t>(out, static_cast<std::uint8_t>(v));
        case ScalarType::kInt16: return AppendRaw<std::int16_t>(out, static_cast<std::int16_t>(v));
        case ScalarType::kUInt16: return AppendRaw<std::uint16_t>(out, static_cast<std::uint16_t>(v));
        case ScalarType::kInt32: return AppendRaw<std::int32_t>(out, static_cast<std::int32_t>(v));
        case ScalarType::kUInt32: return AppendRaw<std::uint32_t>(out, static_cast<std::uint32_t>(v));
        case ScalarType::kFloat32: return AppendRaw<float>(out, static_cast<float>(v));
        case ScalarType::kFloat64: return AppendRaw<double>(out, v);
    }
}

void AppendAscii(std::string& out, ScalarType t, double v) {
    char buf[64];
    std::to_chars_result r;
    if (t == ScalarType::kFloat32) r = std::to_chars(buf, buf + sizeof buf, static_cast<float>(v));
    else if (t == ScalarType::kFloat64) r = std::to_chars(buf, buf + sizeof buf, v);
    else r = std::to_chars(buf, buf + sizeof buf, static_cast<std::int64_t>(v));
    out.append(buf, r.ptr);
}

double ColorOut(const PointCloud& c, float v) {
    if (c.color_type == ScalarType::kUInt8) return std::lround(std::clamp(v, 0.0f, 1.0f) * 255.0f);
    return v;
}

}  // namespace

std::string FormatPly(const PointCloud& cloud, const PlyWriteOptions& options) {
    cloud.CheckConsistent();
    const bool ascii = options.format == PlyFormat::kAscii;
    SURFEL_CHECK(options.format != PlyFormat::kBinaryBigEndian || std::endian::native == std::endian::big,
                 "big-endian output is not supported on this machine");
    const ScalarType ct = cloud.color_type == ScalarType::kUInt8 ? ScalarType::kUInt8 : ScalarType::kFloat32;
    std::string out = "ply\nformat ";
    out += PlyFormatName(options.format);
    out += " 1.0\ncomment written by surfel\n";
    for (const auto& c : options.comments) out += "comment " + c + "\n";
    out += "element vertex " + std::to_string(cloud.size()) + "\n";
    out += "property float x\nproperty float y\nproperty float z\n";
    if (cloud.has_normals()) out += "property float nx\nproperty float ny\nproperty float nz\n";
    if (cloud.has_colors()) {
        for (const char* ch : {"red", "green", "blue", "alpha"}) {
            if (std::string_view(ch) == "alpha" && !cloud.color_has_alpha) break;
            out += std::string("property ") + ScalarTypeName(ct) + " " + ch + "\n";
        }
    }
    if (cloud.has_radii()) out += "property float radius\n";
    for (const auto& e : cloud.extras) out += std::string("property ") + ScalarTypeName(e.type) + " " + e.name + "\n";
    const bool faces = options.write_faces && !cloud.triangles.empty();
    if (faces) out += "element face " + std::to_string(cloud.triangles.size()) + "\nproperty list uchar int vertex_indices\n";
    out += "end_header\n";

    const int channels = cloud.color_has_alpha ? 4 : 3;
    if (!ascii) {
        std::size_t rec = 12 + (cloud.has_normals() ? 12 : 0) + (cloud.has_colors() ? channels * ScalarSize(ct) : 0) +
                          (cloud.has_radii() ? 4 : 0);
        for (const auto& e : cloud.extras) rec += ScalarSize(e.type);
        out.reserve(out.size() + rec * cloud.size() + (faces ? 13 * cloud.triangles.size() : 0));
    }
    for (std::size_t i = 0; i < cloud.size(); ++i) {
        if (ascii) {
            const auto& p = cloud.positions[i];
            AppendFloatAscii(out, p.x()); out += ' ';
            AppendFloatAscii(out, p.y()); out += ' ';
            AppendFloatAscii(out, p.z());
            if (cloud.has_normals())
                for (int k = 0; k < 3; ++k) { out += ' '; AppendFloatAscii(out, cloud.normals[i][k]); }
            if (cloud.has_colors())
                for (int k = 0; k < channels; ++k) { out += ' '; AppendAscii(out, ct, ColorOut(cloud, cloud.colors[i][k])); }
            if (cloud.has_radii()) { out += ' '; AppendFloatAscii(out, cloud.radii[i]); }
            for (const auto& e : cloud.extras) { out += ' '; AppendAscii(out, e.type, e.values[i]); }
            out += '\n';
        } else {
            out.append(reinterpret_cast<const char*>(cloud.positions[i].data()), 12);
            if (cloud.has_normals()) out.append(reinterpret_cast<const char*>(cloud.normals[i].data()), 12);
            if (cloud.has_colors())
                for (int k = 0; k < channels; ++k) AppendBinary(out, ct, ColorOut(cloud, cloud.colors[i][k]));
            if (cloud.has_radii()) AppendRaw<float>(out, cloud.radii[i]);
            for (const auto& e : cloud.extras) AppendBinary(out, e.type, e.values[i]);
        }
    }
    if (faces) {
        for (const auto& t : cloud.triangles) {
            if (ascii) {
                out += "3 " + std::to_string(t[0]) + " " + std::to_string(t[1]) + " " + std::to_string(t[2]) + "\n";
            } else {
                AppendRaw<std::uint8_t>(out, 3);
                for (auto v : t) AppendRaw<std::int32_t>(out, static_cast<std::int32_t>(v));
            }
        }
    }
    return out;
}

// ---- Files and sniffing ---------------------------------------------------------------------------

PointCloud ReadPly(const std::string& path, const PlyReadOptions& options, PlyHeaderInfo* info) {
    return ParsePly(ReadFileBytes(path), path, options, info);
}

void WritePly(const PointCloud& cloud, const std::string& path, const PlyWriteOptions& options) {
    WriteFileBytes(path, FormatPly(cloud, options));
}

bool HasPlyMagic(std::string_view bytes) { return bytes.starts_with("ply\n") || bytes.starts_with("ply\r\n"); }

PlyFormat SniffPlyFormat(std::string_view bytes) {
    std::size_t pos = 0;
    while (pos < bytes.size() && pos < PlyReadOptions{}.max_header_bytes) {
        std::size_t end = bytes.find('\n', pos);
        if (end == std::string_view::npos) end = bytes.size();
        const auto tok = Tokenize(bytes.substr(pos, end - pos));
        pos = end + 1;
        if (tok.empty() || tok[0] == "comment" || tok[0] == "obj_info") continue;
        if (tok[0] == "end_header") break;
        if (tok[0] != "format" || tok.size() < 2) continue;
        if (tok[1] == "binary_little_endian") return PlyFormat::kBinaryLittleEndian;
        if (tok[1] == "binary_big_endian") return PlyFormat::kBinaryBigEndian;
        break;
    }
    return PlyFormat::kAscii;
}

}  // namespace surfel
