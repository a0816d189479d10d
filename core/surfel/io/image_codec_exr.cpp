// The EXR plugin: image_codec.h's interface over OpenEXR itself, for the one thing a render
// writes. Built as the module surfel_image_exr.so beside the executables; image.cpp opens it for
// EXR encodes instead of surfel_image_oiio.so, whose OpenImageIO pulls ~260 shared libraries
// (about 0.3 s of CPU per process) where OpenEXR needs five. It writes the file OpenImageIO
// 2.4's EXR writer writes for the same call, byte for byte: a scanline file with the channels,
// ZIP compression (16 rows a block; zlib level 4 or the "zip:N" asked for), the windows, increasing-y line order, the default pixel
// aspect and screen window, and `capDate` (the local time, "YYYY:MM:DD HH:MM:SS"), which
// OpenImageIO sets when no DateTime is given; half storage is rounded by Imath's half (to
// nearest even), as OpenImageIO's conversion does. test_image_codecs compares the two plugins'
// bytes. It encodes only: reads and PNG stay with the OpenImageIO plugin.
#include <Imath/half.h>
#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfIO.h>
#include <OpenEXR/ImfOutputFile.h>
#include <OpenEXR/ImfStringAttribute.h>
#include <OpenEXR/ImfThreading.h>
#include <OpenEXR/OpenEXRConfig.h>

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <exception>
#include <string>
#include <thread>
#include <vector>

#include "surfel/io/image_codec.h"

namespace {

// An in-memory Imf::OStream (OpenEXR seeks back once, to fill in the line offset table).
class MemoryStream : public Imf::OStream {
public:
    MemoryStream() : Imf::OStream("image.exr") {}
    void write(const char c[], int n) override {
        if (pos_ + std::size_t(n) > bytes_.size()) bytes_.resize(pos_ + std::size_t(n));
        std::memcpy(bytes_.data() + pos_, c, std::size_t(n));
        pos_ += std::size_t(n);
    }
    std::uint64_t tellp() override { return pos_; }
    void seekp(std::uint64_t pos) override { pos_ = pos; }
    const std::vector<char>& bytes() const { return bytes_; }

private:
    std::vector<char> bytes_;
    std::size_t pos_ = 0;
};

// OpenImageIO's default DateTime (exroutput.cpp, spec_to_header): the local time of the encode.
std::string LocalCapDate() {
    const std::time_t now = std::time(nullptr);
    std::tm tm{};
    localtime_r(&now, &tm);
    char text[80];
    std::snprintf(text, sizeof text, "%04d:%02d:%02d %02d:%02d:%02d", tm.tm_year + 1900, tm.tm_mon + 1, tm.tm_mday,
                  tm.tm_hour, tm.tm_min, tm.tm_sec);
    return text;
}

int Encode(const char* format, const SurfelImageView* image, int storage, const char* compression,
           SurfelImageSink sink, void* sink_context, SurfelImageError error, void* error_context) noexcept {
    try {
        if (std::strcmp(format, "exr") != 0) {
            error(error_context, (std::string("the EXR plugin cannot write ") + format).c_str());
            return kSurfelImageFailed;
        }
        if (storage != kSurfelStorageFloat && storage != kSurfelStorageHalf) {
            error(error_context, "the EXR plugin writes float or half pixels only");
            return kSurfelImageFailed;
        }
        // "zip" (zlib level 4, OpenEXR's and OpenImageIO's default) or "zip:N", level N in 1..9, as
        // OpenImageIO names it; the level is not stored in the file.
        int zip_level = 0;
        if (compression && *compression && std::strcmp(compression, "zip") != 0) {
            if (std::strncmp(compression, "zip:", 4) == 0 && compression[4] >= '1' && compression[4] <= '9' &&
                compression[5] == '\0') {
                zip_level = compression[4] - '0';
            } else {
                error(error_context, (std::string("the EXR plugin does not write compression ") + compression).c_str());
                return kSurfelImageFailed;
            }
        }
        const int w = image->width, h = image->height, nc = image->channels;
        if (w < 1 || h < 1 || nc < 1) {
            error(error_context, "EXR encoding failed: the image is empty");
            return kSurfelImageFailed;
        }
        const bool half = storage == kSurfelStorageHalf;
        const Imf::PixelType type = half ? Imf::HALF : Imf::FLOAT;
        Imf::Header header(w, h);
        header.compression() = Imf::ZIP_COMPRESSION;
        if (zip_level > 0) header.zipCompressionLevel() = zip_level;
        header.insert("capDate", Imf::StringAttribute(LocalCapDate()));
        for (int c = 0; c < nc; ++c) header.channels().insert(image->channel_names[c], Imf::Channel(type, 1, 1, false));

        const auto* pixels = static_cast<const float*>(image->pixels);
        const std::size_t count = std::size_t(w) * std::size_t(h) * std::size_t(nc);
        std::vector<Imath::half> halves;
        if (half) {
            halves.resize(count);
            for (std::size_t i = 0; i < count; ++i) halves[i] = Imath::half(pixels[i]);
        }
        const std::size_t elem = half ? sizeof(Imath::half) : sizeof(float);
        char* base = half ? reinterpret_cast<char*>(halves.data()) : const_cast<char*>(reinterpret_cast<const char*>(pixels));
        Imf::FrameBuffer fb;
        for (int c = 0; c < nc; ++c)
            fb.insert(image->channel_names[c],
                      Imf::Slice(type, base + std::size_t(c) * elem, elem * std::size_t(nc), elem * std::size_t(nc) * w));
        // ZIP blocks compressed on every core, as OpenImageIO has OpenEXR do (its default thread
        // count): the bytes do not depend on it. Once per process; the pool lives until exit.
        static const bool threads = [] {
            Imf::setGlobalThreadCount(static_cast<int>(std::max(1u, std::thread::hardware_concurrency())));
            return true;
        }();
        (void)threads;
        MemoryStream stream;
        {
            Imf::OutputFile out(stream, header);  // the file is complete when `out` is destroyed
            out.setFrameBuffer(fb);
            out.writePixels(h);
        }
        sink(sink_context, stream.bytes().data(), stream.bytes().size());
        return kSurfelImageOk;
    } catch (const std::exception& e) {
        error(error_context, (std::string("EXR encoding failed: ") + e.what()).c_str());
        return kSurfelImageFailed;
    } catch (...) {
        error(error_context, "OpenEXR threw an unknown exception");
        return kSurfelImageFailed;
    }
}

int Read(const char* path, SurfelImageAllocate, void*, SurfelImageError error, void* error_context) noexcept {
    error(error_context, (std::string(path) + ": the EXR plugin does not read images").c_str());
    return kSurfelImageFailed;
}

const SurfelImageCodecV1 kCodec = {kSurfelImageCodecAbi, "OpenEXR " OPENEXR_VERSION_STRING, &Encode, &Read};

}  // namespace

extern "C" __attribute__((visibility("default"))) const SurfelImageCodecV1* surfel_image_codec_v1(void) {
    return &kCodec;
}
