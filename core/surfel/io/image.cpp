// Images: the Image type, format choice and the PNG preview's sRGB conversion here; encoding and
// decoding in the image plugin (image_codec.h), opened with dlopen on first use.
#include "surfel/io/image.h"

#include <dlfcn.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <limits>

#include "surfel/base/error.h"
#include "surfel/io/file_bytes.h"
#include "surfel/io/image_codec.h"

#ifndef SURFEL_IMAGE_PLUGIN_NAME
#error "SURFEL_IMAGE_PLUGIN_NAME (the plugin's file name) is set by core/CMakeLists.txt"
#endif
#ifndef SURFEL_EXR_PLUGIN_NAME
#error "SURFEL_EXR_PLUGIN_NAME (the EXR plugin's file name) is set by core/CMakeLists.txt"
#endif
#ifndef SURFEL_IMAGE_PLUGIN_INSTALL_RELDIR
#error "SURFEL_IMAGE_PLUGIN_INSTALL_RELDIR (the installed plugin's folder, from bin/) is set by core/CMakeLists.txt"
#endif

namespace surfel {

int Image::ChannelIndex(const std::string& name) const {
    for (std::size_t i = 0; i < channels.size(); ++i)
        if (channels[i] == name) return static_cast<int>(i);
    return -1;
}

ImageFormat ImageFormatFromPath(const std::string& path) {
    std::string ext = std::filesystem::path(path).extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
    if (ext == ".exr") return ImageFormat::kExr;
    if (ext == ".png") return ImageFormat::kPng;
    throw Error(ErrorCode::kInvalidArgument, path + ": unknown image extension '" + ext + "' (expected .exr or .png)");
}

// ---- Finding and opening the plugins ----------------------------------------------------------
// Two plugins, each opened once per process on first use: surfel_image_oiio.so (OpenImageIO:
// reads, PNG) and surfel_image_exr.so (OpenEXR alone: the EXR a render writes, the same bytes
// for a fraction of the loading). Each is found by its own variable, then beside the executable,
// then in the installed layout.

namespace {

struct PluginKind {
    const char* file;  // the module's file name
    const char* env;   // the variable that names it (only it, when set)
};
constexpr PluginKind kOiioPlugin{SURFEL_IMAGE_PLUGIN_NAME, "SURFEL_IMAGE_PLUGIN"};
constexpr PluginKind kExrPlugin{SURFEL_EXR_PLUGIN_NAME, "SURFEL_EXR_PLUGIN"};

std::vector<std::string> SearchPath(const PluginKind& kind) {
    if (const char* explicit_path = std::getenv(kind.env); explicit_path && *explicit_path) return {explicit_path};
    std::error_code ec;
    const std::filesystem::path exe = std::filesystem::read_symlink("/proc/self/exe", ec);
    if (ec) return {};
    const std::filesystem::path dir = exe.parent_path();
    return {(dir / kind.file).string(),
            (dir / SURFEL_IMAGE_PLUGIN_INSTALL_RELDIR / kind.file).lexically_normal().string()};
}

}  // namespace

std::vector<std::string> ImageCodecSearchPath() { return SearchPath(kOiioPlugin); }
std::vector<std::string> ExrCodecSearchPath() { return SearchPath(kExrPlugin); }

namespace {

struct LoadedCodec {
    const SurfelImageCodecV1* codec = nullptr;
    std::string description;  ///< backend (path), or why loading failed
};

// Tries each candidate in order; the first that opens and has the right interface wins.
LoadedCodec OpenCodec(const PluginKind& kind) {
    const std::vector<std::string> candidates = SearchPath(kind);
    std::string tried;
    for (const std::string& path : candidates) {
        // RTLD_LAZY: of the ~260 libraries' function symbols only those called get bound (RTLD_NOW
        // binds them all up front: 13,000 more relocations); RTLD_LOCAL: OpenImageIO's symbols
        // stay out of the global namespace. The plugin links with --no-undefined, so a lazy symbol cannot be
        // missing from its own code.
        void* handle = ::dlopen(path.c_str(), RTLD_LAZY | RTLD_LOCAL);
        if (!handle) {
            std::string why = ::dlerror();  // usually "<path>: <reason>"
            if (why.rfind(path + ": ", 0) == 0) why.erase(0, path.size() + 2);
            tried += "\n  " + path + ": " + why;
            continue;
        }
        auto entry = reinterpret_cast<SurfelImageCodecEntry>(::dlsym(handle, kSurfelImageCodecEntry));
        const SurfelImageCodecV1* codec = entry ? entry() : nullptr;
        if (!codec || codec->abi != kSurfelImageCodecAbi) {
            tried += "\n  " + path + ": " +
                     (codec ? "interface version " + std::to_string(codec->abi) + ", expected " +
                                  std::to_string(kSurfelImageCodecAbi)
                            : std::string("no ") + kSurfelImageCodecEntry + " in it");
            ::dlclose(handle);
            continue;
        }
        // Never closed: the codec's functions stay valid until exit.
        return {codec, std::string(codec->backend) + " (" + path + ")"};
    }
    if (candidates.empty()) tried = "\n  (cannot read /proc/self/exe to find the executable's folder)";
    return {nullptr, std::string("cannot load the image plugin ") + kind.file +
                         " (install it beside the executable or set " + kind.env + " to its path); tried:" + tried};
}

const LoadedCodec& Loaded() {
    static const LoadedCodec loaded = OpenCodec(kOiioPlugin);  // once per process, thread-safe
    return loaded;
}

const LoadedCodec& LoadedExr() {
    static const LoadedCodec loaded = OpenCodec(kExrPlugin);
    return loaded;
}

const SurfelImageCodecV1& Codec() {
    const LoadedCodec& loaded = Loaded();
    if (!loaded.codec) throw Error(ErrorCode::kFailedPrecondition, "image support is not available: " + loaded.description);
    return *loaded.codec;
}

// The codec that writes EXR: the EXR plugin, else the OpenImageIO plugin (the same bytes);
// `description` gets the one used.
const SurfelImageCodecV1& ExrCodec(std::string* description = nullptr) {
    const LoadedCodec& exr = LoadedExr();
    const LoadedCodec& used = exr.codec ? exr : Loaded();
    if (!used.codec)
        throw Error(ErrorCode::kFailedPrecondition, "EXR output is not available: " + exr.description + "; and " +
                                                        Loaded().description);
    if (description) *description = used.description;
    return *used.codec;
}

ErrorCode CodeOf(int status) {
    switch (status) {
        case kSurfelImageCannotOpen: return ErrorCode::kNotFound;
        case kSurfelImageBadData: return ErrorCode::kInvalidArgument;
        default: return ErrorCode::kInternal;
    }
}

// The sinks run inside the plugin's calls. A failed allocation there terminates (noexcept), as it
// would for any allocation the encoder makes; the plugin itself catches its own.
void AppendBytes(void* context, const void* data, std::size_t size) noexcept {
    static_cast<std::string*>(context)->append(static_cast<const char*>(data), size);
}
void KeepMessage(void* context, const char* message) noexcept { *static_cast<std::string*>(context) = message; }

float LinearToSrgb(float v) {
    v = std::clamp(v, 0.0f, 1.0f);
    return v <= 0.0031308f ? 12.92f * v : 1.055f * std::pow(v, 1.0f / 2.4f) - 0.055f;
}

}  // namespace

std::string LoadImageCodec() {
    Codec();
    return Loaded().description;
}

std::string LoadImageCodec(ImageFormat format) {
    if (format != ImageFormat::kExr) return LoadImageCodec();
    std::string description;
    ExrCodec(&description);
    return description;
}

// ---- Encoding and decoding through the plugin -------------------------------------------------

std::string EncodeImage(const Image& image, ImageFormat format, const ImageWriteOptions& options) {
    SURFEL_CHECK(image.pixels.size() == std::size_t(image.width) * image.height * image.channels.size());
    const SurfelImageCodecV1& codec = format == ImageFormat::kExr ? ExrCodec() : Codec();
    std::vector<const char*> names;
    SurfelImageView view{image.width, image.height, 0, nullptr, -1, -1, nullptr};
    int storage = kSurfelStorageFloat;
    const char* compression = nullptr;
    std::vector<unsigned char> rgb;
    if (format == ImageFormat::kExr) {
        for (const std::string& c : image.channels) names.push_back(c.c_str());
        view.channels = static_cast<int>(image.channels.size());
        view.alpha_channel = image.ChannelIndex("A");
        view.z_channel = image.ChannelIndex("Z");
        view.pixels = image.pixels.data();
        storage = options.half ? kSurfelStorageHalf : kSurfelStorageFloat;
        // ZIP at zlib level 1: 1.3 % more bytes than the default level 4 on the paper's render
        // (692,693 against 683,928), a quarter less of the encode's CPU; the same pixels.
        compression = "zip:1";
    } else {
        // PNG: the preview, R, G, B as 8-bit sRGB.
        const int r = image.ChannelIndex("R"), g = image.ChannelIndex("G"), b = image.ChannelIndex("B");
        if (r < 0 || g < 0 || b < 0) throw Error(ErrorCode::kInvalidArgument, "PNG needs R, G and B channels");
        rgb.resize(std::size_t(image.width) * image.height * 3);
        for (int y = 0; y < image.height; ++y)
            for (int x = 0; x < image.width; ++x)
                for (int c = 0; c < 3; ++c)
                    rgb[(std::size_t(y) * image.width + x) * 3 + c] = static_cast<unsigned char>(
                        std::lround(255.0f * LinearToSrgb(image.At(x, y, c == 0 ? r : c == 1 ? g : b))));
        names = {"R", "G", "B"};
        view.channels = 3;
        view.pixels = rgb.data();
        storage = kSurfelStorageUint8;
    }
    view.channel_names = names.data();
    std::string bytes, message;
    const int status = codec.encode(format == ImageFormat::kExr ? "exr" : "png", &view, storage, compression,
                                    &AppendBytes, &bytes, &KeepMessage, &message);
    if (status != kSurfelImageOk) throw Error(CodeOf(status), message);
    return bytes;
}

void WriteImage(const Image& image, const std::string& path, const ImageWriteOptions& options) {
    WriteFileBytes(path, EncodeImage(image, ImageFormatFromPath(path), options));
}

Image ReadImage(const std::string& path) {
    const SurfelImageCodecV1& codec = Codec();
    Image img;
    // Called from inside the plugin: no exception may leave it.
    auto allocate = [](void* context, int width, int height, int channels, const char* const* names) noexcept
        -> float* {
        Image& out = *static_cast<Image*>(context);
        if (width < 0 || height < 0 || channels < 0) return nullptr;
        const std::size_t count = std::size_t(width) * std::size_t(height) * std::size_t(channels);
        if (count > std::numeric_limits<std::size_t>::max() / sizeof(float) / 2) return nullptr;
        try {
            out.width = width;
            out.height = height;
            out.channels.assign(names, names + channels);
            out.pixels.assign(count, 0.0f);
        } catch (const std::bad_alloc&) {
            return nullptr;
        }
        return out.pixels.data();
    };
    std::string message;
    const int status = codec.read(path.c_str(), allocate, &img, &KeepMessage, &message);
    if (status != kSurfelImageOk) throw Error(CodeOf(status), message);
    return img;
}

}  // namespace surfel
