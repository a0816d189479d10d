#include "surfel/io/image.h"

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>

#include <algorithm>
#include <cmath>
#include <filesystem>

#include "surfel/base/error.h"
#include "surfel/io/file_bytes.h"

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

namespace {
float LinearToSrgb(float v) {
    v = std::clamp(v, 0.0f, 1.0f);
    return v <= 0.0031308f ? 12.92f * v : 1.055f * std::pow(v, 1.0f / 2.4f) - 0.055f;
}
}  // namespace

std::string EncodeImage(const Image& image, ImageFormat format, const ImageWriteOptions& options) {
    SURFEL_CHECK(image.pixels.size() == std::size_t(image.width) * image.height * image.channels.size());
    std::vector<unsigned char> buffer;
    OIIO::Filesystem::IOVecOutput proxy(buffer);
    const char* name = format == ImageFormat::kExr ? "image.exr" : "image.png";
    auto out = OIIO::ImageOutput::create(OIIO::string_view(name), &proxy);
    if (!out) throw Error(ErrorCode::kInternal, std::string("OpenImageIO cannot write ") + name + ": " + OIIO::geterror());
    if (format == ImageFormat::kExr) {
        OIIO::ImageSpec spec(image.width, image.height, static_cast<int>(image.channels.size()),
                             options.half ? OIIO::TypeDesc::HALF : OIIO::TypeDesc::FLOAT);
        spec.channelnames = image.channels;
        const int a = image.ChannelIndex("A"), z = image.ChannelIndex("Z");
        spec.alpha_channel = a;
        spec.z_channel = z;
        spec.attribute("compression", "zip");
        if (!out->open(name, spec) || !out->write_image(OIIO::TypeDesc::FLOAT, image.pixels.data()) || !out->close())
            throw Error(ErrorCode::kInternal, "EXR encoding failed: " + out->geterror());
    } else {
        const int r = image.ChannelIndex("R"), g = image.ChannelIndex("G"), b = image.ChannelIndex("B");
        if (r < 0 || g < 0 || b < 0) throw Error(ErrorCode::kInvalidArgument, "PNG needs R, G and B channels");
        std::vector<unsigned char> rgb(std::size_t(image.width) * image.height * 3);
        for (int y = 0; y < image.height; ++y)
            for (int x = 0; x < image.width; ++x)
                for (int c = 0; c < 3; ++c)
                    rgb[(std::size_t(y) * image.width + x) * 3 + c] = static_cast<unsigned char>(
                        std::lround(255.0f * LinearToSrgb(image.At(x, y, c == 0 ? r : c == 1 ? g : b))));
        OIIO::ImageSpec spec(image.width, image.height, 3, OIIO::TypeDesc::UINT8);
        spec.attribute("oiio:ColorSpace", "sRGB");
        if (!out->open(name, spec) || !out->write_image(OIIO::TypeDesc::UINT8, rgb.data()) || !out->close())
            throw Error(ErrorCode::kInternal, "PNG encoding failed: " + out->geterror());
    }
    return std::string(buffer.begin(), buffer.end());
}

void WriteImage(const Image& image, const std::string& path, const ImageWriteOptions& options) {
    WriteFileBytes(path, EncodeImage(image, ImageFormatFromPath(path), options));
}

Image ReadImage(const std::string& path) {
    auto in = OIIO::ImageInput::open(path);
    if (!in) throw Error(ErrorCode::kNotFound, path + ": cannot read image: " + OIIO::geterror());
    const OIIO::ImageSpec& spec = in->spec();
    Image img;
    img.width = spec.width;
    img.height = spec.height;
    img.channels = spec.channelnames;
    img.pixels.resize(std::size_t(spec.width) * spec.height * spec.nchannels);
    if (!in->read_image(0, 0, 0, spec.nchannels, OIIO::TypeDesc::FLOAT, img.pixels.data()))
        throw Error(ErrorCode::kInvalidArgument, path + ": " + in->geterror());
    return img;
}

}  // namespace surfel
