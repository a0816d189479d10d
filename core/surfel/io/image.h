#pragma once
/// \file
/// Float images with named channels, written and read as EXR and PNG through the image plugin.
///
/// The Image type and ImageFormatFromPath need nothing else. EncodeImage, WriteImage and ReadImage
/// open the plugin (`surfel_image_oiio.so`, OpenImageIO behind it) with dlopen on their first
/// call, so that a program that never touches an image never loads OpenImageIO's ~260 shared
/// libraries (docs/startup.md). The plugin is looked for, in order: the file named by the
/// environment variable SURFEL_IMAGE_PLUGIN (only it, when set); the executable's own folder
/// (build/bin/ in a build tree); `<libdir>/surfel/` of an installed tree, found from the executable's
/// folder (`<bindir>/../lib/surfel/` for the default GNU layout). When none opens,
/// these functions throw Error(kFailedPrecondition) naming every path tried and why it failed.
///
/// Writing EXR (what a render writes) opens a smaller plugin first, `surfel_image_exr.so`
/// (OpenEXR alone: five shared libraries, not ~260), found the same way with the variable
/// SURFEL_EXR_PLUGIN; it writes the bytes the OpenImageIO plugin writes for the same image (the
/// `capDate` header aside, the local time of the encode in both). Where it cannot be loaded, EXR
/// goes through the OpenImageIO plugin; where neither can, Error(kFailedPrecondition) names the
/// paths tried for both.

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

/// The formats an image is written as.
enum class ImageFormat { kExr, kPng };

/// How EncodeImage and WriteImage store the pixels.
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

/// Reads an image file (all channels as float); for tests and tools. Throws Error(kNotFound) when
/// the file cannot be opened, Error(kInvalidArgument) when it cannot be decoded.
Image ReadImage(const std::string& path);

/// Opens the image plugin now, if it is not open yet (EncodeImage, WriteImage and ReadImage do it on
/// first use); a command calls it before long work whose result is an image, so that a missing
/// plugin fails first. Returns the backend and the plugin's path, e.g.
/// "OpenImageIO 2.4.7.0 (/opt/surfel/bin/surfel_image_oiio.so)". Throws Error(kFailedPrecondition)
/// naming every path tried. Thread-safe; the outcome is decided once per process.
std::string LoadImageCodec();

/// Opens what writing `format` needs, if not open yet: for kExr the EXR plugin (or, failing
/// that, the OpenImageIO plugin), for kPng the OpenImageIO plugin (as LoadImageCodec()). Returns
/// the backend and path of the plugin that will write it, e.g.
/// "OpenEXR 3.1.5 (/opt/surfel/bin/surfel_image_exr.so)". Throws Error(kFailedPrecondition)
/// naming every path tried. Thread-safe; each plugin's outcome is decided once per process.
std::string LoadImageCodec(ImageFormat format);

/// Where the OpenImageIO plugin is looked for, in order (see the file comment); empty when the executable's
/// folder cannot be found (no /proc).
std::vector<std::string> ImageCodecSearchPath();

/// Where the EXR plugin (OpenEXR alone) is looked for, in order; empty as above.
std::vector<std::string> ExrCodecSearchPath();

}  // namespace surfel
