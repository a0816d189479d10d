#include "surfel/io/text_internal.h"

#include <charconv>

#include "surfel/base/error.h"

namespace surfel::io_internal {

void Fail(std::string_view file, const std::string& message) {
    throw Error(ErrorCode::kInvalidArgument, std::string(file) + ": " + message);
}

bool IsBlank(std::string_view bytes) {
    return bytes.find_first_not_of(" \t\r\n") == std::string_view::npos;
}

std::vector<std::string_view> Tokenize(std::string_view line) {
    std::vector<std::string_view> out;
    std::size_t i = 0;
    while (i < line.size()) {
        while (i < line.size() && (line[i] == ' ' || line[i] == '\t' || line[i] == '\r')) ++i;
        std::size_t j = i;
        while (j < line.size() && line[j] != ' ' && line[j] != '\t' && line[j] != '\r') ++j;
        if (j > i) out.push_back(line.substr(i, j - i));
        i = j;
    }
    return out;
}

std::string Quote(std::string_view s) {
    std::string q = "'";
    for (char c : s.substr(0, 40)) q += (static_cast<unsigned char>(c) < 32 || c == 127) ? '?' : c;
    if (s.size() > 40) q += "...";
    return q + "'";
}

void AppendFloatAscii(std::string& out, float v) {
    char buf[32];
    auto r = std::to_chars(buf, buf + sizeof buf, v);
    out.append(buf, r.ptr);
}

}  // namespace surfel::io_internal
