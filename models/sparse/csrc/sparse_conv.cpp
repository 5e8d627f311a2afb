// Compiled CPU kernels of the sparse convolutions (models/sparse/native.py builds and loads this file).
//
// Three primitives over a kernel map's neighbour table `neighbours` (M, K) int64, where
// `neighbours[j, k]` is a row of the gathered side or `src.size(0)` where there is none:
//
//   neighbour_conv(src (N, C), neighbours (M, K), weight (K, C, D), order) -> (M, D)
//       out[j] = sum_k src[neighbours[j, k]] @ weight[k]          (submanifold / strided forward,
//                                                                   input gradients through a map's transpose)
//   scatter_conv(src (M, C), neighbours (M, K), weight (K, C, D), num_out) -> (num_out, D)
//       out[neighbours[j, k]] = src[j] @ weight[k]                 (each output row reached exactly once:
//                                                                   transposed forward, strided input gradient)
//   neighbour_weight_grad(src (N, A), neighbours (M, K), dense (M, B), order) -> (K, A, B)
//       grad[k] = sum_j src[neighbours[j, k]]^T dense[j]          (weight gradients)
//
// Design: output-stationary blocks of `kBlockRows` rows. Within a block, for each offset k the rows that
// have a neighbour are listed, and a register-blocked micro-kernel multiplies up to 4 of them at a time
// by weight[k] (which stays in L1 while the block runs through that offset): only useful MACs execute,
// missing neighbours cost nothing. Blocks run in parallel through at::parallel_for; the forward writes
// disjoint rows (no atomics), the weight gradient keeps one accumulator per thread and sums them.
// Output columns are padded to a multiple of 8 floats inside the kernels so every vector op is full.
// `order` (M,) int64, or empty for 0..M-1, is the order in which output rows are visited: spatially sorted
// rows make the neighbours gathered by one block lie close together, so they are reused from cache.

// ATen's tensor and pybind's casters only, not <torch/extension.h> (all of libtorch's C++ API): the first
// build on a machine compiles about 2.5x fewer header lines.
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <vector>

namespace {

typedef float v8 __attribute__((vector_size(32)));
typedef float v8u __attribute__((vector_size(32), aligned(4)));  // unaligned access

constexpr int64_t kLanes = 8;
constexpr int64_t kBlockRows = 64;
constexpr int kMaxRows = 4;

inline v8 load(const float* p) { return *reinterpret_cast<const v8u*>(p); }
inline void store(float* p, v8 v) { *reinterpret_cast<v8u*>(p) = v; }
inline v8 bcast(float x) { return v8{x, x, x, x, x, x, x, x}; }

inline int64_t padded(int64_t d) { return (d + kLanes - 1) / kLanes * kLanes; }

// dst[r][0:Dp] += src[r][0:C] @ w (C, Dp), for R rows, columns in chunks of NV vectors.
template <int R, int NV>
inline void rows_times_weight_chunk(const float* const* src, const float* w, int64_t C, int64_t Dp, int64_t d0,
                                    float* const* dst) {
  v8 acc[R][NV];
  for (int r = 0; r < R; ++r)
    for (int v = 0; v < NV; ++v) acc[r][v] = load(dst[r] + d0 + v * kLanes);
  for (int64_t c = 0; c < C; ++c) {
    v8 wv[NV];
    for (int v = 0; v < NV; ++v) wv[v] = load(w + c * Dp + d0 + v * kLanes);
    for (int r = 0; r < R; ++r) {
      const v8 b = bcast(src[r][c]);
      for (int v = 0; v < NV; ++v) acc[r][v] += b * wv[v];
    }
  }
  for (int r = 0; r < R; ++r)
    for (int v = 0; v < NV; ++v) store(dst[r] + d0 + v * kLanes, acc[r][v]);
}

// Vectors per column chunk: 3 where at least 3 remain (R = 4 rows x 3 vectors fill the 16 vector registers
// of AVX2 with the weight row and the broadcast), except 4 remaining = 2 + 2.
inline int chunk_vectors(int64_t remaining_columns) {
  const int64_t vectors = remaining_columns / kLanes;
  return vectors == 4 ? 2 : static_cast<int>(std::min<int64_t>(vectors, 3));
}

template <int R>
inline void rows_times_weight(const float* const* src, const float* w, int64_t C, int64_t Dp, float* const* dst) {
  for (int64_t d0 = 0; d0 < Dp;) {
    const int nv = chunk_vectors(Dp - d0);
    if (nv == 3) rows_times_weight_chunk<R, 3>(src, w, C, Dp, d0, dst);
    else if (nv == 2) rows_times_weight_chunk<R, 2>(src, w, C, Dp, d0, dst);
    else rows_times_weight_chunk<R, 1>(src, w, C, Dp, d0, dst);
    d0 += nv * kLanes;
  }
}

inline void rows_times_weight_any(int rows, const float* const* src, const float* w, int64_t C, int64_t Dp,
                                  float* const* dst) {
  switch (rows) {
    case 4: rows_times_weight<4>(src, w, C, Dp, dst); break;
    case 3: rows_times_weight<3>(src, w, C, Dp, dst); break;
    case 2: rows_times_weight<2>(src, w, C, Dp, dst); break;
    default: rows_times_weight<1>(src, w, C, Dp, dst); break;
  }
}

// grad[0:A][d0:d0+NV*8] += sum_r src[r][0:A]^T dense[r][d0:...], for R pairs (dense rows padded to Bp).
template <int R, int NV>
inline void outer_products_chunk(const float* const* src, const float* const* dense, int64_t A, int64_t Bp,
                                 int64_t d0, float* grad) {
  v8 g[R][NV];
  for (int r = 0; r < R; ++r)
    for (int v = 0; v < NV; ++v) g[r][v] = load(dense[r] + d0 + v * kLanes);
  for (int64_t a = 0; a < A; ++a) {
    v8 acc[NV];
    for (int v = 0; v < NV; ++v) acc[v] = load(grad + a * Bp + d0 + v * kLanes);
    for (int r = 0; r < R; ++r) {
      const v8 b = bcast(src[r][a]);
      for (int v = 0; v < NV; ++v) acc[v] += b * g[r][v];
    }
    for (int v = 0; v < NV; ++v) store(grad + a * Bp + d0 + v * kLanes, acc[v]);
  }
}

template <int R>
inline void outer_products(const float* const* src, const float* const* dense, int64_t A, int64_t Bp, float* grad) {
  for (int64_t d0 = 0; d0 < Bp;) {
    const int nv = chunk_vectors(Bp - d0);
    if (nv == 3) outer_products_chunk<R, 3>(src, dense, A, Bp, d0, grad);
    else if (nv == 2) outer_products_chunk<R, 2>(src, dense, A, Bp, d0, grad);
    else outer_products_chunk<R, 1>(src, dense, A, Bp, d0, grad);
    d0 += nv * kLanes;
  }
}

inline void outer_products_any(int rows, const float* const* src, const float* const* dense, int64_t A, int64_t Bp,
                               float* grad) {
  switch (rows) {
    case 4: outer_products<4>(src, dense, A, Bp, grad); break;
    case 3: outer_products<3>(src, dense, A, Bp, grad); break;
    case 2: outer_products<2>(src, dense, A, Bp, grad); break;
    default: outer_products<1>(src, dense, A, Bp, grad); break;
  }
}

// (K, C, D) -> (K, C, Dp) with zero columns, contiguous.
std::vector<float> pad_weight(const at::Tensor& weight, int64_t Dp) {
  const int64_t K = weight.size(0), C = weight.size(1), D = weight.size(2);
  std::vector<float> out(static_cast<size_t>(K * C * Dp), 0.0f);
  const float* w = weight.data_ptr<float>();
  for (int64_t kc = 0; kc < K * C; ++kc) std::memcpy(out.data() + kc * Dp, w + kc * D, D * sizeof(float));
  return out;
}

void check_inputs(const at::Tensor& src, const at::Tensor& neighbours, const char* what) {
  TORCH_CHECK(src.device().is_cpu() && neighbours.device().is_cpu(), what, ": CPU tensors expected");
  TORCH_CHECK(src.scalar_type() == at::kFloat, what, ": float32 features expected, got ", src.scalar_type());
  TORCH_CHECK(neighbours.scalar_type() == at::kLong, what, ": int64 neighbours expected");
  TORCH_CHECK(src.dim() == 2 && neighbours.dim() == 2, what, ": 2-D features and neighbours expected");
  TORCH_CHECK(src.is_contiguous() && neighbours.is_contiguous(), what, ": contiguous tensors expected");
}

void check_weight(const at::Tensor& weight, int64_t K, int64_t C, const char* what) {
  TORCH_CHECK(weight.scalar_type() == at::kFloat && weight.is_contiguous() && weight.dim() == 3, what,
              ": contiguous float32 weight (K, C_in, C_out) expected");
  TORCH_CHECK(weight.size(0) == K && weight.size(1) == C, what, ": weight shape ", weight.sizes(),
              " does not match K = ", K, ", C_in = ", C);
}

}  // namespace

const int64_t* row_order(const at::Tensor& order, int64_t M, const char* what) {
  if (order.numel() == 0) return nullptr;
  TORCH_CHECK(order.scalar_type() == at::kLong && order.is_contiguous() && order.numel() == M, what,
              ": order must be a contiguous int64 permutation of the ", M, " rows");
  return order.data_ptr<int64_t>();
}

at::Tensor neighbour_conv(at::Tensor src, at::Tensor neighbours, at::Tensor weight, at::Tensor order) {
  check_inputs(src, neighbours, "neighbour_conv");
  const int64_t N = src.size(0), C = src.size(1), M = neighbours.size(0), K = neighbours.size(1);
  check_weight(weight, K, C, "neighbour_conv");
  const int64_t D = weight.size(2), Dp = padded(D);
  auto out = at::empty({M, D}, src.options());
  if (M == 0) return out;
  const std::vector<float> w = pad_weight(weight, Dp);
  const float* feats = src.data_ptr<float>();
  const int64_t* nbr = neighbours.data_ptr<int64_t>();
  const int64_t* ord = row_order(order, M, "neighbour_conv");
  float* dst = out.data_ptr<float>();
  const int64_t blocks = (M + kBlockRows - 1) / kBlockRows;
  at::parallel_for(0, blocks, 1, [&](int64_t begin, int64_t end) {
    std::vector<float> acc(static_cast<size_t>(kBlockRows * Dp));
    int64_t rows_of[kBlockRows];
    const float* srcs[kBlockRows];
    float* dsts[kBlockRows];
    for (int64_t block = begin; block < end; ++block) {
      const int64_t j0 = block * kBlockRows, rows = std::min(kBlockRows, M - j0);
      std::fill(acc.begin(), acc.end(), 0.0f);
      for (int64_t r = 0; r < rows; ++r) rows_of[r] = ord ? ord[j0 + r] : j0 + r;
      for (int64_t k = 0; k < K; ++k) {
        int count = 0;
        for (int64_t r = 0; r < rows; ++r) {
          // Branch-free listing: about half the slots are empty in ROIs, a branch would mispredict often.
          const int64_t n = nbr[rows_of[r] * K + k];
          srcs[count] = feats + n * C;
          dsts[count] = acc.data() + r * Dp;
          count += n < N;
        }
        const float* wk = w.data() + k * C * Dp;
        for (int p = 0; p < count; p += kMaxRows)
          rows_times_weight_any(std::min(kMaxRows, count - p), srcs + p, wk, C, Dp, dsts + p);
      }
      for (int64_t r = 0; r < rows; ++r) std::memcpy(dst + rows_of[r] * D, acc.data() + r * Dp, D * sizeof(float));
    }
  });
  return out;
}

at::Tensor scatter_conv(at::Tensor src, at::Tensor neighbours, at::Tensor weight, int64_t num_out) {
  check_inputs(src, neighbours, "scatter_conv");
  const int64_t M = src.size(0), C = src.size(1), K = neighbours.size(1);
  TORCH_CHECK(neighbours.size(0) == M, "scatter_conv: one neighbour row per source row expected");
  check_weight(weight, K, C, "scatter_conv");
  const int64_t D = weight.size(2), Dp = padded(D);
  auto out = at::zeros({num_out, D}, src.options());
  if (M == 0 || num_out == 0) return out;
  const std::vector<float> w = pad_weight(weight, Dp);
  const float* feats = src.data_ptr<float>();
  const int64_t* nbr = neighbours.data_ptr<int64_t>();
  float* dst = out.data_ptr<float>();
  const int64_t blocks = (M + kBlockRows - 1) / kBlockRows;
  at::parallel_for(0, blocks, 1, [&](int64_t begin, int64_t end) {
    std::vector<float> tmp(static_cast<size_t>(kMaxRows * Dp));
    const float* srcs[kBlockRows];
    int64_t targets[kBlockRows];
    float* dsts[kMaxRows];
    for (int r = 0; r < kMaxRows; ++r) dsts[r] = tmp.data() + r * Dp;
    for (int64_t block = begin; block < end; ++block) {
      const int64_t j0 = block * kBlockRows, rows = std::min(kBlockRows, M - j0);
      for (int64_t k = 0; k < K; ++k) {
        int count = 0;
        for (int64_t r = 0; r < rows; ++r) {
          const int64_t n = nbr[(j0 + r) * K + k];
          srcs[count] = feats + (j0 + r) * C;
          targets[count] = n;
          count += n < num_out;
        }
        const float* wk = w.data() + k * C * Dp;
        for (int p = 0; p < count; p += kMaxRows) {
          const int group = std::min(kMaxRows, count - p);
          std::fill(tmp.begin(), tmp.end(), 0.0f);
          rows_times_weight_any(group, srcs + p, wk, C, Dp, dsts);
          // Each output row has exactly one (source, offset) pair in a down-sampling map: plain stores.
          for (int r = 0; r < group; ++r) std::memcpy(dst + targets[p + r] * D, dsts[r], D * sizeof(float));
        }
      }
    }
  });
  return out;
}

at::Tensor neighbour_weight_grad(at::Tensor src, at::Tensor neighbours, at::Tensor dense, at::Tensor order) {
  check_inputs(src, neighbours, "neighbour_weight_grad");
  TORCH_CHECK(dense.scalar_type() == at::kFloat && dense.is_contiguous() && dense.dim() == 2 &&
                  dense.size(0) == neighbours.size(0),
              "neighbour_weight_grad: contiguous float32 (M, B) rows expected");
  const int64_t N = src.size(0), A = src.size(1), M = neighbours.size(0), K = neighbours.size(1);
  const int64_t B = dense.size(1), Bp = padded(B);
  const float* feats = src.data_ptr<float>();
  const int64_t* nbr = neighbours.data_ptr<int64_t>();
  const float* rows_b = dense.data_ptr<float>();
  const int64_t* ord = row_order(order, M, "neighbour_weight_grad");
  const int64_t blocks = (M + kBlockRows - 1) / kBlockRows;
  const int threads = std::max<int>(1, at::get_num_threads());
  std::vector<std::vector<float>> partial(static_cast<size_t>(threads));
  if (M > 0) {
    at::parallel_for(0, blocks, 1, [&](int64_t begin, int64_t end) {
      std::vector<float>& grad = partial[static_cast<size_t>(at::get_thread_num())];
      if (grad.empty()) grad.assign(static_cast<size_t>(K * A * Bp), 0.0f);
      std::vector<float> dense_block(static_cast<size_t>(kBlockRows * Bp), 0.0f);
      const float* srcs[kBlockRows];
      const float* denses[kBlockRows];
      int64_t rows_of[kBlockRows];
      for (int64_t block = begin; block < end; ++block) {
        const int64_t j0 = block * kBlockRows, rows = std::min(kBlockRows, M - j0);
        for (int64_t r = 0; r < rows; ++r) {
          rows_of[r] = ord ? ord[j0 + r] : j0 + r;
          std::memcpy(dense_block.data() + r * Bp, rows_b + rows_of[r] * B, B * sizeof(float));
        }
        for (int64_t k = 0; k < K; ++k) {
          int count = 0;
          for (int64_t r = 0; r < rows; ++r) {
            const int64_t n = nbr[rows_of[r] * K + k];
            srcs[count] = feats + n * A;
            denses[count] = dense_block.data() + r * Bp;
            count += n < N;
          }
          float* gk = grad.data() + k * A * Bp;
          for (int p = 0; p < count; p += kMaxRows)
            outer_products_any(std::min(kMaxRows, count - p), srcs + p, denses + p, A, Bp, gk);
        }
      }
    });
  }
  auto out = at::zeros({K, A, B}, src.options());
  float* dst = out.data_ptr<float>();
  for (const auto& grad : partial) {
    if (grad.empty()) continue;
    for (int64_t ka = 0; ka < K * A; ++ka)
      for (int64_t b = 0; b < B; ++b) dst[ka * B + b] += grad[ka * Bp + b];
  }
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("neighbour_conv", &neighbour_conv, "out[j] = sum_k src[nbr[j, k]] @ weight[k]");
  m.def("scatter_conv", &scatter_conv, "out[nbr[j, k]] = src[j] @ weight[k]");
  m.def("neighbour_weight_grad", &neighbour_weight_grad, "grad[k] = sum_j src[nbr[j, k]]^T dense[j]");
}
