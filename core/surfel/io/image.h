#pragma once
/// \file
/// Float images with named channels, written through OpenImageIO (EXR, PNG).

#include <string>
#include <vector>

namespace surfel {

/// An interleaved float image; row 0 is the top row.
struct Image {
    int width = 0, height = 0;
    std::vector<std::string> channels;  ///< e.g. R, G, B, A, Z, N.X, N.Y, N.Z
    std::vector<float> pixels;          ///< width * height * channels.size()
    int ChannelIndex(const std::string& name) const;
    float& At(int x, int y, int c) { return pixels[(std::size_t(y) * width + x) * channels.size() + c]; }
    float At(int x, int y, int c) const { return pixels[(std::size_t(y) * width + x) * channels.size() + c]; }
};

enum class ImageFormat { kExr, kPng };

struct ImageWriteOptions {
    bool half = false;  ///< EXR: 16-bit half floats instead of 32-bit floats.
};

/// Format from the extension (.exr, .png); throws Error(kInvalidArgument) otherwise.
ImageFormat ImageFormatFromPath(const std::string& path);

/// Encodes in memory. EXR keeps every channel (float or half); PNG writes R, G, B as 8-bit sRGB
/// (values clamped to [0, 1]) for a preview.
std::string EncodeImage(const Image& image, ImageFormat format, const ImageWriteOptions& options = {});

/// Writes a file (format from the extension), atomically.
void WriteImage(const Image& image, const std::string& path, const ImageWriteOptions& options = {});

/// Reads an image file with OpenImageIO (all channels as float); for tests and tools.
Image ReadImage(const std::string& path);

}  // namespace surfel
