// The consistency term's k-step chain (cdjax.consistency.fused_chain) as two CUDA kernels called through XLA's FFI:
// the forward runs all k imagined steps of a one-hidden-layer MLP model and the GRU over the real and imagined rows,
// the backward all k steps of the per-row cotangents. Rows (windows) are independent through the chain, so each thread
// block takes kRows of them (and, for the GRU, their kRows imagined twins) through every step, holding what a step
// makes in shared memory and streaming the weights from L2. The weight gradients are not computed here: they sum over
// rows and steps, and stay one XLA product each after the backward (cdjax/kernels/chain.py).
//
// Every array may carry leading batch axes (vmap over seeds: XLA's FFI broadcasts all inputs); the product of s0's
// leading axes is the batch, the grid's y axis. Shapes, per batch entry (W rows, k steps, O state dims, X = O or 2O
// normalised-input dims, N1 hidden units, H GRU units, G = N1 + 3H):
//
//   forward  in:  s0 [W, O], z1a [k, W, N1] (the actions' share of layer 1 plus its bias), gi_re [k, W, 3H] (the real
//                 rows' GRU input part with b_i), w_in [X, G] ([layer 1's state rows | W_i], block-diagonal unless
//                 shared), w_out [N1, O], b_out [O], w_h [H, 3H], b_i [3H], b_hn [H], stats [6, O] (mean and std of
//                 the model's input, the encoder's input and the model's output)
//            out: u [k, W, N1] (hidden layer after relu), states [k+1, W, O], xin [k+1, W, X], both_im [k, W, 3H]
//                 (imagined rows' x W_i, no bias), hh [k, 2W, 3H] (h W_h, no bias), hs [k+1, 2W, H]
//   backward in:  u, xin, both_im, hh, hs, gi_re, w_in, w_out, w_h, b_i, b_hn, stats, dh [2W, H], ds [W, O]
//            out: dgi [k, 2W, 3H], dhh [k, 2W, 3H], dz [k, W, O] (output layer), dz1 [k, W, N1] (hidden layer),
//                 ds0 [W, O]
//
// Products run on the tensor cores (mma.sync m16n8k8, TF32 inputs rounded to nearest, float32 sums), as XLA's default
// precision runs float32 matrix products on this GPU; the rest is float32. O must be at most kSplitCols.
#include <cooperative_groups.h>
#include <cuda_runtime.h>

#include <cstdint>
#include <string>

#include "xla/ffi/api/ffi.h"

namespace cg = cooperative_groups;
namespace ffi = xla::ffi;

namespace {

constexpr int kRows = 16;  // rows (windows) per thread block: one m16 tile of the model's rows, two of the GRU's
constexpr int kThreads = 512;
constexpr int kWarps = kThreads / 32;
#ifndef CDJAX_CHAIN_PROBE
#define CDJAX_CHAIN_PROBE 0
#endif
// Timing probes only (benchmarks.chain_kernel --probe; wrong results): the forward skips its layer-1/GRU-input product
// (1), its recurrent product (2), its output layer (4), its stores of residuals (8), its elementwise steps (16).
constexpr int kProbe = CDJAX_CHAIN_PROBE;
constexpr int kSplitCols = 32;  // the split-K products' widest output (columns, a multiple of 8)

struct Dims {
  int64_t B, W, k, O, X, N1, H;
  __host__ __device__ int64_t G() const { return N1 + 3 * H; }
};

// The row stride of a matrix product's A operand in shared memory: its width padded to 4 mod 32 floats, so that the
// eight rows an m16n8k8 fragment load reads at once fall in distinct banks (a stride of 0 mod 32, as H = 128 is, put
// them all in one bank: 8-way conflicts, the recurrent product's cost four times over).
__host__ __device__ __forceinline__ int64_t padded(int64_t x) { return x + ((4 - x % 32) % 32 + 32) % 32; }

__device__ __forceinline__ float sigmoidf(float x) { return 1.0f / (1.0f + expf(-x)); }

// One GRU unit as flax.linen.GRUCell computes it, from its gates' input parts (ir, iz, in: x W_i + b_i) and recurrent
// parts (hr, hz: h W_h; hn: h W_hn + b_hn).
struct Gru {
  float r, z, n;
};

__device__ __forceinline__ Gru gru_gates(float ir, float iz, float in, float hr, float hz, float hn) {
  Gru u;
  u.r = sigmoidf(ir + hr);
  u.z = sigmoidf(iz + hz);
  u.n = tanhf(in + u.r * hn);
  return u;
}

__device__ __forceinline__ float gru_new(const Gru& u, float h) { return (1.0f - u.z) * u.n + u.z * h; }

// Its backward from the new state's cotangent g (hn and h as in the forward): the gates' pre-activation cotangents
// r, z, n (the recurrent part's n is n * gates.r) and the old state's direct part h.
struct GruGrad {
  float r, z, n, h;
};

// The new state of GRU row q (< 2R) of a block for one unit: a real row's gate input parts from gre (b_i included), an
// imagined row's from gim plus b_i, the recurrent parts from hh; the unit's gate columns are j, j + cs, j + 2 cs of
// rows of ld floats; its biases b_i[unit + g H] and b_hn[unit]; h its old state.
__device__ __forceinline__ float gru_row(int q, const float* gre, const float* gim, const float* hh, int64_t ld,
                                         int64_t j, int64_t cs, const float* b_i, const float* b_hn, int64_t unit,
                                         int64_t H, float h) {
  float gr, gz, gn;
  if (q < kRows) {
    const float* g = gre + q * ld;
    gr = g[j]; gz = g[cs + j]; gn = g[2 * cs + j];
  } else {
    const float* g = gim + (q - kRows) * ld;
    gr = g[j] + b_i[unit]; gz = g[cs + j] + b_i[H + unit]; gn = g[2 * cs + j] + b_i[2 * H + unit];
  }
  const float* a = hh + q * ld;
  return gru_new(gru_gates(gr, gz, gn, a[j], a[cs + j], a[2 * cs + j] + b_hn[unit]), h);
}

// p[0], p[stride], p[2 stride] = a, b, c: one unit's three gate columns
__device__ __forceinline__ void put3(float* p, int64_t stride, float a, float b, float c) {
  p[0] = a;
  p[stride] = b;
  p[2 * stride] = c;
}

__device__ __forceinline__ GruGrad gru_vjp(const Gru& u, float hn, float h, float g) {
  const float dn = g * (1.0f - u.z), dz = g * (h - u.n);
  GruGrad d;
  d.h = g * u.z;
  d.n = dn * (1.0f - u.n * u.n);
  d.r = d.n * hn * u.r * (1.0f - u.r);
  d.z = dz * u.z * (1.0f - u.z);
  return d;
}

__device__ __forceinline__ uint32_t tf32(float x) {
  uint32_t r;
  asm("cvt.rna.tf32.f32 %0, %1;" : "=r"(r) : "f"(x));
  return r;
}

// One warp: c[j][m] += A[16m.., 0:K] B[0:K, n0_j:n0_j+8] for its NT column tiles n0_j = 8 (tile0 + j step) (tiles
// at or past N skipped) and MT tiles of 16 rows, with TF32 tensor-core products (mma m16n8k8) and float32 sums. A in
// shared memory (element (m, k) at A[m * lda + k]); B's element (k, n) at B[k * sbk + n * sbn] in global memory;
// columns n >= N and k >= K count as zero. Per chunk of KC k-steps every tile's B fragments are loaded (their L2 round
// trips overlap) before the products, and each k-step's A fragments are loaded once for all NT tiles. Fragments as the
// PTX ISA lays out m16n8k8 .tf32: lane l holds A's (l/4 + 8 (r%2), l%4 + 4 (r/2)), B's (k = l%4 + 4r, n = l/4) and
// C's (l/4 + 8 (r/2), 2 (l%4) + r%2).
template <int MT, int NT, int KC, bool kSharedB = false>
__device__ __forceinline__ void mma_tiles(const float* A, int lda, const float* __restrict__ B, int64_t sbk,
                                          int64_t sbn, int K, int tile0, int step, int N, float (&c)[NT][MT][4]) {
  const int lane = threadIdx.x & 31, g = lane >> 2, q = lane & 3;
  const float* Bn[NT];
  bool n_ok[NT];
#pragma unroll
  for (int j = 0; j < NT; ++j) {
    const int n = 8 * (tile0 + j * step) + g;
    n_ok[j] = n < N;
    Bn[j] = B + (n_ok[j] ? n * sbn : 0);
  }
  for (int kc = 0; kc < K; kc += 8 * KC) {
    uint32_t bf[NT][KC][2];
#pragma unroll
    for (int j = 0; j < NT; ++j)
#pragma unroll
      for (int i = 0; i < KC; ++i) {
        const int k1 = kc + 8 * i + q, k2 = k1 + 4;
        const float* p1 = Bn[j] + k1 * sbk;
        const float* p2 = Bn[j] + k2 * sbk;
        bf[j][i][0] = tf32(n_ok[j] && k1 < K ? (kSharedB ? *p1 : __ldg(p1)) : 0.0f);
        bf[j][i][1] = tf32(n_ok[j] && k2 < K ? (kSharedB ? *p2 : __ldg(p2)) : 0.0f);
      }
#pragma unroll
    for (int i = 0; i < KC; ++i) {
      const int k0 = kc + 8 * i;
      if (k0 >= K) break;
      const int k1 = k0 + q, k2 = k1 + 4;
      const bool ok1 = k1 < K, ok2 = k2 < K;
      uint32_t af[MT][4];
#pragma unroll
      for (int m = 0; m < MT; ++m) {
        const float* a = A + (16 * m + g) * lda;
        af[m][0] = tf32(ok1 ? a[k1] : 0.0f); af[m][1] = tf32(ok1 ? a[8 * lda + k1] : 0.0f);
        af[m][2] = tf32(ok2 ? a[k2] : 0.0f); af[m][3] = tf32(ok2 ? a[8 * lda + k2] : 0.0f);
      }
#pragma unroll
      for (int j = 0; j < NT; ++j) {
        if (8 * (tile0 + j * step) >= N) continue;  // the same for the whole warp
#pragma unroll
        for (int m = 0; m < MT; ++m)
          asm volatile(
              "mma.sync.aligned.m16n8k8.row.col.f32.tf32.tf32.f32 {%0,%1,%2,%3}, {%4,%5,%6,%7}, {%8,%9}, "
              "{%0,%1,%2,%3};\n"
              : "+f"(c[j][m][0]), "+f"(c[j][m][1]), "+f"(c[j][m][2]), "+f"(c[j][m][3])
              : "r"(af[m][0]), "r"(af[m][1]), "r"(af[m][2]), "r"(af[m][3]), "r"(bf[j][i][0]), "r"(bf[j][i][1]));
      }
    }
  }
}

// f(i, load(i)) for every i < n, each thread's loads issued kBatch at a time before their uses, so that their
// latencies overlap (a loop of one global load and its use per pass waits out each load alone).
template <int kBatch, typename Load, typename F>
__device__ __forceinline__ void batched(int n, Load load, F f) {
  for (int base = threadIdx.x; base < n; base += kBatch * kThreads) {
    float v[kBatch];
#pragma unroll
    for (int j = 0; j < kBatch; ++j) {
      const int i = base + j * kThreads;
      v[j] = i < n ? load(i) : 0.0f;
    }
#pragma unroll
    for (int j = 0; j < kBatch; ++j) {
      const int i = base + j * kThreads;
      if (i < n) f(i, v[j]);
    }
  }
}

// The block: out = A [16 MT, K] B [K, N], the warps taking 8-column tiles round-robin, NT at a time over all of K;
// epi(row, n, value) for n < N. For products with many columns.
template <int MT, int NT, int KC, bool kSharedB = false, typename Epi>
__device__ __forceinline__ void gemm_tiles(const float* A, int lda, const float* __restrict__ B, int64_t sbk,
                                           int64_t sbn, int K, int N, Epi epi) {
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, g = lane >> 2, q = lane & 3;
  for (int tile0 = warp; 8 * tile0 < N; tile0 += NT * kWarps) {
    float c[NT][MT][4] = {};
    mma_tiles<MT, NT, KC, kSharedB>(A, lda, B, sbk, sbn, K, tile0, kWarps, N, c);
#pragma unroll
    for (int j = 0; j < NT; ++j)
#pragma unroll
      for (int m = 0; m < MT; ++m)
#pragma unroll
        for (int r = 0; r < 4; ++r) {
          const int n = 8 * (tile0 + j * kWarps) + 2 * q + (r & 1);
          if (n < N) epi(16 * m + g + 8 * (r >> 1), n, c[j][m][r]);
        }
  }
}

// The block: out = A [16, K] B [K, N] for few columns (N <= kSplitCols), each warp taking a slice of K for every
// column tile; the slices' sums meet in `scratch` ([kWarps, 16, kSplitCols]) and are added in slice order. Holds
// __syncthreads() (one on entry, so that a previous call's sums have been read): every thread must call it.
// epi(row, n, value) for n < N.
template <typename Epi>
__device__ __forceinline__ void gemm_split(const float* A, int lda, const float* __restrict__ B, int64_t sbk,
                                           int64_t sbn, int K, int N, float* scratch, Epi epi) {
  constexpr int NT = kSplitCols / 8;
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, g = lane >> 2, q = lane & 3;
  const int slice = ((K + kWarps - 1) / kWarps + 7) / 8 * 8;
  const int kb = min(K, warp * slice), ke = min(K, kb + slice);
  float c[NT][1][4] = {};
  if (kb < ke) mma_tiles<1, NT, 4>(A + kb, lda, B + kb * sbk, sbk, sbn, ke - kb, 0, 1, N, c);
  __syncthreads();
  float* mine = scratch + warp * 16 * kSplitCols;
#pragma unroll
  for (int j = 0; j < NT; ++j)
#pragma unroll
    for (int r = 0; r < 4; ++r) mine[(g + 8 * (r >> 1)) * kSplitCols + 8 * j + 2 * q + (r & 1)] = c[j][0][r];
  __syncthreads();
  for (int i = threadIdx.x; i < 16 * N; i += kThreads) {
    const int row = i / N, n = i - row * N;
    float v = 0.0f;
    for (int w = 0; w < kWarps; ++w) v += scratch[(w * 16 + row) * kSplitCols + n];
    epi(row, n, v);
  }
}

// The normalised inputs of the states s [R, O] into xin [R, X] (row stride xs; clip((s - mean) / std)); the encoder's
// beside the model's unless shared (X == O).
__device__ __forceinline__ void normalise(const Dims& d, const float* st, float clip, const float* s, float* xin,
                                          int xs) {
  const int O = d.O, X = d.X;
  for (int i = threadIdx.x; i < kRows * O; i += kThreads) {
    const int r = i / O, c = i - r * O;
    xin[r * xs + c] = fminf(fmaxf((s[i] - st[c]) / st[O + c], -clip), clip);
    if (X != O) xin[r * xs + O + c] = fminf(fmaxf((s[i] - st[2 * O + c]) / st[3 * O + c], -clip), clip);
  }
}

// The cotangent of the states from that of their normalised inputs dxin [R, X] (xin: the inputs, for clip's mask).
__device__ __forceinline__ float normalise_vjp(const Dims& d, const float* st, float clip, const float* xin_row,
                                               const float* dxin_row, int c) {
  const int O = d.O;
  float g = fabsf(xin_row[c]) < clip ? dxin_row[c] / st[O + c] : 0.0f;
  if (d.X != O && fabsf(xin_row[O + c]) < clip) g += dxin_row[O + c] / st[3 * O + c];
  return g;
}

__global__ void __launch_bounds__(kThreads) chain_fwd_kernel(
    Dims d, float clip, const float* __restrict__ s0, const float* __restrict__ z1a, const float* __restrict__ gi_re,
    const float* __restrict__ w_in, const float* __restrict__ w_out, const float* __restrict__ b_out,
    const float* __restrict__ w_h, const float* __restrict__ b_i, const float* __restrict__ b_hn,
    const float* __restrict__ stats, float* __restrict__ u_out, float* __restrict__ states,
    float* __restrict__ xin_out, float* __restrict__ both_im, float* __restrict__ hh_out, float* __restrict__ hs) {
  constexpr int R = kRows;
  const int64_t W = d.W, k = d.k, O = d.O, X = d.X, N1 = d.N1, H = d.H, G = d.G(), H3 = 3 * H;
  const int64_t b = blockIdx.y, row0 = int64_t(blockIdx.x) * R;
  const int nr = int(W - row0 < R ? W - row0 : R);
  s0 += b * W * O; z1a += b * k * W * N1; gi_re += b * k * W * H3; w_in += b * X * G; w_out += b * N1 * O;
  b_out += b * O; w_h += b * H * H3; b_i += b * H3; b_hn += b * H; stats += b * 6 * O;
  u_out += b * k * W * N1; states += b * (k + 1) * W * O; xin_out += b * (k + 1) * W * X; both_im += b * k * W * H3;
  hh_out += b * k * 2 * W * H3; hs += b * (k + 1) * 2 * W * H;

  extern __shared__ float smem[];
  float* scratch = smem;                     // [kWarps, 16, kSplitCols]
  float* st = scratch + kWarps * 16 * kSplitCols;  // [6, O]
  const int64_t Xs = padded(X), N1s = padded(N1), Hs = padded(H);  // row strides of the products' A operands
  float* s = st + 6 * O;                     // [R, O]
  float* xin = s + R * O;                    // [R, Xs]
  float* pu = xin + R * Xs;                  // [R, N1s]: layer 1's state part, then (in place) its relu output
  float* gim = pu + R * N1s;                 // [R, 3H]: the imagined rows' x W_i
  float* gre = gim + R * H3;                 // [R, 3H]: the real rows' GRU input part of this step
  float* h = gre + R * H3;                   // [2R, Hs]: real rows, then imagined
  float* hh = h + 2 * R * Hs;                // [2R, 3H]
  // a GRU row of the block (q < 2R) as a row of the [2W, ...] arrays; valid when its window is
  auto grow = [&](int q) { return q < R ? row0 + q : W + row0 + (q - R); };

  for (int i = threadIdx.x; i < 6 * O; i += kThreads) st[i] = stats[i];
  for (int i = threadIdx.x; i < R * O; i += kThreads) s[i] = i / O < nr ? s0[row0 * O + i] : 0.0f;
  for (int i = threadIdx.x; i < 2 * R * Hs; i += kThreads) h[i] = 0.0f;
  __syncthreads();
  normalise(d, st, clip, s, xin, Xs);
  __syncthreads();
  for (int i = threadIdx.x; i < nr * O; i += kThreads) states[row0 * O + i] = s[i];
  for (int i = threadIdx.x; i < nr * X; i += kThreads) xin_out[row0 * X + i] = xin[(i / X) * Xs + i % X];
  for (int i = threadIdx.x; i < 2 * R * H; i += kThreads) {
    const int q = i / H;
    if (q % R < nr) hs[grow(q) * H + i % H] = 0.0f;
  }
  // w_in = [W1_x | W_i] (shared) or [[W1_x, 0], [0, W_i]]: layer 1's state part reads the model's input (columns
  // 0..O-1 of xin), the GRU's input part the encoder's (enc0..enc0+O-1); the zero blocks are never multiplied
  const int64_t enc0 = X == O ? 0 : O;
  gemm_tiles<1, 4, 4>(xin, Xs, w_in, G, 1, O, N1, [&](int r, int n, float v) { pu[r * N1s + n] = v; });
  __syncthreads();

  for (int64_t t = 0; t < k; ++t) {
    const float* z1a_t = z1a + (t * W + row0) * N1;
    if (!(kProbe & 16)) batched<16>(
        int(R * N1), [&](int i) { return i / N1 < nr ? z1a_t[i] : 0.0f; },
        [&](int i, float z) {
          const int r = i / N1;
          float* p = pu + r * N1s + (i - r * N1);
          const float v = r < nr ? fmaxf(*p + z, 0.0f) : 0.0f;
          *p = v;
          if (r < nr && !(kProbe & 8)) u_out[(t * W + row0) * N1 + i] = v;
        });
    __syncthreads();
    // the model's output layer and the new states: s + (z * std + mean)
    if (!(kProbe & 4)) gemm_split(pu, N1s, w_out, O, 1, N1, O, scratch, [&](int r, int c, float z) {
      s[r * O + c] = r < nr ? s[r * O + c] + ((z + b_out[c]) * st[5 * O + c] + st[4 * O + c]) : 0.0f;
    });
    __syncthreads();
    normalise(d, st, clip, s, xin, Xs);
    __syncthreads();
    if (!(kProbe & 8)) {
      for (int i = threadIdx.x; i < nr * O; i += kThreads) states[((t + 1) * W + row0) * O + i] = s[i];
      for (int i = threadIdx.x; i < nr * X; i += kThreads)
        xin_out[((t + 1) * W + row0) * X + i] = xin[(i / X) * Xs + i % X];
    }
    // [next step's layer 1 (state part) | this step's imagined GRU input], and the recurrent products
    if (!(kProbe & 1)) {
      gemm_tiles<1, 4, 4>(xin, Xs, w_in, G, 1, O, N1, [&](int r, int n, float v) { pu[r * N1s + n] = v; });
      gemm_tiles<1, 3, 4>(xin + enc0, Xs, w_in + enc0 * G + N1, G, 1, O, H3, [&](int r, int n, float v) {
        gim[r * H3 + n] = v;
        if (r < nr && !(kProbe & 8)) both_im[(t * W + row0 + r) * H3 + n] = v;
      });
    }
    if (!(kProbe & 2)) gemm_tiles<2, 3, 8>(h, Hs, w_h, H3, 1, H, H3, [&](int q, int n, float v) {
      hh[q * H3 + n] = v;
      if (q % R < nr && !(kProbe & 8)) hh_out[(t * 2 * W + grow(q)) * H3 + n] = v;
    });
    const float* gi_re_t = gi_re + (t * W + row0) * H3;
    if (!(kProbe & 16)) batched<16>(
        int(R * H3), [&](int i) { return i / H3 < nr ? gi_re_t[i] : 0.0f; }, [&](int i, float v) { gre[i] = v; });
    __syncthreads();
    for (int i = threadIdx.x; i < (kProbe & 16 ? 0 : 2 * R * H); i += kThreads) {
      const int q = i / H, j = i - q * H;
      const bool valid = q % R < nr;
      const float hn = gru_row(q, gre, gim, hh, H3, j, H, b_i, b_hn, j, H, h[q * Hs + j]);
      h[q * Hs + j] = hn;
      if (valid && !(kProbe & 8)) hs[((t + 1) * 2 * W + grow(q)) * H + j] = hn;
    }
    __syncthreads();
  }
}

__global__ void __launch_bounds__(kThreads) chain_bwd_kernel(
    Dims d, float clip, const float* __restrict__ u_in, const float* __restrict__ xin_in,
    const float* __restrict__ both_im, const float* __restrict__ hh_in, const float* __restrict__ hs,
    const float* __restrict__ gi_re, const float* __restrict__ w_in, const float* __restrict__ w_out,
    const float* __restrict__ w_h, const float* __restrict__ b_i, const float* __restrict__ b_hn,
    const float* __restrict__ stats, const float* __restrict__ dh_in, const float* __restrict__ ds_in,
    float* __restrict__ dgi, float* __restrict__ dhh_out, float* __restrict__ dz_out, float* __restrict__ dz1_out,
    float* __restrict__ ds0) {
  constexpr int R = kRows;
  const int64_t W = d.W, k = d.k, O = d.O, X = d.X, N1 = d.N1, H = d.H, G = d.G(), H3 = 3 * H;
  const int64_t enc0 = X == O ? 0 : O;  // where the encoder's input starts in xin (w_in's second block's rows)
  const int64_t b = blockIdx.y, row0 = int64_t(blockIdx.x) * R;
  const int nr = int(W - row0 < R ? W - row0 : R);
  u_in += b * k * W * N1; xin_in += b * (k + 1) * W * X; both_im += b * k * W * H3; hh_in += b * k * 2 * W * H3;
  hs += b * (k + 1) * 2 * W * H; gi_re += b * k * W * H3; w_in += b * X * G; w_out += b * N1 * O;
  w_h += b * H * H3; b_i += b * H3; b_hn += b * H; stats += b * 6 * O; dh_in += b * 2 * W * H; ds_in += b * W * O;
  dgi += b * k * 2 * W * H3; dhh_out += b * k * 2 * W * H3; dz_out += b * k * W * O; dz1_out += b * k * W * N1;
  ds0 += b * W * O;

  extern __shared__ float smem[];
  float* scratch = smem;                     // [kWarps, 16, kSplitCols]
  float* st = scratch + kWarps * 16 * kSplitCols;  // [6, O]
  const int64_t Os = padded(O), Gs = padded(G), H3s = padded(H3);  // row strides of the products' A operands
  float* ds = st + 6 * O;                    // [R, O]: the cotangent of the current state
  float* dz = ds + R * O;                    // [R, Os]: of the output layer
  float* dxin = dz + R * Os;                 // [R, X]
  float* xin = dxin + R * X;                 // [R, X]: the step's normalised inputs (clip's mask)
  float* dboth = xin + R * X;                // [R, Gs]: [next step's layer 1 | this step's imagined GRU input]
  float* dh = dboth + R * Gs;                // [2R, H]
  float* dhd = dh + 2 * R * H;               // [2R, H]: the direct part
  float* dhh = dhd + 2 * R * H;              // [2R, H3s]
  auto grow = [&](int q) { return q < R ? row0 + q : W + row0 + (q - R); };

  for (int i = threadIdx.x; i < 6 * O; i += kThreads) st[i] = stats[i];
  for (int i = threadIdx.x; i < R * O; i += kThreads) ds[i] = i / O < nr ? ds_in[row0 * O + i] : 0.0f;
  for (int i = threadIdx.x; i < R * Gs; i += kThreads) dboth[i] = 0.0f;
  for (int i = threadIdx.x; i < 2 * R * H; i += kThreads) {
    const int q = i / H;
    dh[i] = q % R < nr ? dh_in[grow(q) * H + i % H] : 0.0f;
  }
  __syncthreads();

  for (int64_t t = k - 1; t >= 0; --t) {
    // the GRU step's backward, elementwise
    const float* gi_re_t = gi_re + t * W * H3;
    constexpr int kB = 4;  // elements per thread whose seven loads are issued together
    for (int base = threadIdx.x; base < 2 * R * H; base += kB * kThreads) {
      float in[kB][7];
  #pragma unroll
      for (int e = 0; e < kB; ++e) {
        const int i = base + e * kThreads, q = i / H, j = i - q * H;
        const bool valid = i < 2 * R * H && q % R < nr;
        float* v = in[e];
        if (valid) {
          const int64_t gq = grow(q);
          const float* g = q < R ? gi_re_t + (row0 + q) * H3 : both_im + (t * W + row0 + q - R) * H3;
          const float* a = hh_in + (t * 2 * W + gq) * H3;
          v[0] = g[j]; v[1] = g[H + j]; v[2] = g[2 * H + j]; v[3] = a[j]; v[4] = a[H + j]; v[5] = a[2 * H + j];
          v[6] = hs[(t * 2 * W + gq) * H + j];
        } else {
          for (int m = 0; m < 7; ++m) v[m] = 0.0f;
        }
      }
  #pragma unroll
      for (int e = 0; e < kB; ++e) {
        const int i = base + e * kThreads, q = i / H, j = i - q * H;
        if (i >= 2 * R * H) break;
        const bool valid = q % R < nr;
        const float bias = valid && q >= R ? 1.0f : 0.0f;
        const float* v = in[e];
        const float gr = v[0] + bias * b_i[j], gz = v[1] + bias * b_i[H + j], gn = v[2] + bias * b_i[2 * H + j];
        const float ar = v[3], az = v[4], an = v[5] + (valid ? b_hn[j] : 0.0f), hv = v[6];
        const Gru gates = gru_gates(gr, gz, gn, ar, az, an);
        const GruGrad dg = gru_vjp(gates, an, hv, dh[i]);
        dhd[i] = dg.h;
        put3(dhh + q * H3s + j, H, dg.r, dg.z, dg.n * gates.r);
        if (valid) {
          const int64_t base = (t * 2 * W + grow(q)) * H3 + j;
          put3(dgi + base, H, dg.r, dg.z, dg.n);
          put3(dhh_out + base, H, dg.r, dg.z, dg.n * gates.r);
        }
        if (q >= R) put3(dboth + (q - R) * Gs + N1 + j, H, dg.r, dg.z, dg.n);
      }
    }
    batched<4>(
        int(R * X), [&](int i) { return i / X < nr ? xin_in[((t + 1) * W + row0) * X + i] : 0.0f; },
        [&](int i, float v) { xin[i] = v; });
    __syncthreads();
    // the hidden state's cotangent for step t (h W_h's transpose), and the normalised inputs' of s_{t+1}
    gemm_tiles<2, 1, 16>(dhh, H3s, w_h, 1, H3, H3, H,
                         [&](int q, int j, float v) { dh[q * H + j] = dhd[q * H + j] + v; });
    // the normalised inputs' cotangents through w_in's two blocks (their sum where the input is shared)
    gemm_split(dboth, Gs, w_in, 1, G, N1, O, scratch, [&](int r, int c, float v) { dxin[r * X + c] = v; });
    gemm_split(dboth + N1, Gs, w_in + enc0 * G + N1, 1, G, H3, O, scratch, [&](int r, int c, float v) {
      dxin[r * X + enc0 + c] = enc0 ? v : dxin[r * X + c] + v;
    });
    __syncthreads();
    for (int i = threadIdx.x; i < R * O; i += kThreads) {
      const int r = i / O, c = i - r * O;
      ds[i] += normalise_vjp(d, st, clip, xin + r * X, dxin + r * X, c);
      dz[r * Os + c] = ds[i] * st[5 * O + c];
      if (r < nr) dz_out[(t * W + row0) * O + i] = ds[i] * st[5 * O + c];
    }
    // the hidden layer's outputs of step t (relu's mask) where the next step's layer-1 cotangent was
    const float* u_t = u_in + (t * W + row0) * N1;
    batched<16>(
        int(R * N1), [&](int i) { return i / N1 < nr ? u_t[i] : 0.0f; },
        [&](int i, float v) { dboth[(i / N1) * Gs + i % N1] = v; });
    __syncthreads();
    gemm_tiles<1, 4, 4>(dz, Os, w_out, 1, O, O, N1, [&](int r, int n, float v) {
      const float g = r < nr && dboth[r * Gs + n] > 0.0f ? v : 0.0f;
      dboth[r * Gs + n] = g;
      if (r < nr) dz1_out[(t * W + row0 + r) * N1 + n] = g;
    });
    __syncthreads();
  }
  // s_0's cotangent: the carried one and that through layer 1 of step 0
  for (int i = threadIdx.x; i < R * X; i += kThreads) xin[i] = i / X < nr ? xin_in[row0 * X + i] : 0.0f;
  for (int i = threadIdx.x; i < R * X; i += kThreads) dxin[i] = 0.0f;  // the encoder's part: no path from s_0
  gemm_split(dboth, Gs, w_in, 1, G, N1, O, scratch, [&](int r, int c, float v) { dxin[r * X + c] = v; });
  __syncthreads();
  for (int i = threadIdx.x; i < nr * O; i += kThreads) {
    const int r = i / O, c = i - r * O;
    ds0[row0 * O + i] = ds[i] + normalise_vjp(d, st, clip, xin + r * X, dxin + r * X, c);
  }
}

// ---------------------------------------------------------------------------------------------------------------
// The forward as a cluster of kCluster thread blocks per 16 rows (on an H100, 2026-11-27: correct, 1.15 ms for 20
// steps at 512 rows against XLA's 0.50; benchmarks/results/2026-11-27-h100-chain-cluster/). Each block of a
// cluster holds a 1/kCluster column share of every weight in shared memory for all k steps (no L2 round trip in the
// step loop) and 4x as many SMs work on a minibatch. Block c owns hidden units [c n1c, (c+1) n1c) of the model's layer
// and GRU units [c hc, (c+1) hc) (their r, z and n gate columns). The model's path stays in the block but for the
// output layer, whose partial sums over the blocks' units are all-reduced; the GRU's new hidden-state slices are
// all-gathered. Both go through distributed shared memory, each followed by one cluster barrier, double-buffered by
// the step's parity. Same inputs and outputs as chain_fwd_kernel.

constexpr int kCluster = 4;

struct ClusterDims {
  int64_t n1c, hc;     // hidden units and GRU units per block
  int64_t l1, li, lo;  // row strides of the weight shares (8 mod 32: conflict-free B-fragment loads)
  int64_t Xs, n1s, Hs; // row strides of the A operands (4 mod 32)
};

__host__ __device__ __forceinline__ int64_t padded8(int64_t x) { return x + ((8 - x % 32) % 32 + 32) % 32; }

__host__ __device__ __forceinline__ ClusterDims cluster_dims(const Dims& d) {
  ClusterDims c;
  c.n1c = ((d.N1 + kCluster - 1) / kCluster + 7) / 8 * 8;
  c.hc = d.H / kCluster;
  c.l1 = padded8(c.n1c); c.li = padded8(3 * c.hc); c.lo = padded8(d.O);
  c.Xs = padded(d.X); c.n1s = padded(c.n1c); c.Hs = padded(d.H);
  return c;
}

size_t fwd_cluster_smem(const Dims& d) {
  const ClusterDims c = cluster_dims(d);
  const int64_t R = kRows, O = d.O;
  const int64_t weights = O * c.l1 + O * c.li + d.H * c.li + c.n1c * c.lo;
  const int64_t acts = 6 * O + R * O + R * c.Xs + R * c.n1s + 2 * R * 3 * c.hc + 2 * R * 3 * c.hc +
                       2 * 2 * R * c.Hs + 2 * kCluster * R * O;
  return sizeof(float) * (weights + acts);
}

__global__ void __launch_bounds__(kThreads) chain_fwd_cluster_kernel(
    Dims d, float clip, const float* __restrict__ s0, const float* __restrict__ z1a, const float* __restrict__ gi_re,
    const float* __restrict__ w_in, const float* __restrict__ w_out, const float* __restrict__ b_out,
    const float* __restrict__ w_h, const float* __restrict__ b_i, const float* __restrict__ b_hn,
    const float* __restrict__ stats, float* __restrict__ u_out, float* __restrict__ states,
    float* __restrict__ xin_out, float* __restrict__ both_im, float* __restrict__ hh_out, float* __restrict__ hs) {
  constexpr int R = kRows, CS = kCluster;
  cg::cluster_group cluster = cg::this_cluster();
  const int c = int(cluster.block_rank());
  const ClusterDims cd = cluster_dims(d);
  const int64_t W = d.W, k = d.k, O = d.O, X = d.X, N1 = d.N1, H = d.H, G = d.G(), H3 = 3 * H;
  const int64_t n1c = cd.n1c, hc = cd.hc, hc3 = 3 * hc, l1 = cd.l1, li = cd.li, lo = cd.lo;
  const int64_t Xs = cd.Xs, n1s = cd.n1s, Hs = cd.Hs, enc0 = X == O ? 0 : O;
  const int64_t u0 = c * n1c, n1v = N1 - u0 < 0 ? 0 : (N1 - u0 < n1c ? N1 - u0 : n1c);  // this block's hidden units
  const int64_t b = blockIdx.y, row0 = int64_t(blockIdx.x / CS) * R;
  const int nr = int(W - row0 < R ? W - row0 : R);
  s0 += b * W * O; z1a += b * k * W * N1; gi_re += b * k * W * H3; w_in += b * X * G; w_out += b * N1 * O;
  b_out += b * O; w_h += b * H * H3; b_i += b * H3; b_hn += b * H; stats += b * 6 * O;
  u_out += b * k * W * N1; states += b * (k + 1) * W * O; xin_out += b * (k + 1) * W * X; both_im += b * k * W * H3;
  hh_out += b * k * 2 * W * H3; hs += b * (k + 1) * 2 * W * H;
  // this block's gate column j < 3hc as a column of the [.., 3H] arrays: gate j / hc, unit c hc + j % hc
  auto gcol = [&](int64_t j) { return (j / hc) * H + c * hc + j % hc; };

  extern __shared__ float smem[];
  float* W1s = smem;               // [O, l1]: layer 1's state rows, this block's units
  float* Wis = W1s + O * l1;       // [O, li]: W_i, this block's gate columns
  float* Whs = Wis + O * li;       // [H, li]: W_h, this block's gate columns
  float* Wos = Whs + H * li;       // [n1c, lo]: the output layer's rows of this block's units
  float* st = Wos + n1c * lo;      // [6, O]
  float* s = st + 6 * O;           // [R, O]
  float* xin = s + R * O;          // [R, Xs]
  float* pu = xin + R * Xs;        // [R, n1s]
  float* gim = pu + R * n1s;       // [R, 3hc]
  float* gre = gim + R * hc3;      // [R, 3hc]
  float* hh = gre + R * hc3;       // [2R, 3hc]
  float* hf = hh + 2 * R * hc3;    // [2, 2R, Hs]: every unit's hidden state, by the step's parity
  float* zx = hf + 2 * 2 * R * Hs; // [2, CS, R, O]: the blocks' output-layer partial sums, by parity
  auto grow = [&](int q) { return q < R ? row0 + q : W + row0 + (q - R); };

  for (int64_t i = threadIdx.x; i < O * l1; i += kThreads) {
    const int64_t r = i / l1, n = i % l1;
    W1s[i] = n < n1v ? w_in[r * G + u0 + n] : 0.0f;
  }
  for (int64_t i = threadIdx.x; i < O * li; i += kThreads) {
    const int64_t r = i / li, j = i % li;
    Wis[i] = j < hc3 ? w_in[(enc0 + r) * G + N1 + gcol(j)] : 0.0f;
  }
  for (int64_t i = threadIdx.x; i < H * li; i += kThreads) {
    const int64_t r = i / li, j = i % li;
    Whs[i] = j < hc3 ? w_h[r * H3 + gcol(j)] : 0.0f;
  }
  for (int64_t i = threadIdx.x; i < n1c * lo; i += kThreads) {
    const int64_t r = i / lo, n = i % lo;
    Wos[i] = r < n1v && n < O ? w_out[(u0 + r) * O + n] : 0.0f;
  }
  for (int i = threadIdx.x; i < 6 * O; i += kThreads) st[i] = stats[i];
  for (int i = threadIdx.x; i < R * O; i += kThreads) s[i] = i / O < nr ? s0[row0 * O + i] : 0.0f;
  for (int i = threadIdx.x; i < 2 * R * Hs; i += kThreads) hf[i] = 0.0f;
  __syncthreads();
  normalise(d, st, clip, s, xin, int(Xs));
  __syncthreads();
  if (c == 0) {
    for (int i = threadIdx.x; i < nr * O; i += kThreads) states[row0 * O + i] = s[i];
    for (int i = threadIdx.x; i < nr * X; i += kThreads) xin_out[row0 * X + i] = xin[(i / X) * Xs + i % X];
  }
  for (int i = threadIdx.x; i < 2 * R * hc; i += kThreads) {
    const int q = i / int(hc);
    if (q % R < nr) hs[grow(q) * H + c * hc + i % hc] = 0.0f;
  }
  gemm_tiles<1, 1, 4, true>(xin, int(Xs), W1s, l1, 1, int(O), int(n1v), [&](int r, int n, float v) {
    pu[r * n1s + n] = v;
  });
  cluster.sync();  // every block of the cluster runs before any writes into another's shared memory

  for (int64_t t = 0; t < k; ++t) {
    const int par = int(t & 1);
    const float* z1a_t = z1a + (t * W + row0) * N1 + u0;
    batched<8>(
        int(R * n1v), [&](int i) { return i / n1v < nr ? z1a_t[(i / n1v) * N1 + i % n1v] : 0.0f; },
        [&](int i, float z) {
          const int r = int(i / n1v), n = int(i % n1v);
          const float v = r < nr ? fmaxf(pu[r * n1s + n] + z, 0.0f) : 0.0f;
          pu[r * n1s + n] = v;
          if (r < nr) u_out[(t * W + row0 + r) * N1 + u0 + n] = v;
        });
    __syncthreads();
    // this block's share of the output layer, into every block's zx[par][c] (zeros where it holds no units: K = 0)
    gemm_tiles<1, 1, 8, true>(pu, int(n1s), Wos, lo, 1, int(n1v), int(O), [&](int r, int n, float v) {
      for (int rank = 0; rank < CS; ++rank)
        cluster.map_shared_rank(zx, rank)[((par * CS + c) * R + r) * O + n] = v;
    });
    cluster.sync();
    for (int i = threadIdx.x; i < R * O; i += kThreads) {
      const int r = i / int(O), col = i - r * int(O);
      float z = 0.0f;
      for (int rank = 0; rank < CS; ++rank) z += zx[(par * CS + rank) * R * O + i];
      s[i] = r < nr ? s[i] + ((z + b_out[col]) * st[5 * O + col] + st[4 * O + col]) : 0.0f;
    }
    __syncthreads();
    normalise(d, st, clip, s, xin, int(Xs));
    __syncthreads();
    if (c == 0) {
      for (int i = threadIdx.x; i < nr * O; i += kThreads) states[((t + 1) * W + row0) * O + i] = s[i];
      for (int i = threadIdx.x; i < nr * X; i += kThreads)
        xin_out[((t + 1) * W + row0) * X + i] = xin[(i / X) * Xs + i % X];
    }
    gemm_tiles<1, 1, 4, true>(xin, int(Xs), W1s, l1, 1, int(O), int(n1v), [&](int r, int n, float v) {
      pu[r * n1s + n] = v;
    });
    gemm_tiles<1, 1, 4, true>(xin + enc0, int(Xs), Wis, li, 1, int(O), int(hc3), [&](int r, int j, float v) {
      gim[r * hc3 + j] = v;
      if (r < nr) both_im[(t * W + row0 + r) * H3 + gcol(j)] = v;
    });
    const float* hprev = hf + par * 2 * R * Hs;
    gemm_tiles<2, 1, 8, true>(hprev, int(Hs), Whs, li, 1, int(H), int(hc3), [&](int q, int j, float v) {
      hh[q * hc3 + j] = v;
      if (q % R < nr) hh_out[(t * 2 * W + grow(q)) * H3 + gcol(j)] = v;
    });
    const float* gi_re_t = gi_re + (t * W + row0) * H3;
    batched<4>(
        int(R * hc3), [&](int i) { return i / hc3 < nr ? gi_re_t[(i / hc3) * H3 + gcol(i % hc3)] : 0.0f; },
        [&](int i, float v) { gre[i] = v; });
    __syncthreads();
    float* hnext = hf + (1 - par) * 2 * R * Hs;
    for (int i = threadIdx.x; i < 2 * R * hc; i += kThreads) {
      const int q = i / int(hc), j = i - q * int(hc);
      const int64_t unit = c * hc + j;
      const bool valid = q % R < nr;
      const float hn = gru_row(q, gre, gim, hh, hc3, j, hc, b_i, b_hn, unit, H, hprev[q * Hs + unit]);
      for (int rank = 0; rank < CS; ++rank) cluster.map_shared_rank(hnext, rank)[q * Hs + unit] = hn;
      if (valid) hs[((t + 1) * 2 * W + grow(q)) * H + unit] = hn;
    }
    cluster.sync();  // also keeps every block alive while others still write into its shared memory
  }
}

// The backward as a cluster of kCluster blocks per 16 rows (correct on an H100, 2026-11-27), the cluster forward's
// counterpart: block c holds the transposed shares of the weights for its hidden units and GRU units and computes the
// cotangents of its own units; the hidden state's cotangent (each block's partial over its gate columns) is
// reduce-scattered to the blocks that own the units, and the normalised inputs' cotangent (partials over units and
// gate columns) all-reduced, both through distributed shared memory and one cluster barrier a step, double-buffered
// by parity. Same inputs and outputs as chain_bwd_kernel.

size_t bwd_cluster_smem(const Dims& d) {
  const ClusterDims c = cluster_dims(d);
  const int64_t R = kRows, O = d.O, X = d.X, hc3 = 3 * c.hc, lx = padded8(d.O), lh = padded8(d.H);
  const int64_t weights = hc3 * lh + c.n1c * lx + hc3 * lx + O * c.l1;
  const int64_t acts = 6 * O + R * O + R * padded(O) + 2 * R * X + R * c.n1s + R * padded(hc3) + 2 * 2 * R * c.hc +
                       2 * R * padded(hc3) + 2 * kCluster * 2 * R * c.hc + 2 * kCluster * 2 * R * O;
  return sizeof(float) * (weights + acts);
}

__global__ void __launch_bounds__(kThreads) chain_bwd_cluster_kernel(
    Dims d, float clip, const float* __restrict__ u_in, const float* __restrict__ xin_in,
    const float* __restrict__ both_im, const float* __restrict__ hh_in, const float* __restrict__ hs,
    const float* __restrict__ gi_re, const float* __restrict__ w_in, const float* __restrict__ w_out,
    const float* __restrict__ w_h, const float* __restrict__ b_i, const float* __restrict__ b_hn,
    const float* __restrict__ stats, const float* __restrict__ dh_in, const float* __restrict__ ds_in,
    float* __restrict__ dgi, float* __restrict__ dhh_out, float* __restrict__ dz_out, float* __restrict__ dz1_out,
    float* __restrict__ ds0) {
  constexpr int R = kRows, CS = kCluster;
  cg::cluster_group cluster = cg::this_cluster();
  const int c = int(cluster.block_rank());
  const ClusterDims cd = cluster_dims(d);
  const int64_t W = d.W, k = d.k, O = d.O, X = d.X, N1 = d.N1, H = d.H, G = d.G(), H3 = 3 * H;
  const int64_t n1c = cd.n1c, hc = cd.hc, hc3 = 3 * hc, l1 = cd.l1, n1s = cd.n1s, enc0 = X == O ? 0 : O;
  const int64_t lx = padded8(O), lh = padded8(H), Os = padded(O), hcs = padded(hc3);
  const int64_t u0 = c * n1c, n1v = N1 - u0 < 0 ? 0 : (N1 - u0 < n1c ? N1 - u0 : n1c);
  const int64_t b = blockIdx.y, row0 = int64_t(blockIdx.x / CS) * R;
  const int nr = int(W - row0 < R ? W - row0 : R);
  u_in += b * k * W * N1; xin_in += b * (k + 1) * W * X; both_im += b * k * W * H3; hh_in += b * k * 2 * W * H3;
  hs += b * (k + 1) * 2 * W * H; gi_re += b * k * W * H3; w_in += b * X * G; w_out += b * N1 * O;
  w_h += b * H * H3; b_i += b * H3; b_hn += b * H; stats += b * 6 * O; dh_in += b * 2 * W * H; ds_in += b * W * O;
  dgi += b * k * 2 * W * H3; dhh_out += b * k * 2 * W * H3; dz_out += b * k * W * O; dz1_out += b * k * W * N1;
  ds0 += b * W * O;
  auto gcol = [&](int64_t j) { return (j / hc) * H + c * hc + j % hc; };
  auto grow = [&](int q) { return q < R ? row0 + q : W + row0 + (q - R); };

  extern __shared__ float smem[];
  float* WhT = smem;               // [3hc, lh]: W_h's rows of this block's gate columns (WhT[j][u] = W_h[u][gcol j])
  float* W1T = WhT + hc3 * lh;     // [n1c, lx]: layer 1's state rows for this block's units, transposed
  float* WiT = W1T + n1c * lx;     // [3hc, lx]: W_i's columns of this block's gates, transposed
  float* WoT = WiT + hc3 * lx;     // [O, l1]: the output layer's rows of this block's units, transposed
  float* st = WoT + O * l1;        // [6, O]
  float* ds = st + 6 * O;          // [R, O]: the current state's cotangent (the same in every block)
  float* dz = ds + R * O;          // [R, Os]
  float* dxin = dz + R * Os;       // [R, X]
  float* xin = dxin + R * X;       // [R, X]
  float* dp1 = xin + R * X;        // [R, n1s]: the next step's layer-1 cotangent, this block's units
  float* dbim = dp1 + R * n1s;     // [R, hcs]: the imagined rows' GRU-input cotangent, this block's gate columns
  float* dhl = dbim + R * hcs;     // [2R, hc]: h's cotangent, this block's units
  float* dhd = dhl + 2 * R * hc;   // [2R, hc]: its direct part
  float* dhh = dhd + 2 * R * hc;   // [2R, hcs]: the recurrent product's cotangent, this block's gate columns
  float* dhx = dhh + 2 * R * hcs;  // [2, CS, 2R, hc]: the blocks' partials of h's cotangent for this block's units
  float* dxx = dhx + 2 * CS * 2 * R * hc;  // [2, CS, 2, R, O]: the blocks' partials of dxin (model part, encoder part)

  for (int64_t i = threadIdx.x; i < hc3 * lh; i += kThreads) {
    const int64_t j = i / lh, u = i % lh;
    WhT[i] = u < H ? w_h[u * H3 + gcol(j)] : 0.0f;
  }
  for (int64_t i = threadIdx.x; i < n1c * lx; i += kThreads) {
    const int64_t n = i / lx, x = i % lx;
    W1T[i] = n < n1v && x < O ? w_in[x * G + u0 + n] : 0.0f;
  }
  for (int64_t i = threadIdx.x; i < hc3 * lx; i += kThreads) {
    const int64_t j = i / lx, x = i % lx;
    WiT[i] = x < O ? w_in[(enc0 + x) * G + N1 + gcol(j)] : 0.0f;
  }
  for (int64_t i = threadIdx.x; i < O * l1; i += kThreads) {
    const int64_t x = i / l1, n = i % l1;
    WoT[i] = n < n1v ? w_out[(u0 + n) * O + x] : 0.0f;
  }
  for (int i = threadIdx.x; i < 6 * O; i += kThreads) st[i] = stats[i];
  for (int i = threadIdx.x; i < R * O; i += kThreads) ds[i] = i / O < nr ? ds_in[row0 * O + i] : 0.0f;
  for (int i = threadIdx.x; i < R * n1s; i += kThreads) dp1[i] = 0.0f;
  for (int i = threadIdx.x; i < 2 * R * hc; i += kThreads) {
    const int q = i / int(hc);
    dhl[i] = q % R < nr ? dh_in[grow(q) * H + c * hc + i % hc] : 0.0f;
  }
  cluster.sync();

  for (int64_t sidx = 0; sidx < k; ++sidx) {
    const int64_t t = k - 1 - sidx;
    const int par = int(sidx & 1);
    const float* gi_re_t = gi_re + t * W * H3;
    for (int i = threadIdx.x; i < 2 * R * hc; i += kThreads) {
      const int q = i / int(hc), j = i - q * int(hc);
      const int64_t unit = c * hc + j;
      const bool valid = q % R < nr;
      float gr = 0.0f, gz = 0.0f, gn = 0.0f, ar = 0.0f, az = 0.0f, an = 0.0f, hv = 0.0f;
      if (valid) {
        const int64_t gq = grow(q);
        const float* g = q < R ? gi_re_t + (row0 + q) * H3 : both_im + (t * W + row0 + q - R) * H3;
        const float bias = q < R ? 0.0f : 1.0f;
        gr = g[unit] + bias * b_i[unit]; gz = g[H + unit] + bias * b_i[H + unit];
        gn = g[2 * H + unit] + bias * b_i[2 * H + unit];
        const float* a = hh_in + (t * 2 * W + gq) * H3;
        ar = a[unit]; az = a[H + unit]; an = a[2 * H + unit] + b_hn[unit];
        hv = hs[(t * 2 * W + gq) * H + unit];
      }
      const Gru gates = gru_gates(gr, gz, gn, ar, az, an);
      const GruGrad dg = gru_vjp(gates, an, hv, dhl[i]);
      dhd[i] = dg.h;
      put3(dhh + q * hcs + j, hc, dg.r, dg.z, dg.n * gates.r);
      if (valid) {
        const int64_t base = (t * 2 * W + grow(q)) * H3 + unit;
        put3(dgi + base, H, dg.r, dg.z, dg.n);
        put3(dhh_out + base, H, dg.r, dg.z, dg.n * gates.r);
      }
      if (q >= R) put3(dbim + (q - R) * hcs + j, hc, dg.r, dg.z, dg.n);
    }
    batched<2>(
        int(R * X), [&](int i) { return i / X < nr ? xin_in[((t + 1) * W + row0) * X + i] : 0.0f; },
        [&](int i, float v) { xin[i] = v; });
    __syncthreads();
    // partials: h's cotangent over this block's gate columns, to the blocks owning the units; the normalised inputs'
    gemm_tiles<2, 1, 8, true>(dhh, int(hcs), WhT, lh, 1, int(hc3), int(H), [&](int q, int u, float v) {
      const int owner = u / int(hc);
      cluster.map_shared_rank(dhx, owner)[((par * CS + c) * 2 * R + q) * hc + u % hc] = v;
    });
    gemm_tiles<1, 1, 8, true>(dp1, int(n1s), W1T, lx, 1, int(n1v), int(O), [&](int r, int x, float v) {
      for (int rank = 0; rank < CS; ++rank)
        cluster.map_shared_rank(dxx, rank)[(((par * CS + c) * 2 + 0) * R + r) * O + x] = v;
    });
    gemm_tiles<1, 1, 8, true>(dbim, int(hcs), WiT, lx, 1, int(hc3), int(O), [&](int r, int x, float v) {
      for (int rank = 0; rank < CS; ++rank)
        cluster.map_shared_rank(dxx, rank)[(((par * CS + c) * 2 + 1) * R + r) * O + x] = v;
    });
    cluster.sync();
    for (int i = threadIdx.x; i < 2 * R * hc; i += kThreads) {
      float v = dhd[i];
      for (int rank = 0; rank < CS; ++rank) v += dhx[(par * CS + rank) * 2 * R * hc + i];
      dhl[i] = v;
    }
    for (int i = threadIdx.x; i < R * O; i += kThreads) {
      const int r = i / int(O), x = i - r * int(O);
      float m = 0.0f, e = 0.0f;
      for (int rank = 0; rank < CS; ++rank) {
        m += dxx[(((par * CS + rank) * 2 + 0) * R + r) * O + x];
        e += dxx[(((par * CS + rank) * 2 + 1) * R + r) * O + x];
      }
      if (enc0) {
        dxin[r * X + x] = m; dxin[r * X + O + x] = e;
      } else {
        dxin[r * X + x] = m + e;
      }
    }
    __syncthreads();
    for (int i = threadIdx.x; i < R * O; i += kThreads) {
      const int r = i / int(O), x = i - r * int(O);
      ds[i] += normalise_vjp(d, st, clip, xin + r * X, dxin + r * X, x);
      dz[r * Os + x] = ds[i] * st[5 * O + x];
      if (c == 0 && r < nr) dz_out[(t * W + row0) * O + i] = ds[i] * st[5 * O + x];
    }
    const float* u_t = u_in + (t * W + row0) * N1 + u0;  // relu's mask, where dp1 was
    batched<8>(
        int(R * n1v), [&](int i) { return i / n1v < nr ? u_t[(i / n1v) * N1 + i % n1v] : 0.0f; },
        [&](int i, float v) { dp1[(i / n1v) * n1s + i % n1v] = v; });
    __syncthreads();
    gemm_tiles<1, 1, 4, true>(dz, int(Os), WoT, l1, 1, int(O), int(n1v), [&](int r, int n, float v) {
      const float g = r < nr && dp1[r * n1s + n] > 0.0f ? v : 0.0f;
      dp1[r * n1s + n] = g;
      if (r < nr) dz1_out[(t * W + row0 + r) * N1 + u0 + n] = g;
    });
    __syncthreads();
  }
  // s_0's cotangent: the carried one and that through layer 1 of step 0 (the model's part of the inputs only)
  const int par = int(k & 1);
  gemm_tiles<1, 1, 8, true>(dp1, int(n1s), W1T, lx, 1, int(n1v), int(O), [&](int r, int x, float v) {
    for (int rank = 0; rank < CS; ++rank)
      cluster.map_shared_rank(dxx, rank)[(((par * CS + c) * 2 + 0) * R + r) * O + x] = v;
  });
  for (int i = threadIdx.x; i < R * X; i += kThreads) {
    xin[i] = i / X < nr ? xin_in[row0 * X + i] : 0.0f;
    dxin[i] = 0.0f;
  }
  cluster.sync();
  for (int i = threadIdx.x; i < R * O; i += kThreads) {
    const int r = i / int(O), x = i - r * int(O);
    float m = 0.0f;
    for (int rank = 0; rank < CS; ++rank) m += dxx[(((par * CS + rank) * 2 + 0) * R + r) * O + x];
    dxin[r * X + x] = m;
  }
  __syncthreads();
  if (c == 0)
    for (int i = threadIdx.x; i < nr * O; i += kThreads) {
      const int r = i / int(O), x = i - r * int(O);
      ds0[row0 * O + i] = ds[i] + normalise_vjp(d, st, clip, xin + r * X, dxin + r * X, x);
    }
}

size_t fwd_smem(const Dims& d) {
  const int64_t R = kRows, H3 = 3 * d.H;
  return sizeof(float) * (kWarps * 16 * kSplitCols + 6 * d.O + R * (d.O + padded(d.X) + padded(d.N1) + 2 * H3) +
                          2 * R * padded(d.H) + 2 * R * H3);
}

size_t bwd_smem(const Dims& d) {
  const int64_t R = kRows;
  return sizeof(float) * (kWarps * 16 * kSplitCols + 6 * d.O + R * (d.O + padded(d.O) + 2 * d.X + padded(d.G())) +
                          4 * R * d.H + 2 * R * padded(3 * d.H));
}

// Trailing dims of a buffer, checked against `want` (its last want.size() axes); its leading axes' product must be B.
template <typename Buf>
bool shaped(const Buf& buf, std::initializer_list<int64_t> want, int64_t B) {
  auto dims = buf.dimensions();
  const int64_t n = int64_t(want.size());
  if (int64_t(dims.size()) < n) return false;
  int64_t lead = 1;
  for (int64_t i = 0; i < int64_t(dims.size()) - n; ++i) lead *= dims[i];
  int64_t i = int64_t(dims.size()) - n;
  for (int64_t w : want)
    if (dims[i++] != w) return false;
  return lead == B;
}

ffi::Error launched(const char* what) {
  const cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return ffi::Error::Internal(std::string(what) + ": " + cudaGetErrorString(err));
  return ffi::Error::Success();
}

using F32 = ffi::Buffer<ffi::F32>;
using F32Out = ffi::ResultBuffer<ffi::F32>;

// The batch and sizes from s0 [..., W, O], z1a [..., k, W, N1], gi_re [..., k, W, 3H] and w_in [..., X, G].
bool dims_of(const F32& s0, const F32& z1a, const F32& gi_re, const F32& w_in, Dims* d) {
  auto s = s0.dimensions(), z = z1a.dimensions(), g = gi_re.dimensions(), w = w_in.dimensions();
  if (s.size() < 2 || z.size() < 3 || g.size() < 3 || w.size() < 2) return false;
  d->W = s[s.size() - 2]; d->O = s[s.size() - 1];
  d->k = z[z.size() - 3]; d->N1 = z[z.size() - 1];
  d->H = g[g.size() - 1] / 3; d->X = w[w.size() - 2];
  d->B = 1;
  for (size_t i = 0; i + 2 < s.size(); ++i) d->B *= s[i];
  return g[g.size() - 1] == 3 * d->H && (d->X == d->O || d->X == 2 * d->O) && w[w.size() - 1] == d->G() &&
         d->O <= kSplitCols;
}

// The launch of `rows` row tiles (kCluster blocks each when `cluster`) over B batch entries; `attribute` holds the
// cluster's shape while the config is in use.
cudaLaunchConfig_t launch_config(bool cluster, int64_t rows, int64_t B, size_t smem, cudaStream_t stream,
                                 cudaLaunchAttribute (&attribute)[1]) {
  cudaLaunchConfig_t config = {};
  config.gridDim = dim3(unsigned(rows * (cluster ? kCluster : 1)), unsigned(B));
  config.blockDim = dim3(kThreads);
  config.dynamicSmemBytes = smem;
  config.stream = stream;
  attribute[0].id = cudaLaunchAttributeClusterDimension;
  attribute[0].val.clusterDim.x = cluster ? kCluster : 1;
  attribute[0].val.clusterDim.y = 1;
  attribute[0].val.clusterDim.z = 1;
  config.attrs = attribute;
  config.numAttrs = cluster ? 1 : 0;
  return config;
}

// `kernel` (of `d` and then `args`) launched over d's row tiles and batch (kCluster blocks a tile when `cluster`) with
// `smem` bytes of dynamic shared memory; the error, named `name`, when the launch failed.
template <typename Kernel, typename... Args>
ffi::Error launch_chain(Kernel kernel, bool cluster, const Dims& d, size_t smem, cudaStream_t stream, const char* name,
                        Args... args) {
  cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, int(smem));
  cudaLaunchAttribute attribute[1];
  const cudaLaunchConfig_t config = launch_config(cluster, (d.W + kRows - 1) / kRows, d.B, smem, stream, attribute);
  cudaLaunchKernelEx(&config, kernel, d, args...);
  return launched(name);
}

ffi::Error ChainFwdImpl(bool cluster, cudaStream_t stream, float clip, F32 s0, F32 z1a, F32 gi_re, F32 w_in,
                        F32 w_out, F32 b_out, F32 w_h, F32 b_i, F32 b_hn, F32 stats, F32Out u, F32Out states,
                        F32Out xin, F32Out both_im, F32Out hh, F32Out hs) {
  Dims d;
  if (!dims_of(s0, z1a, gi_re, w_in, &d) || (cluster && d.H % (8 * kCluster) != 0))
    return ffi::Error::InvalidArgument("cdjax_chain_fwd: inconsistent shapes (or for clusters H not a multiple of 32)");
  const int64_t B = d.B, W = d.W, k = d.k, O = d.O, X = d.X, N1 = d.N1, H = d.H, H3 = 3 * H;
  const bool ok = shaped(z1a, {k, W, N1}, B) && shaped(gi_re, {k, W, H3}, B) && shaped(w_in, {X, d.G()}, B) &&
                  shaped(w_out, {N1, O}, B) && shaped(b_out, {O}, B) && shaped(w_h, {H, H3}, B) &&
                  shaped(b_i, {H3}, B) && shaped(b_hn, {H}, B) && shaped(stats, {6, O}, B) &&
                  shaped(*u, {k, W, N1}, B) && shaped(*states, {k + 1, W, O}, B) && shaped(*xin, {k + 1, W, X}, B) &&
                  shaped(*both_im, {k, W, H3}, B) && shaped(*hh, {k, 2 * W, H3}, B) &&
                  shaped(*hs, {k + 1, 2 * W, H}, B);
  if (!ok) return ffi::Error::InvalidArgument("cdjax_chain_fwd: a buffer's shape does not match s0, z1a, gi_re, w_in");
  if (B == 0 || W == 0) return ffi::Error::Success();
  return launch_chain(cluster ? chain_fwd_cluster_kernel : chain_fwd_kernel, cluster, d,
                      cluster ? fwd_cluster_smem(d) : fwd_smem(d), stream,
                      cluster ? "cdjax_chain_fwd_cluster" : "cdjax_chain_fwd", clip, s0.typed_data(), z1a.typed_data(),
                      gi_re.typed_data(), w_in.typed_data(), w_out.typed_data(), b_out.typed_data(), w_h.typed_data(),
                      b_i.typed_data(), b_hn.typed_data(), stats.typed_data(), u->typed_data(), states->typed_data(),
                      xin->typed_data(), both_im->typed_data(), hh->typed_data(), hs->typed_data());
}

ffi::Error ChainFwd(cudaStream_t stream, float clip, F32 s0, F32 z1a, F32 gi_re, F32 w_in, F32 w_out, F32 b_out,
                    F32 w_h, F32 b_i, F32 b_hn, F32 stats, F32Out u, F32Out states, F32Out xin, F32Out both_im,
                    F32Out hh, F32Out hs) {
  return ChainFwdImpl(false, stream, clip, s0, z1a, gi_re, w_in, w_out, b_out, w_h, b_i, b_hn, stats, u, states, xin,
                      both_im, hh, hs);
}

ffi::Error ChainFwdCluster(cudaStream_t stream, float clip, F32 s0, F32 z1a, F32 gi_re, F32 w_in, F32 w_out,
                           F32 b_out, F32 w_h, F32 b_i, F32 b_hn, F32 stats, F32Out u, F32Out states, F32Out xin,
                           F32Out both_im, F32Out hh, F32Out hs) {
  return ChainFwdImpl(true, stream, clip, s0, z1a, gi_re, w_in, w_out, b_out, w_h, b_i, b_hn, stats, u, states, xin,
                      both_im, hh, hs);
}

ffi::Error ChainBwdImpl(bool cluster, cudaStream_t stream, float clip, F32 u, F32 xin, F32 both_im, F32 hh, F32 hs,
                        F32 gi_re, F32 w_in, F32 w_out, F32 w_h, F32 b_i, F32 b_hn, F32 stats, F32 dh, F32 ds,
                        F32Out dgi, F32Out dhh, F32Out dz, F32Out dz1, F32Out ds0) {
  auto sd = ds.dimensions(), ud = u.dimensions(), hd = hs.dimensions(), wd = w_in.dimensions();
  if (sd.size() < 2 || ud.size() < 3 || hd.size() < 3 || wd.size() < 2)
    return ffi::Error::InvalidArgument("cdjax_chain_bwd: inconsistent shapes");
  Dims d;
  d.W = sd[sd.size() - 2]; d.O = sd[sd.size() - 1]; d.k = ud[ud.size() - 3]; d.N1 = ud[ud.size() - 1];
  d.H = hd[hd.size() - 1]; d.X = wd[wd.size() - 2];
  d.B = 1;
  for (size_t i = 0; i + 2 < sd.size(); ++i) d.B *= sd[i];
  const int64_t B = d.B, W = d.W, k = d.k, O = d.O, X = d.X, N1 = d.N1, H = d.H, H3 = 3 * H;
  const bool ok = (X == O || X == 2 * O) && O <= kSplitCols && (!cluster || H % (8 * kCluster) == 0) &&
                  shaped(u, {k, W, N1}, B) && shaped(xin, {k + 1, W, X}, B) && shaped(both_im, {k, W, H3}, B) &&
                  shaped(hh, {k, 2 * W, H3}, B) &&
                  shaped(hs, {k + 1, 2 * W, H}, B) && shaped(gi_re, {k, W, H3}, B) && shaped(w_in, {X, d.G()}, B) &&
                  shaped(w_out, {N1, O}, B) && shaped(w_h, {H, H3}, B) && shaped(b_i, {H3}, B) &&
                  shaped(b_hn, {H}, B) && shaped(stats, {6, O}, B) && shaped(dh, {2 * W, H}, B) &&
                  shaped(*dgi, {k, 2 * W, H3}, B) && shaped(*dhh, {k, 2 * W, H3}, B) && shaped(*dz, {k, W, O}, B) &&
                  shaped(*dz1, {k, W, N1}, B) && shaped(*ds0, {W, O}, B);
  if (!ok) return ffi::Error::InvalidArgument("cdjax_chain_bwd: a buffer's shape does not match ds, u, hs, w_in");
  if (B == 0 || W == 0) return ffi::Error::Success();
  return launch_chain(cluster ? chain_bwd_cluster_kernel : chain_bwd_kernel, cluster, d,
                      cluster ? bwd_cluster_smem(d) : bwd_smem(d), stream,
                      cluster ? "cdjax_chain_bwd_cluster" : "cdjax_chain_bwd", clip, u.typed_data(), xin.typed_data(),
                      both_im.typed_data(), hh.typed_data(), hs.typed_data(), gi_re.typed_data(), w_in.typed_data(),
                      w_out.typed_data(), w_h.typed_data(), b_i.typed_data(), b_hn.typed_data(), stats.typed_data(),
                      dh.typed_data(), ds.typed_data(), dgi->typed_data(), dhh->typed_data(), dz->typed_data(),
                      dz1->typed_data(), ds0->typed_data());
}

ffi::Error ChainBwd(cudaStream_t stream, float clip, F32 u, F32 xin, F32 both_im, F32 hh, F32 hs, F32 gi_re,
                    F32 w_in, F32 w_out, F32 w_h, F32 b_i, F32 b_hn, F32 stats, F32 dh, F32 ds, F32Out dgi,
                    F32Out dhh, F32Out dz, F32Out dz1, F32Out ds0) {
  return ChainBwdImpl(false, stream, clip, u, xin, both_im, hh, hs, gi_re, w_in, w_out, w_h, b_i, b_hn, stats, dh, ds,
                      dgi, dhh, dz, dz1, ds0);
}

ffi::Error ChainBwdCluster(cudaStream_t stream, float clip, F32 u, F32 xin, F32 both_im, F32 hh, F32 hs, F32 gi_re,
                           F32 w_in, F32 w_out, F32 w_h, F32 b_i, F32 b_hn, F32 stats, F32 dh, F32 ds, F32Out dgi,
                           F32Out dhh, F32Out dz, F32Out dz1, F32Out ds0) {
  return ChainBwdImpl(true, stream, clip, u, xin, both_im, hh, hs, gi_re, w_in, w_out, w_h, b_i, b_hn, stats, dh, ds,
                      dgi, dhh, dz, dz1, ds0);
}

}  // namespace

// The forward's attribute, ten operands and six results, and the backward's attribute, 14 operands and five results.
#define CDJAX_FWD_BINDING                                                                                  \
  ffi::Ffi::Bind()                                                                                       \
      .Ctx<ffi::PlatformStream<cudaStream_t>>()                                                          \
      .Attr<float>("clip")                                                                               \
      .Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>() \
      .Arg<F32>()                                                                                        \
      .Ret<F32>().Ret<F32>().Ret<F32>().Ret<F32>().Ret<F32>().Ret<F32>()
#define CDJAX_BWD_BINDING                                                                                  \
  ffi::Ffi::Bind()                                                                                       \
      .Ctx<ffi::PlatformStream<cudaStream_t>>()                                                          \
      .Attr<float>("clip")                                                                               \
      .Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>() \
      .Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>().Arg<F32>()                                            \
      .Ret<F32>().Ret<F32>().Ret<F32>().Ret<F32>().Ret<F32>()

XLA_FFI_DEFINE_HANDLER_SYMBOL(CdjaxChainFwd, ChainFwd, CDJAX_FWD_BINDING);

XLA_FFI_DEFINE_HANDLER_SYMBOL(CdjaxChainFwdCluster, ChainFwdCluster, CDJAX_FWD_BINDING);

XLA_FFI_DEFINE_HANDLER_SYMBOL(CdjaxChainBwd, ChainBwd, CDJAX_BWD_BINDING);

XLA_FFI_DEFINE_HANDLER_SYMBOL(CdjaxChainBwdCluster, ChainBwdCluster, CDJAX_BWD_BINDING);

// The shared memory (bytes) of the forward's (which = 0), the backward's (1), the cluster forward's (2) and the
// cluster backward's (3) thread block
// at these widths, for the Python side to decide whether a chain fits before it calls the kernels.
extern "C" int64_t CdjaxChainSmem(int64_t O, int64_t X, int64_t N1, int64_t H, int64_t which) {
  Dims d{1, 1, 1, O, X, N1, H};
  return int64_t(which == 0 ? fwd_smem(d) : which == 1 ? bwd_smem(d) : which == 2 ? fwd_cluster_smem(d)
                                                                                : bwd_cluster_smem(d));
}
