#pragma once
/// \file
/// Internal to surfel_io (not part of its interface): the error, tokenising and number-printing
/// helpers shared by the text readers and writers (PLY ascii, XYZ).

#include <string>
#include <string_view>
#include <vector>

namespace surfel::io_internal {

/// Throws Error(kInvalidArgument) with the message "<file>: <message>".
[[noreturn]] void Fail(std::string_view file, const std::string& message);

/// True when `bytes` is empty or holds only spaces, tabs, CR and LF: no content at all.
bool IsBlank(std::string_view bytes);

/// Splits a line at spaces, tabs and carriage returns; empty fields are dropped.
std::vector<std::string_view> Tokenize(std::string_view line);

/// Quotes a field for an error message: at most 40 characters, control characters as '?'.
std::string Quote(std::string_view s);

/// Appends the shortest decimal that reads back as `v` (std::to_chars).
void AppendFloatAscii(std::string& out, float v);

}  // namespace surfel::io_internal
