// Compiled CPU kernels of int8 sparse convolutions (models/sparse/int8.py builds and loads this file).
//
// Activations are unsigned 8-bit (N, C) rows (C a multiple of 4), weights signed 8-bit, accumulated exactly in
// int32 over a kernel map's neighbour table (as sparse_conv.cpp's float kernels: `neighbours[j, k]` a row of the
// gathered side, `src.size(0)` where missing):
//
//   neighbour_conv_int8(src (N, C) u8, neighbours (M, K), packed weight, ...) -> (M, D)
//       acc[j] = sum_k (src[neighbours[j, k]] - zero_point) . weight[k]      (submanifold / strided)
//   scatter_conv_int8(src (M, C) u8, neighbours (M, K), packed weight, num_out, ...) -> (num_out, D)
//       acc[neighbours[j, k]] = (src[j] - zero_point) . weight[k]            (transposed; each output once)
//
// then the epilogue, in the loop that writes the rows: v = acc * scale[d] + bias[d] + residual[j, d] (a uint8
// residual times its per-channel scale, or a float one), ReLU, and either float32 out or requantised to uint8
// (q = clamp(rint(v / out_scale[d]), 0, 255), a scale per output channel).
//
// Micro-kernels (micro_kernel.h's, as the float kernels': R rows x columns of int32 accumulators, the weight chunk
// kept in registers over the rows), this build's multiply-add in `Int8Ops`:
// - AVX-512 VNNI: `vpdpbusd` multiplies 4 unsigned activation bytes by 4 signed weight bytes per int32 lane and
//   adds them exactly (no intermediate saturation); 8 rows x up to 3 vectors of 16 lanes (+ one 8-lane vector
//   through AVX512VL). Weights packed (K, C/4, Dp, 4) int8.
// - AVX-VNNI (no AVX-512): the same `vpdpbusd` on 8-lane vectors, 4 rows x up to 3 vectors; VNNI layout.
// - AVX2: `vpmaddwd` on activations and weights widened to int16: pairs of u8 x s8 products summed into int32,
//   exact (|255 * 127 * 2| fits int16 x int16 -> int32; `vpmaddubsw` would saturate its int16 pair sums);
//   4 rows x up to 3 vectors of 8 lanes. Weights packed (K, C/2, Dp, 2) int16.
// - anything else: plain C++ over the VNNI layout.
// Output columns are padded to a multiple of 8 inside the kernels; blocks of 64 output rows run in parallel.

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/csrc/utils/pybind.h>

#include <immintrin.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "micro_kernel.h"

namespace {

using namespace radarseg_kernels;

constexpr int64_t kMaxColumns = 4096;  // output channels of one layer, at most

#if defined(__AVX512F__) && defined(__AVX512VNNI__) && defined(__AVX512VL__)
#define RADARSEG_INT8_VNNI512 1
constexpr const char* kPath = "avx512-vnni";
#elif defined(__AVXVNNI__)
#define RADARSEG_INT8_AVXVNNI 1  // AVX-VNNI without AVX-512 (e.g. Alder Lake): vpdpbusd on 8-lane vectors
constexpr const char* kPath = "avx-vnni";
#elif defined(__AVX2__)
#define RADARSEG_INT8_AVX2 1
constexpr const char* kPath = "avx2";
#else
constexpr const char* kPath = "scalar";
#endif

inline int32_t load_u32(const uint8_t* p) {
  int32_t v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}

// The micro-kernel's types and multiply-add on this build's path (micro_kernel.h; the scalar path has none).
struct Int8Ops {
  using in_t = uint8_t;
  using acc_t = int32_t;
  static constexpr int kMaxChunkVectors = 3;
  // 24 columns as a chunk of 16, then one of 8 (the segmenter's 24-wide int8 layers measured faster so than as one)
  static constexpr bool kHalfJoinsWide = false;
#if defined(RADARSEG_INT8_AVX2)
  using weight_t = int16_t;
  static constexpr int64_t kGroup = 2;  // input channels per packed weight group
  // two activation bytes as an int16 pair, zero-extended (the bytes are unsigned)
  static inline int32_t group(const uint8_t* p) {
    return static_cast<int32_t>(p[0]) | (static_cast<int32_t>(p[1]) << 16);
  }
#else
  using weight_t = int8_t;
  static constexpr int64_t kGroup = 4;
  static inline int32_t group(const uint8_t* p) { return load_u32(p); }  // four activation bytes, one lane
#endif
  // Vectors of int32 lanes (the sums'; a weight vector's lanes are 4-byte columns too), cast to the intrinsics'
  // types in `madd` only: accumulators of __m512i (64-bit lanes) make GCC copy each one around every vpdpbusd in
  // the loop, and spill them once they fill the registers.
#if defined(RADARSEG_INT8_VNNI512)
  typedef int32_t wide_v __attribute__((vector_size(64)));
  typedef int32_t half_v __attribute__((vector_size(32)));
  static constexpr int64_t kWide = 16;
  static constexpr int kMaxRows = 8;
  static inline wide_v madd(wide_v acc, int32_t x, wide_v w) {
    return (wide_v)_mm512_dpbusd_epi32((__m512i)acc, _mm512_set1_epi32(x), (__m512i)w);
  }
  static inline half_v madd(half_v acc, int32_t x, half_v w) {
    return (half_v)_mm256_dpbusd_epi32((__m256i)acc, _mm256_set1_epi32(x), (__m256i)w);
  }
#else
  typedef int32_t wide_v __attribute__((vector_size(32)));
  typedef wide_v half_v;
  static constexpr int64_t kWide = 8;
  static constexpr int kMaxRows = 4;
#endif
#if defined(RADARSEG_INT8_AVXVNNI)
  static inline wide_v madd(wide_v acc, int32_t x, wide_v w) {
    return (wide_v)_mm256_dpbusd_avx_epi32((__m256i)acc, _mm256_set1_epi32(x), (__m256i)w);
  }
#elif defined(RADARSEG_INT8_AVX2)
  static inline wide_v madd(wide_v acc, int32_t x, wide_v w) {
    return (wide_v)_mm256_add_epi32((__m256i)acc, _mm256_madd_epi16(_mm256_set1_epi32(x), (__m256i)w));
  }
#endif
};

typedef Int8Ops::weight_t packed_t;
constexpr int kMaxRows = Int8Ops::kMaxRows;
constexpr int64_t kGroup = Int8Ops::kGroup;

// acc[r][0:Dp] += src[r][0:C] . w for `rows` <= kMaxRows rows; w is packed (C / kGroup, Dp, kGroup).
inline void rows_times_weight_any(int rows, const uint8_t* const* src, const packed_t* w, int64_t C, int64_t Dp,
                                  int32_t* const* dst) {
#if defined(RADARSEG_INT8_VNNI512) || defined(RADARSEG_INT8_AVXVNNI) || defined(RADARSEG_INT8_AVX2)
  rows_times_weight<Int8Ops>(rows, src, w, C, Dp, dst);
#else
  for (int r = 0; r < rows; ++r)
    for (int64_t c = 0; c < C; ++c) {
      const int32_t x = src[r][c];
      const packed_t* wc = w + c / kGroup * Dp * kGroup + c % kGroup;
      for (int64_t d = 0; d < Dp; ++d) dst[r][d] += x * static_cast<int32_t>(wc[d * kGroup]);
    }
#endif
}

// The epilogue of a layer (see the file's comment); `zero_point` with `weight_sums` (K, D): the input offset.
struct Epilogue {
  const float* scale = nullptr;  // (D,) acc -> float
  const float* bias = nullptr;   // (D,)
  const uint8_t* residual_u8 = nullptr;
  const float* residual_scale = nullptr;  // (D,)
  const float* residual_f32 = nullptr;
  bool relu = false;
  std::vector<float> inverse;  // (D,) 1 / out_scale: uint8 out; empty: float out

  // Each step a plain loop over the row's columns (vectorised by the compiler), the uint8 store explicitly.
  inline void write(void* out, int64_t row, const int32_t* acc, int64_t D) const {
    float v[kMaxColumns];
    for (int64_t d = 0; d < D; ++d) v[d] = static_cast<float>(acc[d]) * scale[d];
    if (bias)
      for (int64_t d = 0; d < D; ++d) v[d] += bias[d];
    if (residual_u8) {
      const uint8_t* res = residual_u8 + row * D;
      for (int64_t d = 0; d < D; ++d) v[d] += static_cast<float>(res[d]) * residual_scale[d];
    }
    if (residual_f32) {
      const float* res = residual_f32 + row * D;
      for (int64_t d = 0; d < D; ++d) v[d] += res[d];
    }
    if (relu)
      for (int64_t d = 0; d < D; ++d) v[d] = std::max(v[d], 0.0f);
    if (!inverse.empty()) {
      uint8_t* dst = static_cast<uint8_t*>(out) + row * D;
      int64_t d = 0;
#if defined(__AVX2__)
      // 8 columns at a time (a uint8 loop left to the compiler runs scalar below 64 columns): scale, clamp to
      // [0, 255], round to nearest even (the default MXCSR mode), pack to bytes
      const __m256 lo = _mm256_setzero_ps(), hi = _mm256_set1_ps(255.0f);
      for (; d + 8 <= D; d += 8) {
        const __m256 inv = _mm256_loadu_ps(inverse.data() + d);
        const __m256 x = _mm256_min_ps(_mm256_max_ps(_mm256_mul_ps(_mm256_loadu_ps(v + d), inv), lo), hi);
        const __m256i i = _mm256_cvtps_epi32(x);
        const __m128i words = _mm_packus_epi32(_mm256_castsi256_si128(i), _mm256_extracti128_si256(i, 1));
        _mm_storel_epi64(reinterpret_cast<__m128i*>(dst + d), _mm_packus_epi16(words, words));
      }
#endif
      for (; d < D; ++d)
        dst[d] = static_cast<uint8_t>(std::nearbyint(std::min(std::max(v[d] * inverse[d], 0.0f), 255.0f)));
    } else {
      std::memcpy(static_cast<float*>(out) + row * D, v, D * sizeof(float));
    }
  }
};

struct Layer {
  const uint8_t* feats;
  int64_t N, C, M, K, D, Dp;
  const void* nbr;  // int64 or int32 (M, K)
  bool nbr32;
  const packed_t* w;
  int64_t zero_point;
  const int32_t* weight_sums;  // (K, D) or null
  // the map as compact pairs (compact_pairs): each (block, offset)'s present pairs, no missing slots to skip
  const int32_t* pair_offsets = nullptr;  // (blocks * K + 1,)
  const uint8_t* pair_rows = nullptr;     // (P,) output row within its block
  const int32_t* pair_nbrs = nullptr;     // (P,) input row

  inline int64_t neighbour(int64_t i) const {
    return nbr32 ? static_cast<const int32_t*>(nbr)[i] : static_cast<const int64_t*>(nbr)[i];
  }
};

Layer make_layer(const at::Tensor& src, const at::Tensor& neighbours, const at::Tensor& packed, int64_t D,
                 int64_t zero_point, const c10::optional<at::Tensor>& weight_sums, const char* what) {
  TORCH_CHECK(src.device().is_cpu() && neighbours.device().is_cpu() && packed.device().is_cpu(), what,
              ": CPU tensors expected");
  TORCH_CHECK(src.scalar_type() == at::kByte && src.dim() == 2 && src.is_contiguous(), what,
              ": contiguous uint8 features (N, C) expected, got ", src.scalar_type());
  TORCH_CHECK(src.size(1) % 4 == 0, what, ": input channels must be a multiple of 4, got ", src.size(1));
  TORCH_CHECK((neighbours.scalar_type() == at::kLong || neighbours.scalar_type() == at::kInt) &&
                  neighbours.dim() == 2 && neighbours.is_contiguous(),
              what, ": contiguous int64 or int32 neighbours (M, K) expected");
  const int64_t K = neighbours.size(1), C = src.size(1), Dp = padded(D);
  TORCH_CHECK(packed.is_contiguous() && packed.element_size() == sizeof(packed_t) && packed.dim() == 4 &&
                  packed.size(0) == K && packed.size(1) == C / kGroup && packed.size(2) == Dp &&
                  packed.size(3) == kGroup,
              what, ": a weight packed by this build's pack_weight for K = ", K, ", C = ", C, ", D = ", D,
              " expected, got ", packed.sizes());
  TORCH_CHECK(zero_point >= 0 && zero_point <= 255, what, ": zero point must be in [0, 255]");
  const int32_t* sums = nullptr;
  if (zero_point != 0) {
    TORCH_CHECK(weight_sums.has_value() && weight_sums->scalar_type() == at::kInt && weight_sums->is_contiguous() &&
                    weight_sums->dim() == 2 && weight_sums->size(0) == K && weight_sums->size(1) == D,
                what, ": a non-zero zero point needs weight_sums (K, D) int32");
    sums = weight_sums->data_ptr<int32_t>();
  }
  return Layer{src.data_ptr<uint8_t>(), src.size(0), C, neighbours.size(0), K, D, Dp,
               neighbours.data_ptr(), neighbours.scalar_type() == at::kInt, reinterpret_cast<const packed_t*>(packed.data_ptr()), zero_point,
               sums};
}

Epilogue make_epilogue(const at::Tensor& scale, const c10::optional<at::Tensor>& bias,
                       const c10::optional<at::Tensor>& residual, const c10::optional<at::Tensor>& residual_scale,
                       bool relu, const c10::optional<at::Tensor>& out_scale, int64_t rows, int64_t D,
                       const char* what) {
  Epilogue e;
  auto check_vector = [&](const at::Tensor& t, const char* name) {
    TORCH_CHECK(t.scalar_type() == at::kFloat && t.is_contiguous() && t.dim() == 1 && t.size(0) == D, what, ": ",
                name, " must be a contiguous float32 vector of ", D, " values");
  };
  check_vector(scale, "scale");
  e.scale = scale.data_ptr<float>();
  if (bias.has_value()) {
    check_vector(*bias, "bias");
    e.bias = bias->data_ptr<float>();
  }
  if (residual.has_value()) {
    TORCH_CHECK(residual->is_contiguous() && residual->dim() == 2 && residual->size(0) == rows &&
                    residual->size(1) == D,
                what, ": a contiguous residual (", rows, ", ", D, ") expected");
    if (residual->scalar_type() == at::kByte) {
      TORCH_CHECK(residual_scale.has_value(), what, ": a uint8 residual needs its residual_scale");
      check_vector(*residual_scale, "residual_scale");
      e.residual_u8 = residual->data_ptr<uint8_t>();
      e.residual_scale = residual_scale->data_ptr<float>();
    } else {
      TORCH_CHECK(residual->scalar_type() == at::kFloat, what, ": a uint8 or float32 residual expected");
      e.residual_f32 = residual->data_ptr<float>();
    }
  }
  TORCH_CHECK(D <= kMaxColumns, what, ": at most ", kMaxColumns, " output channels");
  if (out_scale.has_value()) {
    check_vector(*out_scale, "out_scale");
    const float* o = out_scale->data_ptr<float>();
    for (int64_t d = 0; d < D; ++d) {
      TORCH_CHECK(std::isfinite(o[d]) && o[d] > 0.0f, what, ": out_scale must be finite and > 0");
      e.inverse.push_back(1.0f / o[d]);
    }
  }
  e.relu = relu;
  return e;
}

at::Tensor make_output(int64_t rows, int64_t D, const Epilogue& e) {
  return at::empty({rows, D}, at::TensorOptions().dtype(e.inverse.empty() ? at::kFloat : at::kByte));
}

// `acc` rows (block buffer, row width Dp) of an output block: each row's int32 sums over its present neighbours.
void neighbour_block(const Layer& L, int64_t j0, int64_t rows, int32_t* acc) {
  const uint8_t* srcs[kBlockRows];
  int32_t* dsts[kBlockRows];
  std::fill(acc, acc + kBlockRows * L.Dp, 0);
  for (int64_t k = 0; k < L.K; ++k) {
    int count = 0;
    if (L.pair_offsets) {
      const int64_t slot = j0 / kBlockRows * L.K + k, begin = L.pair_offsets[slot];
      count = static_cast<int>(L.pair_offsets[slot + 1] - begin);
      for (int p = 0; p < count; ++p) {
        srcs[p] = L.feats + static_cast<int64_t>(L.pair_nbrs[begin + p]) * L.C;
        dsts[p] = acc + static_cast<int64_t>(L.pair_rows[begin + p]) * L.Dp;
      }
    }
    for (int64_t r = 0; r < (L.pair_offsets ? 0 : rows); ++r) {  // branch-free listing of the rows with a neighbour at offset k
      const int64_t n = L.neighbour((j0 + r) * L.K + k);
      srcs[count] = L.feats + (n < L.N ? n : 0) * L.C;
      dsts[count] = acc + r * L.Dp;
      count += n < L.N;
    }
    const packed_t* wk = L.w + k * (L.C / kGroup) * L.Dp * kGroup;
    for (int p = 0; p < count; p += kMaxRows)
      rows_times_weight_any(std::min(kMaxRows, count - p), srcs + p, wk, L.C, L.Dp, dsts + p);
    if (L.weight_sums) {
      const int32_t* sums = L.weight_sums + k * L.D;
      for (int p = 0; p < count; ++p)
        for (int64_t d = 0; d < L.D; ++d) dsts[p][d] -= static_cast<int32_t>(L.zero_point) * sums[d];
    }
  }
}

// Each block of output rows' int32 sums (neighbour_block), blocks in parallel, then `write(row, sums)` for each of
// the block's rows (`sums`: the row's D values).
template <typename F>
void gather_rows(const Layer& L, F&& write) {
  const int64_t blocks = (L.M + kBlockRows - 1) / kBlockRows;
  at::parallel_for(0, blocks, 1, [&](int64_t begin, int64_t end) {
    std::vector<int32_t> acc(static_cast<size_t>(kBlockRows * L.Dp));
    for (int64_t block = begin; block < end; ++block) {
      const int64_t j0 = block * kBlockRows, rows = std::min(kBlockRows, L.M - j0);
      neighbour_block(L, j0, rows, acc.data());
      for (int64_t r = 0; r < rows; ++r) write(j0 + r, acc.data() + r * L.Dp);
    }
  });
}

}  // namespace

at::Tensor neighbour_conv_int8_raw(at::Tensor src, at::Tensor neighbours, at::Tensor packed, int64_t D,
                                   int64_t zero_point, c10::optional<at::Tensor> weight_sums) {
  const Layer L = make_layer(src, neighbours, packed, D, zero_point, weight_sums, "neighbour_conv_int8_raw");
  auto out = at::empty({L.M, D}, at::TensorOptions().dtype(at::kInt));
  int32_t* dst = out.data_ptr<int32_t>();
  gather_rows(L, [&](int64_t row, const int32_t* sums) { std::memcpy(dst + row * D, sums, D * sizeof(int32_t)); });
  return out;
}

at::Tensor neighbour_conv_int8(at::Tensor src, at::Tensor neighbours, at::Tensor packed, int64_t zero_point,
                               c10::optional<at::Tensor> weight_sums, at::Tensor scale, c10::optional<at::Tensor> bias,
                               c10::optional<at::Tensor> residual, c10::optional<at::Tensor> residual_scale, bool relu,
                               c10::optional<at::Tensor> out_scale) {
  const int64_t D = scale.size(0);
  const Layer L = make_layer(src, neighbours, packed, D, zero_point, weight_sums, "neighbour_conv_int8");
  const Epilogue e = make_epilogue(scale, bias, residual, residual_scale, relu, out_scale, L.M, D,
                                   "neighbour_conv_int8");
  auto out = make_output(L.M, D, e);
  void* dst = out.data_ptr();
  gather_rows(L, [&](int64_t row, const int32_t* sums) { e.write(dst, row, sums, D); });
  return out;
}

at::Tensor scatter_conv_int8(at::Tensor src, at::Tensor neighbours, at::Tensor packed, int64_t num_out,
                             int64_t zero_point, c10::optional<at::Tensor> weight_sums, at::Tensor scale,
                             c10::optional<at::Tensor> bias, bool relu, c10::optional<at::Tensor> out_scale) {
  const int64_t D = scale.size(0);
  const Layer L = make_layer(src, neighbours, packed, D, zero_point, weight_sums, "scatter_conv_int8");
  TORCH_CHECK(L.M == L.N, "scatter_conv_int8: one neighbour row per source row expected");
  TORCH_CHECK(num_out >= 0, "scatter_conv_int8: num_out must be >= 0");
  const Epilogue e = make_epilogue(scale, bias, c10::nullopt, c10::nullopt, relu, out_scale, num_out, D,
                                   "scatter_conv_int8");
  auto out = make_output(num_out, D, e);
  void* dst = out.data_ptr();
  {  // rows no pair reaches: the epilogue of zero
    std::vector<int32_t> zero(static_cast<size_t>(D), 0);
    for (int64_t row = 0; row < num_out; ++row) e.write(dst, row, zero.data(), D);
  }
  if (L.M == 0 || num_out == 0) return out;
  const int64_t blocks = (L.M + kBlockRows - 1) / kBlockRows;
  at::parallel_for(0, blocks, 1, [&](int64_t begin, int64_t end) {
    std::vector<int32_t> tmp(static_cast<size_t>(kMaxRows * L.Dp));
    const uint8_t* srcs[kBlockRows];
    int64_t targets[kBlockRows];
    int32_t* dsts[kMaxRows];
    for (int r = 0; r < kMaxRows; ++r) dsts[r] = tmp.data() + r * L.Dp;
    for (int64_t block = begin; block < end; ++block) {
      const int64_t j0 = block * kBlockRows, rows = std::min(kBlockRows, L.M - j0);
      for (int64_t k = 0; k < L.K; ++k) {
        int count = 0;
        for (int64_t r = 0; r < rows; ++r) {
          const int64_t n = L.neighbour((j0 + r) * L.K + k);
          srcs[count] = L.feats + (j0 + r) * L.C;
          targets[count] = n;
          count += n >= 0 && n < num_out;
        }
        const packed_t* wk = L.w + k * (L.C / kGroup) * L.Dp * kGroup;
        for (int p = 0; p < count; p += kMaxRows) {
          const int group = std::min(kMaxRows, count - p);
          std::fill(tmp.begin(), tmp.end(), 0);
          rows_times_weight_any(group, srcs + p, wk, L.C, L.Dp, dsts);
          for (int r = 0; r < group; ++r) {
            if (L.weight_sums)
              for (int64_t d = 0; d < D; ++d)
                dsts[r][d] -= static_cast<int32_t>(L.zero_point) * L.weight_sums[k * D + d];
            e.write(dst, targets[p + r], dsts[r], D);  // each output row has exactly one pair: plain stores
          }
        }
      }
    }
  });
  return out;
}

// A neighbour table (M, K) as compact pairs, in the order the gather kernels visit them: for each block of
// kBlockRows output rows and each offset k, the rows of the block with a neighbour at k and that neighbour.
std::vector<at::Tensor> compact_pairs(at::Tensor neighbours, int64_t num_in) {
  TORCH_CHECK(neighbours.device().is_cpu() && (neighbours.scalar_type() == at::kLong ||
                                              neighbours.scalar_type() == at::kInt) &&
                  neighbours.dim() == 2 && neighbours.is_contiguous(),
              "compact_pairs: contiguous int64 or int32 neighbours (M, K) expected");
  TORCH_CHECK(num_in >= 0 && num_in < (int64_t{1} << 31), "compact_pairs: num_in out of range");
  const int64_t M = neighbours.size(0), K = neighbours.size(1), blocks = (M + kBlockRows - 1) / kBlockRows;
  const bool is32 = neighbours.scalar_type() == at::kInt;
  const void* data = neighbours.data_ptr();
  auto at_ = [&](int64_t i) -> int64_t {
    return is32 ? static_cast<const int32_t*>(data)[i] : static_cast<const int64_t*>(data)[i];
  };
  TORCH_CHECK(M * K < (int64_t{1} << 31), "compact_pairs: too many slots");
  auto offsets = at::empty({blocks * K + 1}, at::TensorOptions().dtype(at::kInt));
  auto rows_out = at::empty({M * K}, at::TensorOptions().dtype(at::kByte));  // narrowed to the pairs below
  auto nbrs_out = at::empty({M * K}, at::TensorOptions().dtype(at::kInt));
  int32_t* o = offsets.data_ptr<int32_t>();
  uint8_t* ro = rows_out.data_ptr<uint8_t>();
  int32_t* no = nbrs_out.data_ptr<int32_t>();
  int64_t p = 0;
  o[0] = 0;
  for (int64_t b = 0; b < blocks; ++b) {
    const int64_t j0 = b * kBlockRows, rows = std::min(kBlockRows, M - j0);
    for (int64_t k = 0; k < K; ++k) {
      for (int64_t r = 0; r < rows; ++r) {  // branch-free: written always, kept where present
        const int64_t n = at_((j0 + r) * K + k);
        ro[p] = static_cast<uint8_t>(r);
        no[p] = static_cast<int32_t>(n);
        p += n >= 0 && n < num_in;
      }
      o[b * K + k + 1] = static_cast<int32_t>(p);
    }
  }
  rows_out = rows_out.narrow(0, 0, p);
  nbrs_out = nbrs_out.narrow(0, 0, p);
  return {offsets, rows_out, nbrs_out};
}

at::Tensor neighbour_conv_int8_pairs(at::Tensor src, at::Tensor offsets, at::Tensor pair_rows, at::Tensor pair_nbrs,
                                     int64_t M, int64_t K, at::Tensor packed, int64_t zero_point,
                                     c10::optional<at::Tensor> weight_sums, at::Tensor scale,
                                     c10::optional<at::Tensor> bias, c10::optional<at::Tensor> residual,
                                     c10::optional<at::Tensor> residual_scale, bool relu,
                                     c10::optional<at::Tensor> out_scale) {
  const char* what = "neighbour_conv_int8_pairs";
  const int64_t D = scale.size(0), blocks = (M + kBlockRows - 1) / kBlockRows;
  TORCH_CHECK(M >= 0 && K >= 1, what, ": M >= 0 and K >= 1 expected");
  TORCH_CHECK(offsets.scalar_type() == at::kInt && offsets.is_contiguous() && offsets.dim() == 1 &&
                  offsets.size(0) == blocks * K + 1,
              what, ": compact_pairs' offsets for M = ", M, ", K = ", K, " expected");
  TORCH_CHECK(pair_rows.scalar_type() == at::kByte && pair_nbrs.scalar_type() == at::kInt &&
                  pair_rows.is_contiguous() && pair_nbrs.is_contiguous() && pair_rows.dim() == 1 &&
                  pair_nbrs.dim() == 1 && pair_rows.size(0) == pair_nbrs.size(0) &&
                  offsets[-1].item<int32_t>() == pair_rows.size(0),
              what, ": compact_pairs' rows (uint8) and neighbours (int32) expected");
  // a table's checks on a (0, K) stand-in, then its M rows
  const at::Tensor no_rows = at::empty({0, K}, at::TensorOptions().dtype(at::kInt));
  Layer L = make_layer(src, no_rows, packed, D, zero_point, weight_sums, what);
  L.M = M;
  L.nbr = nullptr;
  if (pair_nbrs.numel() > 0) {
    const auto [lo, hi] = std::minmax_element(pair_nbrs.data_ptr<int32_t>(),
                                              pair_nbrs.data_ptr<int32_t>() + pair_nbrs.numel());
    TORCH_CHECK(*lo >= 0 && *hi < L.N, what, ": a neighbour outside the input rows");
  }
  L.pair_offsets = offsets.data_ptr<int32_t>();
  L.pair_rows = pair_rows.data_ptr<uint8_t>();
  L.pair_nbrs = pair_nbrs.data_ptr<int32_t>();
  const Epilogue e = make_epilogue(scale, bias, residual, residual_scale, relu, out_scale, M, D, what);
  auto out = make_output(M, D, e);
  void* dst = out.data_ptr();
  gather_rows(L, [&](int64_t row, const int32_t* sums) { e.write(dst, row, sums, D); });
  return out;
}

// (K, C, D) int8 -> this build's packed layout (K, C / kGroup, Dp, kGroup), zero columns past D.
at::Tensor pack_weight(at::Tensor weight) {
  TORCH_CHECK(weight.scalar_type() == at::kChar && weight.dim() == 3 && weight.is_contiguous(),
              "pack_weight: a contiguous int8 weight (K, C_in, C_out) expected");
  const int64_t K = weight.size(0), C = weight.size(1), D = weight.size(2), Dp = padded(D);
  TORCH_CHECK(C % 4 == 0, "pack_weight: input channels must be a multiple of 4, got ", C);
  const auto dtype = sizeof(packed_t) == 1 ? at::kChar : at::kShort;
  auto out = at::zeros({K, C / kGroup, Dp, kGroup}, at::TensorOptions().dtype(dtype));
  const int8_t* w = weight.data_ptr<int8_t>();
  packed_t* p = reinterpret_cast<packed_t*>(out.data_ptr());
  for (int64_t k = 0; k < K; ++k)
    for (int64_t c = 0; c < C; ++c)
      for (int64_t d = 0; d < D; ++d)
        p[((k * (C / kGroup) + c / kGroup) * Dp + d) * kGroup + c % kGroup] = w[(k * C + c) * D + d];
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.attr("path") = kPath;
  m.def("pack_weight", &pack_weight, "(K, C, D) int8 weight in this build's packed layout");
  m.def("neighbour_conv_int8_raw", &neighbour_conv_int8_raw,
        "int32 acc[j] = sum_k (src[nbr[j, k]] - zero_point) . weight[k]");
  m.def("neighbour_conv_int8", &neighbour_conv_int8,
        "the int8 gather convolution with its epilogue (scale, bias, residual, ReLU, float or uint8 out)");
  m.def("compact_pairs", &compact_pairs,
        "a neighbour table as each (block, offset)'s present pairs: offsets, rows in block, neighbours");
  m.def("neighbour_conv_int8_pairs", &neighbour_conv_int8_pairs,
        "neighbour_conv_int8 over compact_pairs' tables (the same sums, no missing slots visited)");
  m.def("scatter_conv_int8", &scatter_conv_int8,
        "the int8 scatter convolution (each output row reached once) with its epilogue");
}
