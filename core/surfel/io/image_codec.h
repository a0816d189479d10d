#pragma once
/// \file
/// The C interface between the image functions of image.h and the image plugin
/// (`surfel_image_oiio.so`, OpenImageIO behind it), which they open with dlopen on first use so
/// that a command that writes no image never loads OpenImageIO's ~260 shared libraries.
///
/// Internal: only image.cpp (the host side) and image_codec_oiio.cpp (the plugin) include it.
/// Plain C types only, and no exception crosses it: the plugin reports failures through the
/// error callback and a status; the host turns them into surfel::Error. docs/startup.md has the
/// design.

#include <cstddef>
#include <cstdint>

extern "C" {

/// Version of this interface; the host refuses a plugin that reports another one.
inline constexpr std::uint32_t kSurfelImageCodecAbi = 1;

/// The name of the entry point the host looks up with dlsym.
inline constexpr const char* kSurfelImageCodecEntry = "surfel_image_codec_v1";

/// Status of a plugin call.
enum SurfelImageStatus : int {
    kSurfelImageOk = 0,
    kSurfelImageCannotOpen = 1,  ///< The file cannot be opened (maps to ErrorCode::kNotFound).
    kSurfelImageBadData = 2,     ///< The file or the pixels cannot be decoded (kInvalidArgument).
    kSurfelImageFailed = 3,      ///< The backend failed (kInternal).
};

/// How a pixel is stored in the encoded file.
enum SurfelImageStorage : int {
    kSurfelStorageFloat = 0,  ///< 32-bit float (EXR).
    kSurfelStorageHalf = 1,   ///< 16-bit half float (EXR).
    kSurfelStorageUint8 = 2,  ///< 8-bit unsigned (PNG); the pixels passed in are uint8 too.
};

/// Interleaved pixels to encode: width * height * channels values, row 0 at the top, float for
/// kSurfelStorageFloat/Half and uint8 for kSurfelStorageUint8.
struct SurfelImageView {
    int width, height, channels;
    const char* const* channel_names;  ///< `channels` names (R, G, B, A, Z, N.X, ...).
    int alpha_channel, z_channel;      ///< Index of A and Z, or -1.
    const void* pixels;
};

/// Receives the encoded bytes (possibly in several calls, in order).
typedef void (*SurfelImageSink)(void* context, const void* data, std::size_t size);
/// Receives the message of a failure (called once, before the call returns its status).
typedef void (*SurfelImageError)(void* context, const char* message);
/// Called once by `read` with the image's shape and channel names; returns a buffer of
/// width * height * channels floats that the plugin fills, or null to abort the read.
typedef float* (*SurfelImageAllocate)(void* context, int width, int height, int channels,
                                      const char* const* channel_names);

/// The plugin's functions. Every call is thread-safe and catches its own exceptions.
struct SurfelImageCodecV1 {
    std::uint32_t abi;    ///< kSurfelImageCodecAbi.
    const char* backend;  ///< e.g. "OpenImageIO 2.4.7".
    /// Encodes `image` as `format` ("exr", "png"); for EXR, `compression` names the scheme
    /// ("zip", or "zip:N" for zlib level N in 1..9, as OpenImageIO names it). The bytes go to
    /// `sink`, a failure's message to `error`.
    int (*encode)(const char* format, const SurfelImageView* image, int storage,
                  const char* compression, SurfelImageSink sink, void* sink_context,
                  SurfelImageError error, void* error_context);
    /// Reads the file at `path`, every channel as float, into the buffer `allocate` returns.
    int (*read)(const char* path, SurfelImageAllocate allocate, void* allocate_context,
                SurfelImageError error, void* error_context);
};

/// The plugin's one exported symbol (kSurfelImageCodecEntry).
typedef const SurfelImageCodecV1* (*SurfelImageCodecEntry)(void);

}  // extern "C"
