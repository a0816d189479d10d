#pragma once
/// \file
/// Whole files as bytes: read into memory, written atomically.

#include <string>
#include <string_view>

namespace surfel {

/// Reads a whole file into memory (pipes and special files too, which report no size).
/// Throws Error(kInvalidArgument) for a directory, Error(kNotFound) when the file cannot be
/// opened, Error(kInternal) on a short read.
std::string ReadFileBytes(const std::string& path);

/// Writes `bytes` to `path` atomically: into `<path>.tmp-surfel`, then renamed into place, so a
/// reader sees the old file or the whole new one. Throws Error(kNotFound) when the file cannot be
/// created or renamed, Error(kInternal) when the write fails.
void WriteFileBytes(const std::string& path, std::string_view bytes);

}  // namespace surfel
