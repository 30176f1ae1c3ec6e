// Training targets gathered from the float16 image cache (native CPU kernel).
//
// A training step with texel groups reads, for every group g and each of its B images, a block of
// `length` consecutive texels (modulo the image's texels) from the cache of decoded images
// (dynbtf/training/images.py, ImageStore.get_blocks):
//
//   out[b, g * length + j, c] = float(cache[rows[g * B + b], (starts[g] + j) mod texels, c])
//
// cache: float16 (n_images, texels, channels), row-major; out: float32 (B, G * length, channels).
// One pass that converts while it copies (F16C where the build has it, else an exact scalar
// conversion): the NumPy version built index arrays and converted in a second pass, on the core the
// training kernel wants. Built by dynbtf/decoder/native/__init__.py per instruction-set level.

#include <cstdint>
#include <cstring>
#if defined(__F16C__)
#include <immintrin.h>
#endif

namespace {

// IEEE binary16 -> binary32, exact for every value (NaN payloads kept, subnormals normalized)
inline float half_to_float(uint16_t h) {
    const uint32_t sign = static_cast<uint32_t>(h & 0x8000u) << 16;
    const uint32_t exponent = (h >> 10) & 0x1fu, mantissa = h & 0x3ffu;
    uint32_t bits;
    if (exponent == 0) {
        if (mantissa == 0) {
            bits = sign;
        } else {  // mantissa * 2^-24 = 1.f * 2^(k - 24), k the highest set bit
            const int k = 31 - __builtin_clz(mantissa);
            bits = sign | (static_cast<uint32_t>(k + 103) << 23) | (((mantissa << (10 - k)) & 0x3ffu) << 13);
        }
    } else if (exponent == 31) {
        bits = sign | 0x7f800000u | (mantissa << 13);
    } else {
        bits = sign | ((exponent + 112) << 23) | (mantissa << 13);
    }
    float f;
    std::memcpy(&f, &bits, sizeof f);
    return f;
}

// dst[0 .. n) = float(src[0 .. n))
inline void convert(const uint16_t* src, int64_t n, float* dst) {
    int64_t i = 0;
#if defined(__F16C__)
    for (; i + 8 <= n; i += 8) {
        const __m128i h = _mm_loadu_si128(reinterpret_cast<const __m128i*>(src + i));
        _mm256_storeu_ps(dst + i, _mm256_cvtph_ps(h));
    }
#endif
    for (; i < n; ++i) dst[i] = half_to_float(src[i]);
}

}  // namespace

// Returns 0, or 1 for arguments outside the ranges stated above (nothing written then).
extern "C" int dynbtf_gather_blocks_f16(const uint16_t* cache, int64_t n_images, int64_t texels, int32_t channels,
                                        const int64_t* rows, int64_t groups, int64_t images, const int64_t* starts,
                                        int64_t length, float* out) {
    if (texels < 1 || channels < 1 || groups < 0 || images < 0 || length < 1 || length > texels) return 1;
    for (int64_t k = 0; k < groups * images; ++k)
        if (rows[k] < 0 || rows[k] >= n_images) return 1;
    const int64_t C = channels, row_stride = groups * length * C;
    for (int64_t g = 0; g < groups; ++g) {
        const int64_t a = ((starts[g] % texels) + texels) % texels;
        const int64_t first = a + length <= texels ? length : texels - a;  // texels before the wrap
        for (int64_t b = 0; b < images; ++b) {
            const uint16_t* image = cache + rows[g * images + b] * texels * C;
            float* dst = out + b * row_stride + g * length * C;
            convert(image + a * C, first * C, dst);
            if (first < length) convert(image, (length - first) * C, dst + first * C);
        }
    }
    return 0;
}

// dst[0 .. n) = float(src[0 .. n)): the scalar conversion above, for the tests (checked against NumPy)
extern "C" void dynbtf_half_to_float(const uint16_t* src, int64_t n, float* dst) {
    for (int64_t i = 0; i < n; ++i) dst[i] = half_to_float(src[i]);
}
