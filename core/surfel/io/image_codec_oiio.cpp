// The image plugin: image_codec.h's interface over OpenImageIO. Built as the module
// surfel_image_oiio.so beside the executables; image.cpp opens it on first use.
#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>

#include <exception>
#include <string>
#include <vector>

#include "surfel/io/image_codec.h"

namespace {

// Encode: one in-memory file through OpenImageIO's IOProxy.
int Encode(const char* format, const SurfelImageView* image, int storage, const char* compression,
           SurfelImageSink sink, void* sink_context, SurfelImageError error,
           void* error_context) noexcept {
    try {
        std::vector<unsigned char> buffer;
        OIIO::Filesystem::IOVecOutput proxy(buffer);
        const std::string name = std::string("image.") + format;
        auto out = OIIO::ImageOutput::create(OIIO::string_view(name), &proxy);
        if (!out) {
            error(error_context, ("OpenImageIO cannot write " + name + ": " + OIIO::geterror()).c_str());
            return kSurfelImageFailed;
        }
        const OIIO::TypeDesc stored = storage == kSurfelStorageHalf    ? OIIO::TypeDesc::HALF
                                      : storage == kSurfelStorageUint8 ? OIIO::TypeDesc::UINT8
                                                                       : OIIO::TypeDesc::FLOAT;
        const OIIO::TypeDesc given =
            storage == kSurfelStorageUint8 ? OIIO::TypeDesc::UINT8 : OIIO::TypeDesc::FLOAT;
        OIIO::ImageSpec spec(image->width, image->height, image->channels, stored);
        spec.channelnames.assign(image->channel_names, image->channel_names + image->channels);
        spec.alpha_channel = image->alpha_channel;
        spec.z_channel = image->z_channel;
        if (compression && *compression) spec.attribute("compression", compression);
        if (storage == kSurfelStorageUint8) spec.attribute("oiio:ColorSpace", "sRGB");
        if (!out->open(name, spec) || !out->write_image(given, image->pixels) || !out->close()) {
            error(error_context, (std::string(format) + " encoding failed: " + out->geterror()).c_str());
            return kSurfelImageFailed;
        }
        sink(sink_context, buffer.data(), buffer.size());
        return kSurfelImageOk;
    } catch (const std::exception& e) {
        error(error_context, e.what());
        return kSurfelImageFailed;
    } catch (...) {
        error(error_context, "OpenImageIO threw an unknown exception");
        return kSurfelImageFailed;
    }
}

// Read: every channel of the first subimage as float.
int Read(const char* path, SurfelImageAllocate allocate, void* allocate_context,
         SurfelImageError error, void* error_context) noexcept {
    try {
        auto in = OIIO::ImageInput::open(path);
        if (!in) {
            error(error_context, (std::string(path) + ": cannot read image: " + OIIO::geterror()).c_str());
            return kSurfelImageCannotOpen;
        }
        const OIIO::ImageSpec& spec = in->spec();
        std::vector<const char*> names;
        for (const std::string& n : spec.channelnames) names.push_back(n.c_str());
        float* pixels = allocate(allocate_context, spec.width, spec.height, spec.nchannels, names.data());
        if (!pixels) {
            error(error_context, (std::string(path) + ": image too large to read").c_str());
            return kSurfelImageBadData;
        }
        if (!in->read_image(0, 0, 0, spec.nchannels, OIIO::TypeDesc::FLOAT, pixels)) {
            error(error_context, (std::string(path) + ": " + in->geterror()).c_str());
            return kSurfelImageBadData;
        }
        return kSurfelImageOk;
    } catch (const std::exception& e) {
        error(error_context, e.what());
        return kSurfelImageFailed;
    } catch (...) {
        error(error_context, "OpenImageIO threw an unknown exception");
        return kSurfelImageFailed;
    }
}

const SurfelImageCodecV1 kCodec = {kSurfelImageCodecAbi, "OpenImageIO " OIIO_VERSION_STRING, &Encode, &Read};

}  // namespace

extern "C" __attribute__((visibility("default"))) const SurfelImageCodecV1* surfel_image_codec_v1(void) {
    return &kCodec;
}
