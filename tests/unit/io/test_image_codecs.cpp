// The two image plugins write the same EXR (issue 19.1): the EXR plugin (OpenEXR alone) must give
// the bytes of the OpenImageIO plugin for every image the host hands it, the capDate header (the
// local time of each encode) aside. Both plugins are opened here directly, from the paths ctest
// sets (SURFEL_IMAGE_PLUGIN, SURFEL_EXR_PLUGIN), and through the host's EncodeImage.
#include <dlfcn.h>
#include <gtest/gtest.h>

#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/io/image.h"
#include "surfel/io/image_codec.h"

namespace surfel {
namespace {

const SurfelImageCodecV1* OpenPlugin(const char* variable) {
    const char* path = std::getenv(variable);
    if (!path || !*path) return nullptr;
    void* handle = ::dlopen(path, RTLD_LAZY | RTLD_LOCAL);
    if (!handle) return nullptr;
    auto entry = reinterpret_cast<SurfelImageCodecEntry>(::dlsym(handle, kSurfelImageCodecEntry));
    return entry ? entry() : nullptr;
}

void Append(void* context, const void* data, std::size_t size) noexcept {
    static_cast<std::string*>(context)->append(static_cast<const char*>(data), size);
}
void Keep(void* context, const char* message) noexcept { *static_cast<std::string*>(context) = message; }

std::string Encode(const SurfelImageCodecV1& codec, const Image& image, int storage, std::string* message,
                   const char* compression = "zip") {
    std::vector<const char*> names;
    for (const std::string& c : image.channels) names.push_back(c.c_str());
    const SurfelImageView view{image.width, image.height, static_cast<int>(names.size()), names.data(),
                               image.ChannelIndex("A"), image.ChannelIndex("Z"), image.pixels.data()};
    std::string bytes;
    const int status = codec.encode("exr", &view, storage, compression, &Append, &bytes, &Keep, message);
    return status == kSurfelImageOk ? bytes : std::string();
}

// The file with its capDate value (a string attribute: name, type, 4-byte size, value) blanked.
std::string WithoutDate(std::string exr) {
    static const std::string key("capDate\0string\0", 15);
    const std::size_t at = exr.find(key);
    EXPECT_NE(at, std::string::npos) << "no capDate header";
    if (at == std::string::npos || at + key.size() + 4 > exr.size()) return exr;
    std::int32_t size = 0;
    std::memcpy(&size, exr.data() + at + key.size(), 4);
    EXPECT_EQ(size, 19) << "capDate is YYYY:MM:DD HH:MM:SS";
    for (std::int32_t i = 0; i < size && at + key.size() + 4 + i < exr.size(); ++i) exr[at + key.size() + 4 + i] = '#';
    return exr;
}

// A render-shaped image: 8 channels, with the values a render writes (+inf depth on a miss) and
// those that test the half conversion (overflow, the largest half, subnormals, -0, NaN).
Image TestImage(int width, int height, std::vector<std::string> channels) {
    Image img;
    img.width = width;
    img.height = height;
    img.channels = std::move(channels);
    const std::size_t n = std::size_t(width) * height * img.channels.size();
    img.pixels.resize(n);
    std::uint64_t x = 88172645463325252ULL;
    for (std::size_t i = 0; i < n; ++i) {
        x ^= x << 13, x ^= x >> 7, x ^= x << 17;
        img.pixels[i] = float(double(x >> 11) * 0x1.0p-53 * 2.0 - 0.5);
    }
    const float specials[] = {std::numeric_limits<float>::infinity(), -std::numeric_limits<float>::infinity(),
                              std::numeric_limits<float>::quiet_NaN(), 70000.0f, 65504.0f, 65519.0f, 65520.0f,
                              6.1e-5f, 3.0e-8f, 1.0e-9f, -0.0f, 1.0f + 0x1.0p-11f, 1.0f + 0x1.8p-11f};
    for (std::size_t k = 0; k < std::size(specials) && k < n; ++k) img.pixels[k * 7 % n] = specials[k];
    return img;
}

class ImageCodecs : public ::testing::Test {
protected:
    void SetUp() override {
        oiio_ = OpenPlugin("SURFEL_IMAGE_PLUGIN");
        exr_ = OpenPlugin("SURFEL_EXR_PLUGIN");
        if (!oiio_ || !exr_) GTEST_FAIL() << "SURFEL_IMAGE_PLUGIN and SURFEL_EXR_PLUGIN must name the plugins (ctest sets them)";
    }
    const SurfelImageCodecV1* oiio_ = nullptr;
    const SurfelImageCodecV1* exr_ = nullptr;
};

TEST_F(ImageCodecs, TheExrPluginWritesTheBytesOfTheOpenImageIoPlugin) {
    const std::vector<std::string> render{"R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z"};
    struct Case {
        int width, height;
        std::vector<std::string> channels;
    };
    // Heights around ZIP's 16-row blocks, a single pixel, a single channel, the channels in
    // another order than the file's (alphabetical) one.
    const std::vector<Case> cases = {{320, 250, render}, {24, 16, render}, {17, 33, render}, {1, 1, render},
                                     {5, 3, {"Z"}},      {9, 7, {"N.Z", "R", "A", "B"}}};
    // Each at OpenEXR's default zlib level and at the levels asked for by name ("zip:N").
    for (const Case& c : cases)
        for (const int storage : {kSurfelStorageFloat, kSurfelStorageHalf})
            for (const char* compression : {"zip", "zip:1", "zip:9"}) {
                SCOPED_TRACE(::testing::Message() << c.width << "x" << c.height << " storage " << storage << " "
                                                  << compression);
                const Image img = TestImage(c.width, c.height, c.channels);
                std::string m1, m2;
                const std::string a = Encode(*oiio_, img, storage, &m1, compression),
                                  b = Encode(*exr_, img, storage, &m2, compression);
                ASSERT_FALSE(a.empty()) << m1;
                ASSERT_FALSE(b.empty()) << m2;
                EXPECT_EQ(a.size(), b.size());
                EXPECT_TRUE(WithoutDate(a) == WithoutDate(b));
            }
}

TEST_F(ImageCodecs, TheExrPluginRefusesWhatItDoesNotWrite) {
    const Image img = TestImage(4, 4, {"R", "G", "B"});
    std::vector<const char*> names{"R", "G", "B"};
    const SurfelImageView view{4, 4, 3, names.data(), -1, -1, img.pixels.data()};
    std::string bytes, message;
    EXPECT_EQ(exr_->encode("png", &view, kSurfelStorageUint8, nullptr, &Append, &bytes, &Keep, &message),
              kSurfelImageFailed);
    EXPECT_NE(message.find("png"), std::string::npos) << message;
    EXPECT_EQ(exr_->encode("exr", &view, kSurfelStorageFloat, "piz", &Append, &bytes, &Keep, &message),
              kSurfelImageFailed);
    EXPECT_NE(message.find("piz"), std::string::npos) << message;
    for (const char* level : {"zip:0", "zip:10", "zip:", "zipper"}) {
        EXPECT_EQ(exr_->encode("exr", &view, kSurfelStorageFloat, level, &Append, &bytes, &Keep, &message),
                  kSurfelImageFailed)
            << level;
        EXPECT_NE(message.find(level), std::string::npos) << message;
    }
    EXPECT_TRUE(bytes.empty());
}

// Through the host: EncodeImage picks the EXR plugin for EXR, and reading the file back (through
// OpenImageIO) gives every value written.
TEST_F(ImageCodecs, EncodeImageWritesExrThatReadsBack) {
    EXPECT_NE(LoadImageCodec(ImageFormat::kExr).find("OpenEXR"), std::string::npos) << LoadImageCodec(ImageFormat::kExr);
    EXPECT_NE(LoadImageCodec(ImageFormat::kPng).find("OpenImageIO"), std::string::npos);
    const Image img = TestImage(33, 20, {"R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z"});
    std::string message;
    // (EncodeImage asks for ZIP at zlib level 1.)
    EXPECT_TRUE(WithoutDate(EncodeImage(img, ImageFormat::kExr)) ==
                WithoutDate(Encode(*oiio_, img, kSurfelStorageFloat, &message, "zip:1")));
    const std::string path = ::testing::TempDir() + "surfel_codecs_" + std::to_string(::getpid()) + ".exr";
    WriteImage(img, path);
    const Image back = ReadImage(path);
    std::remove(path.c_str());
    ASSERT_EQ(back.width, img.width);
    ASSERT_EQ(back.height, img.height);
    for (const std::string& c : img.channels) {
        const int i = back.ChannelIndex(c), j = img.ChannelIndex(c);
        ASSERT_GE(i, 0) << c;
        for (int y = 0; y < img.height; ++y)
            for (int x = 0; x < img.width; ++x) {
                const float a = back.At(x, y, i), b = img.At(x, y, j);
                if (std::isnan(b)) EXPECT_TRUE(std::isnan(a));
                else EXPECT_EQ(a, b) << c << " " << x << "," << y;
            }
    }
}

}  // namespace
}  // namespace surfel
