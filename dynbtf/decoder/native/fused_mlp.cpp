// Fused L1 training step of a LeakyReLU MLP over whole-image batches (native CPU kernel).
//
// The Python side (dynbtf/training/fused_mlp.py) documents the maths; this file computes, for
// the work items handed to one thread, exactly what its torch fallback computes:
//
//   z1[b, t] = P[t] + Q[g(t), b]                    (layer 1, split per texel / per image)
//   a1 = lrelu(z1);  a_k = lrelu(W_k a_{k-1} + c_k) (hidden layers 2 .. L-1, H x H)
//   y  = W_L a_{L-1} + c_L                          (output layer, C x H, no activation)
//   loss = sum |y - target|                         (summed; the caller divides by the count)
//
// and the gradients of that sum with respect to P (rows of the items, overwritten), Q, every
// W_k and c_k (per work item, into the item's slot; see FusedL1Args). d|r|/dr = sign(r), sign(0) = 0.
//
// Samples are processed in tiles of one image x up to TILE texels whose activations stay in the
// L1 cache. Two precisions share one driver:
//   * fp32: GCC vector extensions of the build level's width (VW floats: 16 on AVX-512, 8 on AVX2, 4 on
//     SSE2/NEON), register blocks sized to its vector registers;
//   * bf16: AVX512-BF16 dot products (vdpbf16ps) on bfloat16 activations, weights and
//     gradients, accumulated in fp32 (mixed precision: P, Q, biases, loss, residuals, masks and
//     every gradient accumulator stay fp32). Only built when the compiler targets AVX512-BF16.
//
// Built on first use by dynbtf/decoder/native/__init__.py, once per instruction-set level (explicit flags,
// never -march=native; see dynbtf/cpu.py), called via ctypes from dynbtf/decoder/fused_mlp.py.

#include <cstdint>
#include <cstring>
#include <cmath>
#include <algorithm>
#include <type_traits>
#include <memory>
#include <vector>
#if defined(__AVX512BF16__) && defined(__AVX512BW__)
#include <immintrin.h>
#define DYNBTF_HAVE_BF16 1
#else
#define DYNBTF_HAVE_BF16 0
#endif

extern "C" {

// Mirrored by ctypes in dynbtf/decoder/fused_mlp.py: keep the field order.
//
// Several threads call the kernel with the same arguments; each takes the next work item from the shared
// counter `next_item` until none is left (so a thread the OS delays does less, not the others waiting for
// it), and writes that item's gradients into the item's own slot of `item_grads`. The caller sums the
// slots in item order: the result does not depend on which thread ran which item.
struct FusedL1Args {
    int32_t hidden;            // H (a multiple of 16, at most 128)
    int32_t out_channels;      // C (1 .. 16)
    int32_t n_layers;          // layers after the first: n_layers - 1 hidden (H x H) + the output layer (C x H)
    int32_t groups;            // G
    int32_t images;            // B
    int32_t texels_per_group;  // n
    float slope;               // LeakyReLU negative slope (> 0)
    int32_t n_items;
    const int64_t* items;      // (n_items, 3): group, first texel, end texel (within the group)
    const float* positional_pre;   // (G * n, H)
    const float* image_pre;        // (G, B, H)
    const float* target;           // (B, G * n, C)
    const float* const* weights;   // n_layers pointers, row-major (out, in)
    const float* const* biases;    // n_layers pointers
    float* grad_positional;        // (G * n, H): the items' rows are overwritten
    int64_t item_stride;           // floats per item slot (dynbtf_fused_l1_item_floats)
    float* item_grads;             // (n_items, item_stride): per item dW_0 .. dW_{L-1}, dc_0 .. dc_{L-1}, dQ (B, H)
    double* item_loss;             // (n_items,): sum of |residual| over the item's samples
    int32_t* next_item;            // shared by the calling threads: the next item to take (starts at 0)
};

int dynbtf_fused_l1_fp32(FusedL1Args* args);
int dynbtf_fused_l1_bf16(FusedL1Args* args);
int dynbtf_fused_l1_has_bf16(void);
int dynbtf_fused_l1_args_size(void);  // sizeof(FusedL1Args): the ctypes mirror checks it on load
int dynbtf_fused_l1_supports(int32_t hidden, int32_t out_channels, int32_t n_layers);  // 1 if a path exists
// floats of one item's gradient slot: the layers' weights and biases, then the item's images' dQ (B x H)
int64_t dynbtf_fused_l1_item_floats(int32_t hidden, int32_t out_channels, int32_t n_layers, int32_t images);
// The caller's sums of the item slots once every item is done, each in item order (so the same whatever thread
// ran which item): weight_grads (item_stride - B H floats: every dW_k, then every dc_k) = scale x the sum over all
// items; image_grads (G, B, H) = scale x the sum of dQ over group g's items (the items grouped: n_items / G per
// group, in group order); *loss = the sum of item_loss. Returns 1 where the items are not so grouped.
int dynbtf_fused_l1_reduce(const FusedL1Args* args, float scale, float* weight_grads, float* image_grads,
                           double* loss);

// Inference: out = MLP(a) for rows a of layer 1's activations, a = lrelu(x) of its pre-activation x when
// activate_input is 1, else a = x (the same products as the training forward, fp32, no gradients). Mirrored
// by ctypes in dynbtf/decoder/fused_mlp.py.
struct MlpArgs {
    int32_t hidden;                // H
    int32_t out_channels;          // C
    int32_t n_layers;              // layers after the first, as FusedL1Args
    float slope;
    int32_t activate_input;
    int64_t rows;
    const float* x;                // (rows, H)
    const float* const* weights;   // n_layers pointers, row-major (out, in)
    const float* const* biases;
    float* out;                    // (rows, C)
};
int dynbtf_mlp_forward_fp32(MlpArgs* args);

// y = x W + b for rows x (rows, in) and W (in, out) row-major, out a multiple of 16 (at most MAX_HIDDEN):
// each row's sum in input order, whatever the rows around it (BLAS's sums depend on the blocking, and with
// MKL's AVX2 kernels on the calling thread, so evaluation's layer 1 comes here). Returns 1 for another out.
int dynbtf_affine_rows_fp32(int64_t rows, int32_t in, int32_t out, const float* x, const float* w, const float* b,
                            float* y);

// Layer 1 of a Triple Plane decoder in a training step, with the plane fetches it reads. The fused loss above
// takes layer 1 split in two parts, one per texel and one per image:
//
//   P[r] = W_U f_U[texel[r]]                       (N rows: the step's texels; no bias)
//   P[r] = W_U sum_j w[j, r] f_U[texel[j, r]]       (with texel weights: N points between texel centres, each
//                                                   the weighted sum of J texels, e.g. J = 4 bilinear taps)
//   a[i] = sum_k weight[i, k] f_A[index[i, k]]     (image i's angular features: bilinear taps of the stacked
//                                                   angular planes [f_H; f_D], per plane)
//   Q[i] = W_A a[i] + b_1                          (one row per image)
//
// with [W_U | W_A] layer 1's (H, C_U + C_A) weight. dynbtf_first_layer_forward computes P, a and Q; given the
// gradients dP and dQ the fused loss returns, dynbtf_first_layer_backward computes everything below them:
//
//   dW_U = sum_r dP[r] f_U[texel[r]]^T    dW_A = sum_i dQ[i] a[i]^T    db_1 = sum_i dQ[i]
//   df_U[texel[r]] += W_U^T dP[r]         df_A[index[i, k]] += weight[i, k] W_A^T dQ[i]
//   (with texel weights: df_U[texel[j, r]] += w[j, r] W_U^T dP[r])
//
// with the fp32 register blocks of the fused kernel, on the calling thread, every sum in one fixed order
// (repeated texels and taps add up in row order, as torch's index_add_). Small products next to the fused
// loss's; in torch they were a dozen operators of 50-100 us each. Mirrored by ctypes in
// dynbtf/decoder/fused_mlp.py (triple_plane_l1_loss); keep the field order.
struct FirstLayerArgs {
    int32_t hidden;           // H
    int32_t positional;       // C_U
    int32_t angular;          // C_A: the angular planes' channels times the planes
    int32_t plane_channels;   // channels of one angular plane
    int32_t taps;             // taps per plane and image (4: bilinear)
    int32_t texel_taps;       // J: texels per row (1 without texel weights)
    int64_t rows;             // N: the step's texels
    int64_t images;           // the step's images (G * B)
    int64_t plane_rows;       // rows of `plane`: every texel index is checked against it
    int64_t angular_rows;     // rows of `angular_planes`: every tap index is checked against it
    float positional_scale;   // backward: dP is taken times this factor (the fused loss leaves it unscaled)
    const float* weight;      // (H, C_U + C_A): layer 1's weight, row-major (torch's nn.Linear layout)
    const float* bias;        // (H,)
    const float* plane;       // (plane_rows, C_U): f_U flattened
    const int64_t* texels;    // (J, N): rows of `plane` (null: rows 0 .. N-1, J = 1)
    const float* texel_weight;  // (J, N): each row's weights of its J texels (null: J = 1, weight 1)
    const float* angular_planes;  // (angular_rows, plane_channels): [f_H; f_D] flattened
    const int64_t* tap_index;     // (images, planes, taps): rows of angular_planes
    const float* tap_weight;      // (images, planes, taps)
    float* positional_pre;    // (N, H): P
    float* angular_features;  // (images, C_A): a
    float* image_pre;         // (images, H): Q
};
int dynbtf_first_layer_args_size(void);
int dynbtf_first_layer_supports(int32_t hidden, int32_t positional, int32_t angular);  // 1 if a path exists
// 0, or 1 (sizes without a path), 2 (a texel or tap index outside its plane)
int dynbtf_first_layer_forward(const FirstLayerArgs* args);
// grad_weight (H, C_U + C_A), grad_bias (H,) overwritten; grad_plane, grad_angular_planes added to (zero them)
int dynbtf_first_layer_backward(const FirstLayerArgs* args, const float* grad_positional_pre,
                                const float* grad_image_pre, float* grad_weight, float* grad_bias, float* grad_plane,
                                float* grad_angular_planes);
}

namespace {

constexpr int MAX_HIDDEN = 128;
constexpr int MAX_LAYERS = 8;
constexpr int MAX_OUT = 16;
constexpr int TILE = 64;   // samples per tile (one image x up to TILE texels); a multiple of 8

// This thread's T, made on its first call and kept for the thread's life. Returned as a pointer loaded from
// thread-local storage: bound to a thread_local object itself, GCC recomputes the object's address inside the
// loops (a __tls_get_addr call in a shared library, measured at about a tenth of the bf16 kernel's time); a
// loaded pointer it keeps in a register.
template <class T>
T* thread_scratch() {
    static thread_local std::unique_ptr<T> held;
    if (!held) held.reset(new T);
    return held.get();
}

// The build's vector unit (dynbtf/decoder/native/__init__.py compiles one library per level):
// VW float32 lanes per vector and NREG vector registers, which size the register blocks below.
#if defined(__AVX512F__)
constexpr int VW = 16, NREG = 32;
#elif defined(__AVX2__)
constexpr int VW = 8, NREG = 16;
#elif defined(__aarch64__)
constexpr int VW = 4, NREG = 32;   // NEON
#else
constexpr int VW = 4, NREG = 16;   // SSE2 (x86-64 baseline) or the compiler's generic vectors
#endif
constexpr int OUT_LD = 16;  // leading dimension of the output rows (MAX_OUT floats)

typedef float vf __attribute__((vector_size(4 * VW)));
typedef int32_t vi __attribute__((vector_size(4 * VW)));

inline vf loadv(const float* p) { vf v; std::memcpy(&v, p, sizeof v); return v; }
inline void storev(float* p, vf v) { std::memcpy(p, &v, sizeof v); }
// a broadcast: x - 0 is x for every x, so the compiler drops the subtraction (vf{} + x is not: -0 + 0 = +0)
inline vf splat(float x) { return x - vf{}; }
inline vf lrelu(vf z, float slope) { return z > 0 ? z : z * slope; }
inline float hsum(vf v) {
    float s = 0.f;
    for (int j = 0; j < VW; ++j) s += v[j];
    return s;
}

// Rows of samples per register block of a product with NV vectors per row: the accumulators (R x NV), the R
// rows' broadcasts and one vector of weights must fit the vector registers (AVX2, H = 32: 3; AVX-512: 8).
template <int NV>
constexpr int block_rows() {
    constexpr int fit = (NREG - 1) / (NV + 1);
    return fit >= 8 ? 8 : fit < 1 ? 1 : fit;
}

// body(rows, s) with rows a std::integral_constant: whole blocks of R rows s = 0, R, 2R, ... of S, then the rest
// in blocks of 2 and 1 (the sums of a row do not depend on its block)
template <int R, class Body>
__attribute__((always_inline)) inline void in_blocks(int S, Body&& body) {
    int s = 0;
    for (; s + R <= S; s += R) body(std::integral_constant<int, R>{}, s);
    if (R > 2 && s + 2 <= S) { body(std::integral_constant<int, 2>{}, s); s += 2; }
    for (; s < S; ++s) body(std::integral_constant<int, 1>{}, s);
}

// ------------------------------------------------------------------------------------------ fp32
// Activations are fp32 rows of H floats; layer weights are used as given (row-major (out, in)) and
// transposed (in, out padded to whole vectors) for the forward pass.
struct Fp32 {
    typedef float act_t;
    int H, C;
    // per layer: transposed weights (in, out_padded) for the forward pass and (out, in) as given
    alignas(64) float wt[MAX_LAYERS][MAX_HIDDEN * MAX_HIDDEN];
    const float* w[MAX_LAYERS];

    void prepare(const FusedL1Args* a) { prepare(a->hidden, a->out_channels, a->n_layers, a->weights); }
    void prepare(int hidden, int out_channels, int n_layers, const float* const* weights) {
        H = hidden; C = out_channels;
        for (int k = 0; k < n_layers; ++k) {
            const bool last = k == n_layers - 1;
            const int out = last ? C : H, outp = last ? (C + VW - 1) / VW * VW : H;
            w[k] = weights[k];
            for (int i = 0; i < H; ++i)
                for (int o = 0; o < outp; ++o) wt[k][i * outp + o] = o < out ? weights[k][o * H + i] : 0.f;
        }
    }
    // row of fp32 values -> stored activation row (identity)
    static void store_row(act_t* dst, const float* src, int H) { std::memcpy(dst, src, H * sizeof(float)); }
    // S rows of `width` fp32 gradients -> the rows the backward products read (fp32: the same rows)
    static const act_t* lowp(const float* src, int S, int width, act_t* buf) {
        (void)S; (void)width; (void)buf;
        return src;
    }

    // acc[r][v] += sum over i < n of rows[r * ld + i] * w[i * VW NV + VW v .. + VW] (w row-major, VW NV wide):
    // per i, the R broadcasts stay in registers while the NV weight vectors stream through one register
    template <int NV, int R>
    __attribute__((always_inline)) static inline void accumulate_rows(const float* rows, int ld, const float* w, int n,
                                                                      vf (&acc)[R][NV]) {
        for (int i = 0; i < n; ++i) {
            vf x[R];
            for (int r = 0; r < R; ++r) x[r] = splat(rows[r * ld + i]);
            for (int v = 0; v < NV; ++v) {
                const vf wv = loadv(w + (i * NV + v) * VW);
                for (int r = 0; r < R; ++r) acc[r][v] += x[r] * wv;
            }
        }
    }

    // Y[s] = lrelu(W X[s] + c) for S samples (S a multiple of 8); gain[s] = lrelu'(pre-activation) (1 or slope),
    // unless gain is null (inference)
    template <int NV>
    void hidden_forward(int k, const act_t* X, const float* bias, float slope, int S, act_t* Y, float* gain) const {
        const int H = VW * NV;
        const float* wk = wt[k];
        in_blocks<block_rows<NV>()>(S, [&](auto rows, int s) {
            constexpr int R = decltype(rows)::value;
            vf acc[R][NV];
            for (int r = 0; r < R; ++r)
                for (int v = 0; v < NV; ++v) acc[r][v] = loadv(bias + VW * v);
            accumulate_rows<NV, R>(X + s * H, H, wk, H, acc);
            for (int r = 0; r < R; ++r)
                for (int v = 0; v < NV; ++v) {
                    storev(Y + (s + r) * H + VW * v, lrelu(acc[r][v], slope));
                    if (gain) storev(gain + (s + r) * H + VW * v, acc[r][v] > 0 ? splat(1.f) : splat(slope));
                }
        });
    }
    // out[s, 0:VW NO] = W_L X[s] + c (lanes >= C are zero; rows OUT_LD apart)
    template <int NV, int NO>
    void output_forward(int k, const act_t* X, const float* bias, int S, float* out) const {
        const int H = VW * NV;
        const float* wk = wt[k];
        in_blocks<block_rows<NO>()>(S, [&](auto rows, int s) {
            constexpr int R = decltype(rows)::value;
            vf acc[R][NO];
            for (int r = 0; r < R; ++r)
                for (int v = 0; v < NO; ++v) acc[r][v] = loadv(bias + VW * v);
            accumulate_rows<NO, R>(X + s * H, H, wk, H, acc);
            for (int r = 0; r < R; ++r)
                for (int v = 0; v < NO; ++v) storev(out + (s + r) * OUT_LD + VW * v, acc[r][v]);
        });
    }
    // dX[s] = (W^T dZ[s]) for S samples; dZ rows have `out` fp32 entries, ldz apart
    template <int NV>
    void backward_input(int k, const float* dZ, int out, int ldz, int S, float* dX) const {
        const int H = VW * NV;
        const float* wk = w[k];
        in_blocks<block_rows<NV>()>(S, [&](auto rows, int s) {
            constexpr int R = decltype(rows)::value;
            vf acc[R][NV];
            for (int r = 0; r < R; ++r)
                for (int v = 0; v < NV; ++v) acc[r][v] = vf{};
            accumulate_rows<NV, R>(dZ + s * ldz, ldz, wk, out, acc);
            for (int r = 0; r < R; ++r)
                for (int v = 0; v < NV; ++v) storev(dX + (s + r) * H + VW * v, acc[r][v]);
        });
    }
    // dW[o, :] += sum_s dZ[s, o] X[s, :] for o < out: blocks of output rows (no zero rows computed)
    template <int NV>
    void backward_weights(const float* dZ, int out, int ldz, const act_t* X, int S, float* dW) const {
        in_blocks<block_rows<NV>()>(out, [&](auto rows, int o0) {
            weight_rows<NV, decltype(rows)::value>(dZ, o0, ldz, X, S, dW);
        });
    }
    // dW[o0 + r, :] += sum_s dZ[s, o0 + r] X[s, :] for r < RB: per sample, the RB broadcasts stay in registers
    // while the NV vectors of X[s] stream through one register
    template <int NV, int RB>
    static void weight_rows(const float* dZ, int o0, int ldz, const act_t* X, int S, float* dW) {
        const int H = VW * NV;
        vf acc[RB][NV];
        for (int r = 0; r < RB; ++r)
            for (int v = 0; v < NV; ++v) acc[r][v] = loadv(dW + (o0 + r) * H + VW * v);
        for (int s = 0; s < S; ++s) {
            vf g[RB];
            for (int r = 0; r < RB; ++r) g[r] = splat(dZ[s * ldz + o0 + r]);
            for (int v = 0; v < NV; ++v) {
                const vf x = loadv(X + s * H + VW * v);
                for (int r = 0; r < RB; ++r) acc[r][v] += g[r] * x;
            }
        }
        for (int r = 0; r < RB; ++r)
            for (int v = 0; v < NV; ++v) storev(dW + (o0 + r) * H + VW * v, acc[r][v]);
    }
};

#if DYNBTF_HAVE_BF16
// ------------------------------------------------------------------------------------------ bf16
// Activation rows are H bfloat16 values (round to nearest even). For vdpbf16ps the weights are
// laid out as pairs: forward  wf[k][pair p][v] = 16 lanes j of (W[16v+j, 2p], W[16v+j, 2p+1]),
//                    backward wb[k][pair m][v] = 16 lanes j of (W[2m, 16v+j], W[2m+1, 16v+j]).
struct Bf16 {
    typedef uint16_t act_t;
    int H, C;
    alignas(64) uint16_t wf[MAX_LAYERS][MAX_HIDDEN * MAX_HIDDEN];
    alignas(64) uint16_t wb[MAX_LAYERS][MAX_HIDDEN * MAX_HIDDEN];

    static uint16_t to_bf16(float x) {  // round to nearest even (inputs are finite)
        uint32_t u;
        std::memcpy(&u, &x, 4);
        u += 0x7FFF + ((u >> 16) & 1);
        return static_cast<uint16_t>(u >> 16);
    }
    void prepare(const FusedL1Args* a) {
        H = a->hidden; C = a->out_channels;
        int NV = H / 16;
        for (int k = 0; k < a->n_layers; ++k) {
            const float* W = a->weights[k];
            bool last = k == a->n_layers - 1;
            int out = last ? C : H, nvo = last ? 1 : NV;
            for (int p = 0; p < H / 2; ++p)          // forward: pairs over inputs
                for (int v = 0; v < nvo; ++v)
                    for (int j = 0; j < 16; ++j)
                        for (int e = 0; e < 2; ++e) {
                            int o = 16 * v + j;
                            wf[k][((p * nvo + v) * 16 + j) * 2 + e] = o < out ? to_bf16(W[o * H + 2 * p + e]) : 0;
                        }
            int pairs_out = (out + 1) / 2;             // backward: pairs over outputs
            for (int m = 0; m < pairs_out; ++m)
                for (int v = 0; v < NV; ++v)
                    for (int j = 0; j < 16; ++j)
                        for (int e = 0; e < 2; ++e) {
                            int o = 2 * m + e;
                            wb[k][((m * NV + v) * 16 + j) * 2 + e] = o < out ? to_bf16(W[o * H + 16 * v + j]) : 0;
                        }
        }
    }
    static void store_row(act_t* dst, const float* src, int H) {
        for (int v = 0; v < H / 16; ++v)
            _mm256_storeu_si256(reinterpret_cast<__m256i*>(dst + 16 * v),
                                (__m256i)_mm512_cvtneps_pbh(_mm512_loadu_ps(src + 16 * v)));
    }
    static const act_t* lowp(const float* src, int S, int width, act_t* buf) {
        for (int i = 0; i < S * width; i += 16)
            _mm256_storeu_si256(reinterpret_cast<__m256i*>(buf + i), (__m256i)_mm512_cvtneps_pbh(_mm512_loadu_ps(src + i)));
        return buf;
    }
    static __m512i bcast_pair(const uint16_t* row, int p) {
        int32_t x;
        std::memcpy(&x, row + 2 * p, 4);
        return _mm512_set1_epi32(x);
    }
    // acc[r][v] += sum over pairs p < npairs of (rows[r * ld + 2p], rows[r * ld + 2p + 1]) . weight
    // pair p of lane block v (w laid out as wf / wb above), one vdpbf16ps per (p, r, v)
    template <int NV, int R>
    __attribute__((always_inline)) static inline void accumulate_pairs(const uint16_t* rows, int ld, const uint16_t* w, int npairs, __m512 (&acc)[R][NV]) {
        for (int p = 0; p < npairs; ++p) {
            __m512i wv[NV];
            for (int v = 0; v < NV; ++v)
                wv[v] = _mm512_load_si512(reinterpret_cast<const void*>(w + (p * NV + v) * 32));
            for (int r = 0; r < R; ++r) {
                __m512i x = bcast_pair(rows + r * ld, p);
                for (int v = 0; v < NV; ++v)
                    acc[r][v] = _mm512_dpbf16_ps(acc[r][v], (__m512bh)x, (__m512bh)wv[v]);
            }
        }
    }

    template <int NV>
    void hidden_forward(int k, const act_t* X, const float* bias, float slope, int S, act_t* Y, float* gain) const {
        const int H = 16 * NV;
        constexpr int R = NV <= 2 ? 8 : 4;
        const __m512 sl = _mm512_set1_ps(slope), one = _mm512_set1_ps(1.f);
        for (int s = 0; s < S; s += R) {
            __m512 acc[R][NV];
            for (int r = 0; r < R; ++r)
                for (int v = 0; v < NV; ++v) acc[r][v] = _mm512_loadu_ps(bias + 16 * v);
            accumulate_pairs<NV, R>(X + s * H, H, wf[k], H / 2, acc);
            for (int r = 0; r < R; ++r)
                for (int v = 0; v < NV; ++v) {
                    __mmask16 pos = _mm512_cmp_ps_mask(acc[r][v], _mm512_setzero_ps(), _CMP_GT_OQ);
                    __m512 y = _mm512_mask_blend_ps(pos, _mm512_mul_ps(acc[r][v], sl), acc[r][v]);
                    _mm256_storeu_si256(reinterpret_cast<__m256i*>(Y + (s + r) * H + 16 * v),
                                        (__m256i)_mm512_cvtneps_pbh(y));
                    _mm512_storeu_ps(gain + (s + r) * H + 16 * v, _mm512_mask_blend_ps(pos, sl, one));
                }
        }
    }
    template <int NV, int NO>
    void output_forward(int k, const act_t* X, const float* bias16, int S, float* out) const {
        static_assert(NO == 1, "bf16 builds have 16 lanes: one vector holds every output");
        const int H = 16 * NV;
        for (int s = 0; s < S; s += 8) {
            __m512 acc[8][1];
            for (int r = 0; r < 8; ++r) acc[r][0] = _mm512_loadu_ps(bias16);
            accumulate_pairs<1, 8>(X + s * H, H, wf[k], H / 2, acc);
            for (int r = 0; r < 8; ++r) _mm512_storeu_ps(out + (s + r) * 16, acc[r][0]);
        }
    }
    // dX[s] = W^T dZ[s] from bf16 gradient rows (leading dimension ldz, zero beyond `out`)
    template <int NV>
    void backward_input(int k, const act_t* dZ, int out, int ldz, int S, float* dX) const {
        const int H = 16 * NV;
        constexpr int R = NV <= 2 ? 8 : 4;
        const int pairs = (out + 1) / 2;
        for (int s = 0; s < S; s += R) {
            __m512 acc[R][NV];
            for (int r = 0; r < R; ++r)
                for (int v = 0; v < NV; ++v) acc[r][v] = _mm512_setzero_ps();
            accumulate_pairs<NV, R>(dZ + s * ldz, ldz, wb[k], pairs, acc);
            for (int r = 0; r < R; ++r)
                for (int v = 0; v < NV; ++v) _mm512_storeu_ps(dX + (s + r) * H + 16 * v, acc[r][v]);
        }
    }
    // dW[o, :] += sum_s dZ[s, o] X[s, :], summing sample pairs (s, s + 1) per vdpbf16ps
    template <int NV>
    void backward_weights(const act_t* dZ, int out, int ldz, const act_t* X, int S, float* dW) const {
        const int H = 16 * NV;
        constexpr int R = NV <= 2 ? 8 : 4;
        // interleave sample pairs: xi[q][v] lane j = (X[2q, 16v+j], X[2q+1, 16v+j]); zi[q][o] = (dZ[2q, o], dZ[2q+1, o])
        alignas(64) uint16_t xi[TILE / 2][MAX_HIDDEN * 2];
        alignas(64) uint32_t zi[TILE / 2][MAX_HIDDEN + 16];
        alignas(64) static const uint16_t interleave[32] = {0, 32, 1, 33, 2, 34, 3, 35, 4, 36, 5, 37, 6, 38, 7, 39,
                                                            8, 40, 9, 41, 10, 42, 11, 43, 12, 44, 13, 45, 14, 46, 15, 47};
        const __m512i idx = _mm512_load_si512(reinterpret_cast<const void*>(interleave));
        for (int q = 0; q < S / 2; ++q) {
            for (int v = 0; v < NV; ++v) {
                __m512i a = _mm512_maskz_loadu_epi16(0xFFFF, X + (2 * q) * H + 16 * v);  // 16 channels, upper half 0
                __m512i b = _mm512_maskz_loadu_epi16(0xFFFF, X + (2 * q + 1) * H + 16 * v);
                __m512i ab = _mm512_permutex2var_epi16(a, idx, b);
                _mm512_store_si512(reinterpret_cast<void*>(xi[q] + 32 * v), ab);
            }
            for (int v = 0; v < (out + 15) / 16; ++v) {
                __m512i a = _mm512_maskz_loadu_epi16(0xFFFF, dZ + (2 * q) * ldz + 16 * v);
                __m512i b = _mm512_maskz_loadu_epi16(0xFFFF, dZ + (2 * q + 1) * ldz + 16 * v);
                _mm512_store_si512(reinterpret_cast<void*>(zi[q] + 16 * v), _mm512_permutex2var_epi16(a, idx, b));
            }
        }
        for (int o0 = 0; o0 < out; o0 += R) {
            int rn = std::min(R, out - o0);
            __m512 acc[R][NV];
            for (int r = 0; r < R; ++r)
                for (int v = 0; v < NV; ++v)
                    acc[r][v] = r < rn ? _mm512_loadu_ps(dW + (o0 + r) * H + 16 * v) : _mm512_setzero_ps();
            for (int q = 0; q < S / 2; ++q) {
                __m512i xv[NV];
                for (int v = 0; v < NV; ++v) xv[v] = _mm512_load_si512(reinterpret_cast<const void*>(xi[q] + 32 * v));
                for (int r = 0; r < R; ++r) {
                    __m512i g = _mm512_set1_epi32(static_cast<int32_t>(r < rn ? zi[q][o0 + r] : 0u));
                    for (int v = 0; v < NV; ++v)
                        acc[r][v] = _mm512_dpbf16_ps(acc[r][v], (__m512bh)g, (__m512bh)xv[v]);
                }
            }
            for (int r = 0; r < rn; ++r)
                for (int v = 0; v < NV; ++v) _mm512_storeu_ps(dW + (o0 + r) * H + 16 * v, acc[r][v]);
        }
    }
};
#endif

// ---------------------------------------------------------------------------------------- driver
// NV vectors per hidden row, NO vectors per output row (ceil(C / VW)).
template <class Prec, int NV, int NO>
int run(FusedL1Args* a) {
    const int H = VW * NV, C = a->out_channels, L = a->n_layers, B = a->images, n = a->texels_per_group;
    const float slope = a->slope;
    typedef typename Prec::act_t act_t;
    // per thread, reused between calls: the weight layouts, and per tile the activations act[k] (the input of
    // layer k + 2; act[0] = a1) as the products read them, gain[k] = lrelu'(pre-activation of act[k]) in fp32,
    // gradients in fp32 and as the products read them
    struct Scratch {
        Prec prec;
        alignas(64) act_t act[MAX_LAYERS][TILE * MAX_HIDDEN];
        alignas(64) float gain[MAX_LAYERS][TILE * MAX_HIDDEN];
        alignas(64) float a1[TILE * MAX_HIDDEN];
        alignas(64) float dz[2][TILE * MAX_HIDDEN];
        alignas(64) act_t dz_low[TILE * MAX_HIDDEN];
        alignas(64) float out[TILE * OUT_LD];
        alignas(64) float dgrad_p[TILE * MAX_HIDDEN];
    };
    Scratch& own = *thread_scratch<Scratch>();  // one thread-local lookup per call (see thread_scratch)
    auto& prec = own.prec;
    auto& act = own.act;
    auto& gain = own.gain;
    auto& a1 = own.a1;
    auto& dz = own.dz;
    auto& dz_low = own.dz_low;
    auto& out = own.out;
    auto& dgrad_p = own.dgrad_p;
    prec.prepare(a);
    alignas(64) float bias_out[OUT_LD] = {0};
    for (int c = 0; c < C; ++c) bias_out[c] = a->biases[L - 1][c];
    const vf one = splat(1.f), zero = vf{}, sl = splat(slope);
    vi lane_ok[NO];  // output lane VW v + j is a channel (< C)
    for (int v = 0; v < NO; ++v)
        for (int j = 0; j < VW; ++j) lane_ok[v][j] = VW * v + j < C ? -1 : 0;
    for (;;) {
        const int it = __atomic_fetch_add(a->next_item, 1, __ATOMIC_RELAXED);
        if (it >= a->n_items) break;
        const int64_t g = a->items[3 * it], t_begin = a->items[3 * it + 1], t_end = a->items[3 * it + 2];
        // this item's gradient slot: dW_k, dc_k, then dQ of its images
        float* slot = a->item_grads + static_cast<int64_t>(it) * a->item_stride;
        std::fill(slot, slot + a->item_stride, 0.f);
        float* grad_weights[MAX_LAYERS];
        float* grad_biases[MAX_LAYERS];
        float* cursor = slot;
        for (int k = 0; k < L; ++k) {
            grad_weights[k] = cursor;
            cursor += (k == L - 1 ? C : H) * H;
        }
        for (int k = 0; k < L; ++k) {
            grad_biases[k] = cursor;
            cursor += k == L - 1 ? C : H;
        }
        float* grad_image = cursor;  // (B, H)
        double loss = 0.0;   // per-tile float partial sums, added in double
        for (int64_t t0 = t_begin; t0 < t_end; t0 += TILE) {
            const int T = static_cast<int>(std::min<int64_t>(TILE, t_end - t0));
            const int S = (T + 7) & ~7;             // padded samples carry zero gradients
            const int64_t row0 = g * n + t0;
            const float* P = a->positional_pre + row0 * H;
            std::fill(dgrad_p, dgrad_p + T * H, 0.f);
            for (int b = 0; b < B; ++b) {
                const float* Q = a->image_pre + (g * B + b) * H;
                float* dQ = grad_image + b * H;
                // layer 1: z1 = P[t] + Q[b]; a1 = lrelu(z1)
                // fp32 products read a1 itself; bf16 ones a rounded copy
                constexpr bool same_rows = std::is_same<act_t, float>::value;
                float* a1_rows = same_rows ? reinterpret_cast<float*>(act[0]) : a1;
                for (int s = 0; s < S; ++s)
                    for (int v = 0; v < NV; ++v) {
                        vf z = s < T ? loadv(P + s * H + VW * v) + loadv(Q + VW * v) : vf{};
                        storev(a1_rows + s * H + VW * v, lrelu(z, slope));
                        storev(gain[0] + s * H + VW * v, z > 0 ? one : sl);
                    }
                if (!same_rows)
                    for (int s = 0; s < S; ++s) Prec::store_row(act[0] + s * H, a1 + s * H, H);
                // hidden layers 2 .. L-1, output layer L
                for (int k = 0; k < L - 1; ++k)
                    prec.template hidden_forward<NV>(k, act[k], a->biases[k], slope, S, act[k + 1], gain[k + 1]);
                prec.template output_forward<NV, NO>(L - 1, act[L - 1], bias_out, S, out);
                // L1 loss and its gradient sign(r), rows of OUT_LD (lanes >= C and padded samples: 0)
                float* dy = dz[1];
                const float* tgt = a->target + (static_cast<int64_t>(b) * a->groups * n + row0) * C;
                vf loss_acc = vf{};
                for (int s = 0; s < S; ++s)
                    for (int v = 0; v < NO; ++v) {
                        // target lanes VW v .. of sample s: read whole where the tile's targets hold VW floats
                        // from there (the lanes >= C, the next samples' values, are masked), else copied
                        vf t;
                        if (s < T && (s * C + VW * (v + 1)) <= T * C) {
                            t = lane_ok[v] ? loadv(tgt + s * C + VW * v) : zero;
                        } else {
                            alignas(64) float part[VW] = {0};
                            if (s < T) std::memcpy(part, tgt + s * C + VW * v, sizeof(float) * std::max(0, std::min(VW, C - VW * v)));
                            t = loadv(part);
                        }
                        vf r = s < T ? loadv(out + s * OUT_LD + VW * v) - t : vf{};
                        loss_acc += r > 0 ? r : -r;
                        storev(dy + s * OUT_LD + VW * v, (r > 0 ? one : zero) - (r < 0 ? one : zero));
                    }
                loss += hsum(loss_acc);
                // output layer backward
                float* gb = grad_biases[L - 1];
                for (int v = 0; v < NO; ++v) {
                    vf gb_acc = vf{};
                    for (int s = 0; s < T; ++s) gb_acc += loadv(dy + s * OUT_LD + VW * v);
                    for (int j = 0; j < VW && VW * v + j < C; ++j) gb[VW * v + j] += gb_acc[j];
                }
                const act_t* dy_low = Prec::lowp(dy, S, OUT_LD, dz_low);
                prec.template backward_weights<NV>(dy_low, C, OUT_LD, act[L - 1], S, grad_weights[L - 1]);
                prec.template backward_input<NV>(L - 1, dy_low, C, OUT_LD, S, dz[0]);
                int cur = 0;  // dz[cur]: dL/d act[k + 1] (fp32)
                for (int k = L - 2; k >= 0; --k) {
                    // through the LeakyReLU that produced act[k + 1], then hidden layer k (weights[k])
                    float* d = dz[cur];
                    const float* gk = gain[k + 1];
                    vf gbk[NV];
                    for (int v = 0; v < NV; ++v) gbk[v] = loadv(grad_biases[k] + VW * v);
                    for (int s = 0; s < S; ++s)
                        for (int v = 0; v < NV; ++v) {
                            vf x = loadv(d + s * H + VW * v) * loadv(gk + s * H + VW * v);
                            storev(d + s * H + VW * v, x);
                            gbk[v] += x;   // padded samples are zero
                        }
                    for (int v = 0; v < NV; ++v) storev(grad_biases[k] + VW * v, gbk[v]);
                    const act_t* d_low = Prec::lowp(d, S, H, dz_low);
                    prec.template backward_weights<NV>(d_low, H, H, act[k], S, grad_weights[k]);
                    prec.template backward_input<NV>(k, d_low, H, H, S, dz[1 - cur]);
                    cur = 1 - cur;
                }
                // through layer 1's LeakyReLU: dL/dz1 -> P (per texel) and Q (per image)
                const float* d = dz[cur];
                vf q_acc[NV];
                for (int v = 0; v < NV; ++v) q_acc[v] = loadv(dQ + VW * v);
                for (int s = 0; s < T; ++s)
                    for (int v = 0; v < NV; ++v) {
                        vf x = loadv(d + s * H + VW * v) * loadv(gain[0] + s * H + VW * v);
                        q_acc[v] += x;
                        storev(dgrad_p + s * H + VW * v, loadv(dgrad_p + s * H + VW * v) + x);
                    }
                for (int v = 0; v < NV; ++v) storev(dQ + VW * v, q_acc[v]);
            }
            std::memcpy(a->grad_positional + row0 * H, dgrad_p, sizeof(float) * T * H);
        }
        a->item_loss[it] = loss;
    }
    return 0;
}

template <int NV, int NO>
int run_forward(MlpArgs* a) {
    const int H = VW * NV, C = a->out_channels, L = a->n_layers;
    struct Scratch {
        Fp32 prec;
        alignas(64) float act[MAX_LAYERS][TILE * MAX_HIDDEN];
        alignas(64) float out[TILE * OUT_LD];
    };
    Scratch& own = *thread_scratch<Scratch>();  // one thread-local lookup per call (see thread_scratch)
    auto& prec = own.prec;
    auto& act = own.act;
    auto& out = own.out;
    prec.prepare(H, C, L, a->weights);
    alignas(64) float bias_out[OUT_LD] = {0};
    for (int c = 0; c < C; ++c) bias_out[c] = a->biases[L - 1][c];
    for (int64_t r0 = 0; r0 < a->rows; r0 += TILE) {
        const int T = static_cast<int>(std::min<int64_t>(TILE, a->rows - r0));
        const int S = (T + 7) & ~7;
        const float* x = a->x + r0 * H;
        for (int s = 0; s < S; ++s)
            for (int v = 0; v < NV; ++v) {
                const vf z = s < T ? loadv(x + s * H + VW * v) : vf{};
                storev(act[0] + s * H + VW * v, a->activate_input ? lrelu(z, a->slope) : z);
            }
        for (int k = 0; k < L - 1; ++k)
            prec.template hidden_forward<NV>(k, act[k], a->biases[k], a->slope, S, act[k + 1], nullptr);
        prec.template output_forward<NV, NO>(L - 1, act[L - 1], bias_out, S, out);
        float* y = a->out + r0 * C;
        for (int s = 0; s < T; ++s)
            for (int c = 0; c < C; ++c) y[s * C + c] = out[s * OUT_LD + c];
    }
    return 0;
}

// The one rule for which shapes the kernel runs (Python asks dynbtf_fused_l1_supports).
bool supported(int hidden, int out_channels, int n_layers) {
    const int blocks = hidden / 16;
    return hidden % 16 == 0 && (blocks == 1 || blocks == 2 || blocks == 3 || blocks == 4 || blocks == 8) &&
           hidden <= MAX_HIDDEN && out_channels >= 1 && out_channels <= MAX_OUT && n_layers >= 1 &&
           n_layers <= MAX_LAYERS - 1;
}

template <class Prec, int NV>
int dispatch_out(FusedL1Args* a) {
    switch ((a->out_channels + VW - 1) / VW) {
        case 1: return run<Prec, NV, 1>(a);
        case 2: return run<Prec, NV, (VW < 16 ? 2 : 1)>(a);
        case 3: return run<Prec, NV, (VW < 8 ? 3 : 1)>(a);
        case 4: return run<Prec, NV, (VW < 8 ? 4 : 1)>(a);
        default: return 1;
    }
}

template <class Prec>
int dispatch(FusedL1Args* a) {
    if (!supported(a->hidden, a->out_channels, a->n_layers) || !(a->slope > 0)) return 1;
    switch (a->hidden / VW) {
        case 16 / VW: return dispatch_out<Prec, 16 / VW>(a);
        case 32 / VW: return dispatch_out<Prec, 32 / VW>(a);
        case 48 / VW: return dispatch_out<Prec, 48 / VW>(a);
        case 64 / VW: return dispatch_out<Prec, 64 / VW>(a);
        case 128 / VW: return dispatch_out<Prec, 128 / VW>(a);
        default: return 1;
    }
}

}  // namespace

extern "C" int dynbtf_fused_l1_fp32(FusedL1Args* args) { return dispatch<Fp32>(args); }

extern "C" int dynbtf_fused_l1_bf16(FusedL1Args* args) {
#if DYNBTF_HAVE_BF16
    return dispatch<Bf16>(args);
#else
    (void)args;
    return 2;
#endif
}

template <int NV>
int forward_out(MlpArgs* a) {
    switch ((a->out_channels + VW - 1) / VW) {
        case 1: return run_forward<NV, 1>(a);
        case 2: return run_forward<NV, (VW < 16 ? 2 : 1)>(a);
        case 3: return run_forward<NV, (VW < 8 ? 3 : 1)>(a);
        case 4: return run_forward<NV, (VW < 8 ? 4 : 1)>(a);
        default: return 1;
    }
}

extern "C" int dynbtf_mlp_forward_fp32(MlpArgs* a) {
    if (!supported(a->hidden, a->out_channels, a->n_layers) || !(a->slope >= 0)) return 1;
    switch (a->hidden / VW) {
        case 16 / VW: return forward_out<16 / VW>(a);
        case 32 / VW: return forward_out<32 / VW>(a);
        case 48 / VW: return forward_out<48 / VW>(a);
        case 64 / VW: return forward_out<64 / VW>(a);
        case 128 / VW: return forward_out<128 / VW>(a);
        default: return 1;
    }
}

template <int NV>
void affine_rows(int64_t rows, int in, const float* x, const float* w, const float* b, float* y) {
    constexpr int R = block_rows<NV>();
    const int out = VW * NV;
    int64_t r0 = 0;
    for (; r0 + R <= rows; r0 += R) {
        vf acc[R][NV];
        for (int r = 0; r < R; ++r)
            for (int v = 0; v < NV; ++v) acc[r][v] = loadv(b + VW * v);
        Fp32::accumulate_rows<NV, R>(x + r0 * in, in, w, in, acc);
        for (int r = 0; r < R; ++r)
            for (int v = 0; v < NV; ++v) storev(y + (r0 + r) * out + VW * v, acc[r][v]);
    }
    for (; r0 < rows; ++r0) {  // the last rows one at a time: the same sums
        vf acc[1][NV];
        for (int v = 0; v < NV; ++v) acc[0][v] = loadv(b + VW * v);
        Fp32::accumulate_rows<NV, 1>(x + r0 * in, in, w, in, acc);
        for (int v = 0; v < NV; ++v) storev(y + r0 * out + VW * v, acc[0][v]);
    }
}

extern "C" int dynbtf_affine_rows_fp32(int64_t rows, int32_t in, int32_t out, const float* x, const float* w,
                                       const float* b, float* y) {
    if (in < 1 || out % VW || out > MAX_HIDDEN) return 1;
    switch (out / VW) {
        case 16 / VW: affine_rows<16 / VW>(rows, in, x, w, b, y); return 0;
        case 32 / VW: affine_rows<32 / VW>(rows, in, x, w, b, y); return 0;
        case 48 / VW: affine_rows<48 / VW>(rows, in, x, w, b, y); return 0;
        case 64 / VW: affine_rows<64 / VW>(rows, in, x, w, b, y); return 0;
        case 128 / VW: affine_rows<128 / VW>(rows, in, x, w, b, y); return 0;
        default: return 1;
    }
}

extern "C" int dynbtf_fused_l1_has_bf16(void) { return DYNBTF_HAVE_BF16; }

extern "C" int dynbtf_fused_l1_args_size(void) { return static_cast<int>(sizeof(FusedL1Args)); }

extern "C" int dynbtf_fused_l1_supports(int32_t hidden, int32_t out_channels, int32_t n_layers) {
    return supported(hidden, out_channels, n_layers) ? 1 : 0;
}

extern "C" int64_t dynbtf_fused_l1_item_floats(int32_t hidden, int32_t out_channels, int32_t n_layers,
                                               int32_t images) {
    const int64_t H = hidden, C = out_channels, L = n_layers;
    return (L - 1) * (H * H + H) + C * H + C + static_cast<int64_t>(images) * H;
}

// ------------------------------------------------------------------------------------------ layer 1
namespace {

bool first_layer_supported(int hidden, int positional, int angular) {
    auto whole = [](int n) { return n == 16 || n == 32; };  // whole vectors at every level
    return (hidden == 16 || hidden == 32 || hidden == 64) && whole(positional) && whole(angular);
}

// 0 when the sizes have a path and every texel and tap index reads inside its plane; else 1 (sizes), 2 (index)
int first_layer_check(const FirstLayerArgs* a) {
    if (!first_layer_supported(a->hidden, a->positional, a->angular) || a->plane_channels < 1 || a->taps < 1 ||
        a->angular % a->plane_channels || a->rows < 0 || a->images < 0 || a->rows > (int64_t(1) << 24) ||
        a->images > (int64_t(1) << 24) || a->texel_taps < 1 || a->texel_taps > 16 ||
        ((a->texel_taps > 1 || a->texel_weight) && !(a->texels && a->texel_weight)))
        return 1;
    if (a->texels) {
        for (int64_t r = 0; r < a->texel_taps * a->rows; ++r)
            if (a->texels[r] < 0 || a->texels[r] >= a->plane_rows) return 2;
    } else if (a->rows > a->plane_rows) {
        return 2;
    }
    const int64_t n_taps = a->images * (a->angular / a->plane_channels) * a->taps;
    for (int64_t j = 0; j < n_taps; ++j)
        if (a->tap_index[j] < 0 || a->tap_index[j] >= a->angular_rows) return 2;
    return 0;
}

// out (rows, VW NV) = x (rows, n) wt (n, VW NV) + init (null: 0), in blocks of rows (each row's sum in input order)
template <int NV>
void rows_times(int64_t rows, int n, const float* x, const float* wt, const float* init, float* out) {
    constexpr int R = block_rows<NV>();
    const int H = VW * NV;
    in_blocks<R>(static_cast<int>(rows), [&](auto block, int s) {
        constexpr int RB = decltype(block)::value;
        vf acc[RB][NV];
        for (int r = 0; r < RB; ++r)
            for (int v = 0; v < NV; ++v) acc[r][v] = init ? loadv(init + VW * v) : vf{};
        Fp32::accumulate_rows<NV, RB>(x + static_cast<int64_t>(s) * n, n, wt, n, acc);
        for (int r = 0; r < RB; ++r)
            for (int v = 0; v < NV; ++v) storev(out + (static_cast<int64_t>(s) + r) * H + VW * v, acc[r][v]);
    });
}

// the gradients of y = x W^T (+ b) below dy (rows, H) for x (rows, VW NX): grad_w (H, VW NX) = dy^T x (overwritten)
// and grad_x (rows, VW NX) = dy W, W (H, VW NX) row-major and contiguous
template <int NX>
void rows_times_backward(int64_t rows, int H, const float* x, const float* dy, const float* w, float* grad_w,
                         float* grad_x) {
    const int n = VW * NX;
    std::fill(grad_w, grad_w + static_cast<int64_t>(H) * n, 0.f);
    in_blocks<block_rows<NX>()>(H, [&](auto block, int o0) {
        Fp32::weight_rows<NX, decltype(block)::value>(dy, o0, H, x, static_cast<int>(rows), grad_w);
    });
    in_blocks<block_rows<NX>()>(static_cast<int>(rows), [&](auto block, int s) {
        constexpr int RB = decltype(block)::value;
        vf acc[RB][NX];
        for (int r = 0; r < RB; ++r)
            for (int v = 0; v < NX; ++v) acc[r][v] = vf{};
        Fp32::accumulate_rows<NX, RB>(dy + static_cast<int64_t>(s) * H, H, w, H, acc);
        for (int r = 0; r < RB; ++r)
            for (int v = 0; v < NX; ++v) storev(grad_x + (static_cast<int64_t>(s) + r) * n + VW * v, acc[r][v]);
    });
}

// the step's positional rows f_U[texel[r]] (with texel weights: sum_j w[j, r] f_U[texel[j, r]], j in order) as
// one contiguous (N, C_U) block
void gather_positional(const FirstLayerArgs* a, std::vector<float>& x) {
    const int CU = a->positional;
    const int64_t N = a->rows;
    x.resize(static_cast<size_t>(N) * CU);
    if (!a->texel_weight) {
        for (int64_t r = 0; r < N; ++r)
            std::memcpy(x.data() + r * CU, a->plane + (a->texels ? a->texels[r] : r) * CU, sizeof(float) * CU);
        return;
    }
    for (int64_t r = 0; r < N; ++r) {
        float* row = x.data() + r * CU;
        for (int c = 0; c < CU; ++c) row[c] = 0.f;
        for (int j = 0; j < a->texel_taps; ++j) {
            const float w = a->texel_weight[j * N + r];
            const float* texel = a->plane + a->texels[j * N + r] * CU;
            for (int c = 0; c < CU; ++c) row[c] += w * texel[c];
        }
    }
}

// the columns [c0, c0 + n) of layer 1's weight: transposed (n, H) for the forward products, or as given (H, n)
void weight_columns(const FirstLayerArgs* a, int c0, int n, bool transposed, std::vector<float>& w) {
    const int H = a->hidden, in = a->positional + a->angular;
    w.resize(static_cast<size_t>(n) * H);
    for (int h = 0; h < H; ++h)
        for (int c = 0; c < n; ++c)
            w[transposed ? static_cast<size_t>(c) * H + h : static_cast<size_t>(h) * n + c] =
                a->weight[static_cast<int64_t>(h) * in + c0 + c];
}

template <int NH>
void first_layer_forward(const FirstLayerArgs* a) {
    const int CU = a->positional, CA = a->angular, K = a->taps, CP = a->plane_channels, planes = CA / CP;
    std::vector<float> x, wt;
    gather_positional(a, x);
    weight_columns(a, 0, CU, true, wt);
    rows_times<NH>(a->rows, CU, x.data(), wt.data(), nullptr, a->positional_pre);
    for (int64_t i = 0; i < a->images; ++i)
        for (int q = 0; q < planes; ++q) {
            const int64_t* idx = a->tap_index + (i * planes + q) * K;
            const float* tw = a->tap_weight + (i * planes + q) * K;
            float* f = a->angular_features + i * CA + q * CP;
            for (int c = 0; c < CP; ++c) f[c] = 0.f;
            for (int k = 0; k < K; ++k)
                for (int c = 0; c < CP; ++c) f[c] += tw[k] * a->angular_planes[idx[k] * CP + c];
        }
    weight_columns(a, CU, CA, true, wt);
    rows_times<NH>(a->images, CA, a->angular_features, wt.data(), a->bias, a->image_pre);
}

template <int NU, int NA>
void first_layer_backward(const FirstLayerArgs* a, const float* dP, const float* dQ, float* grad_weight,
                          float* grad_bias, float* grad_plane, float* grad_angular_planes) {
    const int H = a->hidden, CU = a->positional, CA = a->angular, K = a->taps, CP = a->plane_channels;
    const int in = CU + CA, planes = CA / CP;
    std::vector<float> x, w, grad_w_u(static_cast<size_t>(H) * CU), grad_w_a(static_cast<size_t>(H) * CA);
    std::vector<float> grad_x(static_cast<size_t>(std::max(a->rows * CU, a->images * CA)));
    gather_positional(a, x);
    weight_columns(a, 0, CU, false, w);
    rows_times_backward<NU>(a->rows, H, x.data(), dP, w.data(), grad_w_u.data(), grad_x.data());
    for (int64_t r = 0; r < a->rows; ++r) {  // in row order (each row's texels in order): repeats add up
        for (int j = 0; j < a->texel_taps; ++j) {
            const int64_t at = j * a->rows + r;
            float* g = grad_plane + (a->texels ? a->texels[at] : r) * CU;
            const float scale = a->texel_weight ? a->positional_scale * a->texel_weight[at] : a->positional_scale;
            for (int c = 0; c < CU; ++c) g[c] += scale * grad_x[r * CU + c];
        }
    }
    weight_columns(a, CU, CA, false, w);
    rows_times_backward<NA>(a->images, H, a->angular_features, dQ, w.data(), grad_w_a.data(), grad_x.data());
    for (int h = 0; h < H; ++h) grad_bias[h] = 0.f;
    for (int64_t i = 0; i < a->images; ++i) {
        for (int h = 0; h < H; ++h) grad_bias[h] += dQ[i * H + h];
        for (int q = 0; q < planes; ++q) {
            const int64_t* idx = a->tap_index + (i * planes + q) * K;
            const float* tw = a->tap_weight + (i * planes + q) * K;
            for (int k = 0; k < K; ++k) {
                float* g = grad_angular_planes + idx[k] * CP;
                for (int c = 0; c < CP; ++c) g[c] += tw[k] * grad_x[i * CA + q * CP + c];
            }
        }
    }
    for (int h = 0; h < H; ++h) {
        for (int c = 0; c < CU; ++c)
            grad_weight[static_cast<int64_t>(h) * in + c] = a->positional_scale * grad_w_u[static_cast<size_t>(h) * CU + c];
        std::memcpy(grad_weight + static_cast<int64_t>(h) * in + CU, grad_w_a.data() + static_cast<size_t>(h) * CA,
                    sizeof(float) * CA);
    }
}

template <int NU>
void first_layer_backward_u(const FirstLayerArgs* a, const float* dP, const float* dQ, float* gw, float* gb,
                            float* gp, float* ga) {
    if (a->angular == 16) first_layer_backward<NU, 16 / VW>(a, dP, dQ, gw, gb, gp, ga);
    else first_layer_backward<NU, 32 / VW>(a, dP, dQ, gw, gb, gp, ga);
}

}  // namespace

extern "C" int dynbtf_fused_l1_reduce(const FusedL1Args* a, float scale, float* weight_grads, float* image_grads,
                                      double* loss) {
    if (a->groups < 1 || a->n_items < 1 || a->n_items % a->groups) return 1;
    const int64_t bh = static_cast<int64_t>(a->images) * a->hidden, n_weights = a->item_stride - bh;
    const int64_t per_group = a->n_items / a->groups;
    std::fill(weight_grads, weight_grads + n_weights, 0.f);
    std::fill(image_grads, image_grads + a->groups * bh, 0.f);
    double total = 0.0;
    for (int64_t item = 0; item < a->n_items; ++item) {
        const float* slot = a->item_grads + item * a->item_stride;
        for (int64_t j = 0; j < n_weights; ++j) weight_grads[j] += slot[j];
        float* dq = image_grads + (item / per_group) * bh;
        for (int64_t j = 0; j < bh; ++j) dq[j] += slot[n_weights + j];
        total += a->item_loss[item];
    }
    for (int64_t j = 0; j < n_weights; ++j) weight_grads[j] *= scale;
    for (int64_t j = 0; j < a->groups * bh; ++j) image_grads[j] *= scale;
    *loss = total;
    return 0;
}

extern "C" int dynbtf_first_layer_args_size(void) { return static_cast<int>(sizeof(FirstLayerArgs)); }

extern "C" int dynbtf_first_layer_supports(int32_t hidden, int32_t positional, int32_t angular) {
    return first_layer_supported(hidden, positional, angular) ? 1 : 0;
}

extern "C" int dynbtf_first_layer_forward(const FirstLayerArgs* a) {
    if (const int code = first_layer_check(a)) return code;
    switch (a->hidden) {
        case 16: first_layer_forward<16 / VW>(a); break;
        case 32: first_layer_forward<32 / VW>(a); break;
        default: first_layer_forward<64 / VW>(a); break;
    }
    return 0;
}

extern "C" int dynbtf_first_layer_backward(const FirstLayerArgs* a, const float* grad_positional_pre,
                                           const float* grad_image_pre, float* grad_weight, float* grad_bias,
                                           float* grad_plane, float* grad_angular_planes) {
    if (const int code = first_layer_check(a)) return code;
    if (a->positional == 16)
        first_layer_backward_u<16 / VW>(a, grad_positional_pre, grad_image_pre, grad_weight, grad_bias, grad_plane,
                                        grad_angular_planes);
    else
        first_layer_backward_u<32 / VW>(a, grad_positional_pre, grad_image_pre, grad_weight, grad_bias, grad_plane,
                                        grad_angular_planes);
    return 0;
}
