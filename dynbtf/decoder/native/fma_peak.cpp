// The FMA throughput of one thread at the build's instruction-set level: what "share of the peak" in
// dynbtf's benchmarks divides by. Independent fused multiply-adds on VW-lane vectors held in registers
// (enough chains to cover the FMA latency of every current core), nothing else.
// Built per level by dynbtf/decoder/native/__init__.py; Python: dynbtf.decoder.native.fma_peak_flops().
#include <cstdint>

#if defined(__AVX512F__)
constexpr int VW = 16;
#elif defined(__AVX__)
constexpr int VW = 8;
#else
constexpr int VW = 4;
#endif
constexpr int CHAINS = 12;  // 12 x 8 lanes: AVX2's 16 registers hold them; 2 FMA ports x 5-6 cycles latency

typedef float vf __attribute__((vector_size(4 * VW)));

extern "C" int dynbtf_fma_lanes(void) { return VW; }
extern "C" int dynbtf_fma_chains(void) { return CHAINS; }

// Runs `iterations` rounds of CHAINS vector FMAs; returns a value that depends on all of them (so none is
// optimized away). FLOP = 2 * VW * CHAINS * iterations.
extern "C" float dynbtf_fma_loop(int64_t iterations) {
    const vf m = vf{} + 0.999999f, a = vf{} + 1e-7f;
    vf c0 = vf{} + 1.00f, c1 = vf{} + 1.01f, c2 = vf{} + 1.02f, c3 = vf{} + 1.03f, c4 = vf{} + 1.04f,
       c5 = vf{} + 1.05f, c6 = vf{} + 1.06f, c7 = vf{} + 1.07f, c8 = vf{} + 1.08f, c9 = vf{} + 1.09f,
       c10 = vf{} + 1.10f, c11 = vf{} + 1.11f;
    for (int64_t i = 0; i < iterations; ++i) {
        c0 = c0 * m + a; c1 = c1 * m + a; c2 = c2 * m + a; c3 = c3 * m + a; c4 = c4 * m + a; c5 = c5 * m + a;
        c6 = c6 * m + a; c7 = c7 * m + a; c8 = c8 * m + a; c9 = c9 * m + a; c10 = c10 * m + a; c11 = c11 * m + a;
    }
    vf s = ((c0 + c1) + (c2 + c3)) + ((c4 + c5) + (c6 + c7)) + ((c8 + c9) + (c10 + c11));
    float r = 0.f;
    for (int j = 0; j < VW; ++j) r += s[j];
    return r;
}
