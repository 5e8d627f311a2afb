// Compiled CPU kernels of the sparse convolutions (models/sparse/compiled.py builds and loads this file).
//
// Three primitives over a kernel map's neighbour table `neighbours` (M, K) int64, where
// `neighbours[j, k]` is a row of the gathered side or `src.size(0)` where there is none:
//
//   neighbour_conv(src (N, C), neighbours (M, K), weight (K, C, D)) -> (M, D)
//       out[j] = sum_k src[neighbours[j, k]] @ weight[k]          (submanifold / strided forward,
//                                                                   input gradients through a map's transpose)
//   scatter_conv(src (M, C), neighbours (M, K), weight (K, C, D), num_out) -> (num_out, D)
//       out[neighbours[j, k]] = src[j] @ weight[k]                 (each output row reached exactly once:
//                                                                   transposed forward, strided input gradient)
//   neighbour_weight_grad(src (N, A), neighbours (M, K), dense (M, B)) -> (K, A, B)
//       grad[k] = sum_j src[neighbours[j, k]]^T dense[j]          (weight gradients)
//
// Design: output-stationary blocks of `kBlockRows` rows. Within a block, for each offset k the rows that
// have a neighbour are listed, and a register-blocked micro-kernel (micro_kernel.h, shared with the int8
// kernels) multiplies up to 4 (AVX2) or 8 (AVX-512) of them at a time by weight[k] (which stays in L1 while the
// block runs through that offset): only useful MACs execute, missing neighbours cost nothing. Blocks run in
// parallel through at::parallel_for; the forward writes disjoint rows (no atomics), the weight gradient keeps one
// accumulator per thread and sums them.
// Output columns are padded to a multiple of 8 floats inside the kernels so every vector op is full.
// For inference, `neighbour_conv_fused` and `scatter_conv_fused` apply a folded BatchNorm's bias, a residual sum and
// a ReLU in the loop that writes the output rows (no extra pass over the features).

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

#include "micro_kernel.h"

namespace {

using namespace radarseg_kernels;

// Vectors: `half` is 8 floats (AVX2's register); `wide` is 16 floats where the compiler targets AVX-512
// (-march=native on such a CPU: 32 registers, 16 lanes), else the same 8 floats. Columns are padded to a
// multiple of 8; a column chunk is `NW` wide vectors plus `NH` (0 or 1) half vectors, so a 24-column layer
// on AVX-512 runs as 16 + 8 lanes and never pads to 32.
typedef float half_v __attribute__((vector_size(32)));
#if defined(__AVX512F__)
typedef float wide_v __attribute__((vector_size(64)));
#else
typedef half_v wide_v;
#endif

// The micro-kernel's types and multiply-add on float32 rows (micro_kernel.h).
struct FloatOps {
  using in_t = float;
  using weight_t = float;
  using acc_t = float;
  using wide_v = ::wide_v;
  using half_v = ::half_v;
#if defined(__AVX512F__)
  static constexpr int64_t kWide = 16;
  static constexpr int kMaxRows = 8;  // 8 rows x up to 3 vectors = 24 accumulators of 32 registers
#else
  static constexpr int64_t kWide = 8;
  static constexpr int kMaxRows = 4;  // 4 rows x 3 vectors = 12 accumulators of AVX2's 16 registers
#endif
  static constexpr int kMaxChunkVectors = 3;
  static constexpr bool kHalfJoinsWide = true;  // 24 columns as one chunk of 16 + 8
  static constexpr int64_t kGroup = 1;

  static inline float group(const float* p) { return *p; }
  template <typename V>
  static inline V madd(V acc, float x, V w) { return acc + (x - V{}) * w; }  // scalar - vector broadcasts the scalar
};

constexpr int kMaxRows = FloatOps::kMaxRows;

// grad[0:A][d0:d0+columns] += sum_r src[r][0:A]^T dense[r][d0:...], for R pairs (dense rows padded to Bp).
template <int R, int NW, int NH>
inline void outer_products_chunk(const float* const* src, const float* const* dense, int64_t A, int64_t Bp,
                                 int64_t d0, float* grad) {
  Tile<FloatOps, R, NW, NH> g;
  for (int r = 0; r < R; ++r) g.load_row(r, dense[r] + d0);
  for (int64_t a = 0; a < A; ++a) {
    float* ga = grad + a * Bp + d0;
    Tile<FloatOps, 1, NW, NH> acc;
    acc.load_row(0, ga);
    for (int r = 0; r < R; ++r) acc.madd_row(0, src[r][a], g, r);
    acc.store_row(0, ga);
  }
}

// dst[r] += src[r] @ w for `rows` <= kMaxRows rows.
inline void rows_times_weight_any(int rows, const float* const* src, const float* w, int64_t C, int64_t Dp,
                                  float* const* dst) {
  rows_times_weight<FloatOps>(rows, src, w, C, Dp, dst);
}

// grad += sum_r src[r]^T dense[r] for `rows` <= kMaxRows pairs.
inline void outer_products_any(int rows, const float* const* src, const float* const* dense, int64_t A, int64_t Bp,
                               float* grad) {
  over_tiles<FloatOps>(rows, Bp, [&](auto r, int64_t d0, auto nw, auto nh) {
    outer_products_chunk<decltype(r)::value, decltype(nw)::value, decltype(nh)::value>(src, dense, A, Bp, d0, grad);
  });
}

// The rows of a block (`rows` of them from row `j0`) that have a neighbour at offset k, listed branch-free (about
// half the slots are empty in ROIs, a branch would mispredict often): each one's gathered row of `gathered`
// (row width `width`) in `srcs`, its row of the block buffer `block` (row width `Dp`) in `block_rows`.
inline int list_present(const int64_t* nbr, int64_t j0, int64_t rows, int64_t K, int64_t k, int64_t N,
                        const float* gathered, int64_t width, float* block, int64_t Dp, const float** srcs,
                        float** block_rows) {
  int count = 0;
  for (int64_t r = 0; r < rows; ++r) {
    const int64_t n = nbr[(j0 + r) * K + k];
    srcs[count] = gathered + n * width;
    block_rows[count] = block + r * Dp;
    count += n < N;
  }
  return count;
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

// The output epilogue of an inference layer: out = max(acc + bias + residual, 0), each part optional (a BatchNorm
// folded into the weights and bias, the residual sum of a block and its ReLU, in the loop that writes the rows).
struct Epilogue {
  const float* bias = nullptr;      // (D,)
  const float* residual = nullptr;  // (M, D), row j added to output row j
  bool relu = false;

  inline void write(float* out, const float* acc, const float* residual_row, int64_t D) const {
    for (int64_t d = 0; d < D; ++d) {
      float v = acc[d];
      if (bias) v += bias[d];
      if (residual_row) v += residual_row[d];
      out[d] = relu ? std::max(v, 0.0f) : v;
    }
  }
};

at::Tensor neighbour_conv_impl(const at::Tensor& src, const at::Tensor& neighbours, const at::Tensor& weight,
                               const Epilogue& epilogue, const char* what) {
  check_inputs(src, neighbours, what);
  const int64_t N = src.size(0), C = src.size(1), M = neighbours.size(0), K = neighbours.size(1);
  check_weight(weight, K, C, what);
  const int64_t D = weight.size(2), Dp = padded(D);
  auto out = at::empty({M, D}, src.options());
  if (M == 0) return out;
  const std::vector<float> w = pad_weight(weight, Dp);
  const float* feats = src.data_ptr<float>();
  const int64_t* nbr = neighbours.data_ptr<int64_t>();
  float* dst = out.data_ptr<float>();
  const int64_t blocks = (M + kBlockRows - 1) / kBlockRows;
  at::parallel_for(0, blocks, 1, [&](int64_t begin, int64_t end) {
    std::vector<float> acc(static_cast<size_t>(kBlockRows * Dp));
    const float* srcs[kBlockRows];
    float* dsts[kBlockRows];
    for (int64_t block = begin; block < end; ++block) {
      const int64_t j0 = block * kBlockRows, rows = std::min(kBlockRows, M - j0);
      std::fill(acc.begin(), acc.end(), 0.0f);
      for (int64_t k = 0; k < K; ++k) {
        const int count = list_present(nbr, j0, rows, K, k, N, feats, C, acc.data(), Dp, srcs, dsts);
        const float* wk = w.data() + k * C * Dp;
        for (int p = 0; p < count; p += kMaxRows)
          rows_times_weight_any(std::min(kMaxRows, count - p), srcs + p, wk, C, Dp, dsts + p);
      }
      for (int64_t r = 0; r < rows; ++r) {
        const float* res = epilogue.residual ? epilogue.residual + (j0 + r) * D : nullptr;
        epilogue.write(dst + (j0 + r) * D, acc.data() + r * Dp, res, D);
      }
    }
  });
  return out;
}

Epilogue make_epilogue(const c10::optional<at::Tensor>& bias, const c10::optional<at::Tensor>& residual, bool relu,
                       int64_t M, int64_t D, const char* what) {
  Epilogue e;
  e.relu = relu;
  if (bias.has_value()) {
    TORCH_CHECK(bias->scalar_type() == at::kFloat && bias->is_contiguous() && bias->dim() == 1 && bias->size(0) == D,
                what, ": a contiguous float32 bias of ", D, " values expected");
    e.bias = bias->data_ptr<float>();
  }
  if (residual.has_value()) {
    TORCH_CHECK(residual->scalar_type() == at::kFloat && residual->is_contiguous() && residual->dim() == 2 &&
                    residual->size(0) == M && residual->size(1) == D,
                what, ": a contiguous float32 residual (", M, ", ", D, ") expected");
    e.residual = residual->data_ptr<float>();
  }
  return e;
}

}  // namespace

at::Tensor neighbour_conv(at::Tensor src, at::Tensor neighbours, at::Tensor weight) {
  return neighbour_conv_impl(src, neighbours, weight, Epilogue{}, "neighbour_conv");
}

at::Tensor neighbour_conv_fused(at::Tensor src, at::Tensor neighbours, at::Tensor weight,
                                c10::optional<at::Tensor> bias, c10::optional<at::Tensor> residual, bool relu) {
  const Epilogue e = make_epilogue(bias, residual, relu, neighbours.size(0), weight.size(2), "neighbour_conv_fused");
  return neighbour_conv_impl(src, neighbours, weight, e, "neighbour_conv_fused");
}

at::Tensor scatter_conv_fused(at::Tensor src, at::Tensor neighbours, at::Tensor weight, int64_t num_out,
                              c10::optional<at::Tensor> bias, bool relu) {
  check_inputs(src, neighbours, "scatter_conv");
  const int64_t M = src.size(0), C = src.size(1), K = neighbours.size(1);
  TORCH_CHECK(neighbours.size(0) == M, "scatter_conv: one neighbour row per source row expected");
  check_weight(weight, K, C, "scatter_conv");
  const int64_t D = weight.size(2), Dp = padded(D);
  const Epilogue epilogue = make_epilogue(bias, c10::nullopt, relu, num_out, D, "scatter_conv");
  auto out = at::empty({num_out, D}, src.options());
  float* dst = out.data_ptr<float>();
  {  // rows no pair reaches: the epilogue of zero
    std::vector<float> zero(static_cast<size_t>(D), 0.0f);
    for (int64_t row = 0; row < num_out; ++row) epilogue.write(dst + row * D, zero.data(), nullptr, D);
  }
  if (M == 0 || num_out == 0) return out;
  const std::vector<float> w = pad_weight(weight, Dp);
  const float* feats = src.data_ptr<float>();
  const int64_t* nbr = neighbours.data_ptr<int64_t>();
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
          for (int r = 0; r < group; ++r) epilogue.write(dst + targets[p + r] * D, dsts[r], nullptr, D);
        }
      }
    }
  });
  return out;
}

at::Tensor scatter_conv(at::Tensor src, at::Tensor neighbours, at::Tensor weight, int64_t num_out) {
  return scatter_conv_fused(src, neighbours, weight, num_out, c10::nullopt, false);
}

at::Tensor neighbour_weight_grad(at::Tensor src, at::Tensor neighbours, at::Tensor dense) {
  check_inputs(src, neighbours, "neighbour_weight_grad");
  TORCH_CHECK(dense.scalar_type() == at::kFloat && dense.is_contiguous() && dense.dim() == 2 &&
                  dense.size(0) == neighbours.size(0),
              "neighbour_weight_grad: contiguous float32 (M, B) rows expected");
  const int64_t N = src.size(0), A = src.size(1), M = neighbours.size(0), K = neighbours.size(1);
  const int64_t B = dense.size(1), Bp = padded(B);
  const float* feats = src.data_ptr<float>();
  const int64_t* nbr = neighbours.data_ptr<int64_t>();
  const float* rows_b = dense.data_ptr<float>();
  const int64_t blocks = (M + kBlockRows - 1) / kBlockRows;
  const int threads = std::max<int>(1, at::get_num_threads());
  std::vector<std::vector<float>> partial(static_cast<size_t>(threads));
  if (M > 0) {
    at::parallel_for(0, blocks, 1, [&](int64_t begin, int64_t end) {
      std::vector<float>& grad = partial[static_cast<size_t>(at::get_thread_num())];
      if (grad.empty()) grad.assign(static_cast<size_t>(K * A * Bp), 0.0f);
      std::vector<float> dense_block(static_cast<size_t>(kBlockRows * Bp), 0.0f);
      const float* srcs[kBlockRows];
      float* denses[kBlockRows];
      for (int64_t block = begin; block < end; ++block) {
        const int64_t j0 = block * kBlockRows, rows = std::min(kBlockRows, M - j0);
        for (int64_t r = 0; r < rows; ++r) {
          std::memcpy(dense_block.data() + r * Bp, rows_b + (j0 + r) * B, B * sizeof(float));
        }
        for (int64_t k = 0; k < K; ++k) {
          const int count = list_present(nbr, j0, rows, K, k, N, feats, A, dense_block.data(), Bp, srcs, denses);
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

at::Tensor grid_neighbours(at::Tensor grid, at::Tensor flat, at::Tensor delta) {
  TORCH_CHECK(grid.device().is_cpu() && flat.device().is_cpu() && delta.device().is_cpu(),
              "grid_neighbours: CPU tensors expected");
  TORCH_CHECK(grid.scalar_type() == at::kInt && grid.is_contiguous() && grid.dim() == 1,
              "grid_neighbours: a contiguous int32 grid expected");
  TORCH_CHECK(flat.scalar_type() == at::kLong && delta.scalar_type() == at::kLong && flat.dim() == 1 &&
                  delta.dim() == 1 && flat.is_contiguous() && delta.is_contiguous(),
              "grid_neighbours: contiguous int64 cells and offsets expected");
  const int64_t M = flat.size(0), K = delta.size(0), cells = grid.size(0);
  auto out = at::empty({M, K}, flat.options());
  const int32_t* g = grid.data_ptr<int32_t>();
  const int64_t* f = flat.data_ptr<int64_t>();
  const int64_t* d = delta.data_ptr<int64_t>();
  int64_t* o = out.data_ptr<int64_t>();
  if (M == 0 || K == 0) return out;
  const auto [f_lo, f_hi] = std::minmax_element(f, f + M);
  const auto [d_lo, d_hi] = std::minmax_element(d, d + K);
  TORCH_CHECK(*f_lo + *d_lo >= 0 && *f_hi + *d_hi < cells, "grid_neighbours: a cell outside the grid");
  at::parallel_for(0, M, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t j = begin; j < end; ++j)
      for (int64_t k = 0; k < K; ++k) o[j * K + k] = g[f[j] + d[k]];
  });
  return out;
}

namespace radarseg {
std::vector<at::Tensor> pyramid_maps(at::Tensor coords, int64_t levels, int64_t max_cells);  // kernel_maps.cpp
}  // namespace radarseg

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("neighbour_conv", &neighbour_conv, "out[j] = sum_k src[nbr[j, k]] @ weight[k]");
  m.def("scatter_conv", &scatter_conv, "out[nbr[j, k]] = src[j] @ weight[k]");
  m.def("neighbour_conv_fused", &neighbour_conv_fused,
        "max(sum_k src[nbr[j, k]] @ weight[k] + bias + residual[j], 0), each part optional");
  m.def("scatter_conv_fused", &scatter_conv_fused, "out[nbr[j, k]] = max(src[j] @ weight[k] + bias, 0)");
  m.def("neighbour_weight_grad", &neighbour_weight_grad, "grad[k] = sum_j src[nbr[j, k]]^T dense[j]");
  m.def("grid_neighbours", &grid_neighbours, "out[j, k] = grid[flat[j] + delta[k]] as int64");
  m.def("pyramid_maps", &radarseg::pyramid_maps,
        "coordinates, 3^3 and 2^3 kernel maps and pair counts of every level of a voxel pyramid");
}
