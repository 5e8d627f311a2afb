// The register-blocked micro-kernel of both convolution extensions (sparse_conv.cpp on float32 rows,
// sparse_conv_int8.cpp on uint8 rows times int8 weights summed in int32), and the walk that runs it over a group of
// rows and all of a layer's padded output columns.
//
//   dst[r][0:Dp] += src[r][0:C] . w        for `rows` <= kMaxRows rows, w packed (C / kGroup, Dp, kGroup)
//
// A chunk of columns of R rows is a `Tile`: NW wide vectors (kWide lanes) and NH (0 or 1) half vectors (8 lanes) per
// row, held in registers while the chunk's weights are loaded once per input group and multiplied into every row.
// Every column is 4 bytes (a float, an int32 sum, or a packed group of kGroup weights), so a row's chunk is
// contiguous: its wide vectors one after another, then the half one.
//
// The element types, vectors and multiply-add come from an `Ops` type:
//   in_t, weight_t, acc_t                 activation, packed weight and accumulator elements
//   wide_v, half_v                        vectors of kWide and 8 lanes (the same type where kWide is 8)
//   kWide, kGroup, kMaxRows, kMaxChunkVectors, kHalfJoinsWide (see over_columns)
//   group(const in_t*)                    the kGroup activations of one input group, as the scalar to broadcast
//   madd(acc, x, w)                       acc + broadcast(x) . w, for wide_v and (where kWide is 16) half_v

#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <type_traits>

namespace radarseg_kernels {

constexpr int64_t kLanes = 8;       // columns are padded to a multiple of 8
constexpr int64_t kBlockRows = 64;  // output rows of one parallel block

inline int64_t padded(int64_t d) { return (d + kLanes - 1) / kLanes * kLanes; }

template <int N>
using Count = std::integral_constant<int, N>;

// Unaligned loads and stores (memcpy compiles to one vector move; an alignment attribute on a typedef would be
// dropped when the type is a template argument).
template <typename V>
inline V load(const void* p) {
  V v;
  std::memcpy(&v, p, sizeof(V));
  return v;
}
template <typename V>
inline void store(void* p, V v) { std::memcpy(p, &v, sizeof(V)); }

// R rows x one chunk of columns in registers (see the file's comment).
template <typename Ops, int R, int NW, int NH>
struct Tile {
  using wide_v = typename Ops::wide_v;
  using half_v = typename Ops::half_v;
  wide_v wide[R][NW > 0 ? NW : 1];
  half_v half[R];

  // Row r from the chunk that starts at `p`.
  inline void load_row(int r, const void* p) {
    const char* bytes = static_cast<const char*>(p);
    for (int v = 0; v < NW; ++v) wide[r][v] = load<wide_v>(bytes + v * sizeof(wide_v));
    if constexpr (NH > 0) half[r] = load<half_v>(bytes + NW * sizeof(wide_v));
  }
  inline void store_row(int r, void* p) const {
    char* bytes = static_cast<char*>(p);
    for (int v = 0; v < NW; ++v) store<wide_v>(bytes + v * sizeof(wide_v), wide[r][v]);
    if constexpr (NH > 0) store<half_v>(bytes + NW * sizeof(wide_v), half[r]);
  }
  // Row r += x (broadcast) times row o of `other`.
  template <int OR, typename X>
  inline void madd_row(int r, X x, const Tile<Ops, OR, NW, NH>& other, int o) {
    for (int v = 0; v < NW; ++v) wide[r][v] = Ops::madd(wide[r][v], x, other.wide[o][v]);
    if constexpr (NH > 0) half[r] = Ops::madd(half[r], x, other.half[o]);
  }
};

// dst[r][d0:d0 + NW * kWide + NH * 8] += src[r][0:C] . w[:, d0:...], for R rows.
template <typename Ops, int R, int NW, int NH>
inline void rows_times_weight_chunk(const typename Ops::in_t* const* src, const typename Ops::weight_t* w, int64_t C,
                                    int64_t Dp, int64_t d0, typename Ops::acc_t* const* dst) {
  Tile<Ops, R, NW, NH> acc;
  for (int r = 0; r < R; ++r) acc.load_row(r, dst[r] + d0);
  for (int64_t c = 0; c < C; c += Ops::kGroup) {
    Tile<Ops, 1, NW, NH> weights;
    weights.load_row(0, w + (c / Ops::kGroup * Dp + d0) * Ops::kGroup);
    for (int r = 0; r < R; ++r) acc.madd_row(r, Ops::group(src[r] + c), weights, 0);
  }
  for (int r = 0; r < R; ++r) acc.store_row(r, dst[r] + d0);
}

// The padded columns in chunks: as many wide vectors as fit (at most kMaxChunkVectors, and two + two for four),
// then, where kWide is 16, one half vector for 8 columns left over (in the last wide one's chunk when 24 are left
// and Ops::kHalfJoinsWide); `chunk(d0, Count<NW>{}, Count<NH>{})` runs one chunk.
template <typename Ops, typename F>
inline void over_columns(int64_t Dp, F&& chunk) {
  constexpr int64_t kWide = Ops::kWide;
  constexpr int kMaxChunkVectors = Ops::kMaxChunkVectors;
  static_assert(kWide == kLanes || kWide == 2 * kLanes, "wide vectors of 8 or 16 lanes");
  for (int64_t d0 = 0; d0 < Dp;) {
    const int64_t wide = (Dp - d0) / kWide;
    const bool half = (Dp - d0) % kWide != 0;  // never where kWide is 8: Dp is a multiple of 8
    if (wide >= kMaxChunkVectors && wide != 4) {
      chunk(d0, Count<kMaxChunkVectors>{}, Count<0>{});
      d0 += kMaxChunkVectors * kWide;
    } else if (wide >= 2) {
      chunk(d0, Count<2>{}, Count<0>{});
      d0 += 2 * kWide;
    } else if (wide == 1 && !(half && Ops::kHalfJoinsWide)) {
      chunk(d0, Count<1>{}, Count<0>{});
      d0 += kWide;
    } else if constexpr (kWide > kLanes) {
      if constexpr (Ops::kHalfJoinsWide) {
        if (wide == 1) {
          chunk(d0, Count<1>{}, Count<1>{});
          d0 += kWide + kLanes;
          continue;
        }
      }
      chunk(d0, Count<0>{}, Count<1>{});
      d0 += kLanes;
    }
  }
}

// `body(Count<R>{})` for R = rows (1 <= rows <= MaxRows): the row count as a compile-time constant.
template <int MaxRows, typename F>
inline void with_rows(int rows, F&& body) {
  static_assert(MaxRows == 4 || MaxRows == 8, "4 or 8 rows at a time");
  switch (rows) {  // the cases above MaxRows never come
    case 8: body(Count<std::min(8, MaxRows)>{}); break;
    case 7: body(Count<std::min(7, MaxRows)>{}); break;
    case 6: body(Count<std::min(6, MaxRows)>{}); break;
    case 5: body(Count<std::min(5, MaxRows)>{}); break;
    case 4: body(Count<4>{}); break;
    case 3: body(Count<3>{}); break;
    case 2: body(Count<2>{}); break;
    default: body(Count<1>{}); break;
  }
}

// `tile(Count<R>{}, d0, Count<NW>{}, Count<NH>{})` over every chunk of Dp columns of a group of `rows` rows.
template <typename Ops, typename F>
inline void over_tiles(int rows, int64_t Dp, F&& tile) {
  with_rows<Ops::kMaxRows>(rows, [&](auto r) {
    over_columns<Ops>(Dp, [&](int64_t d0, auto nw, auto nh) { tile(r, d0, nw, nh); });
  });
}

// dst[r] += src[r] . w for `rows` <= kMaxRows rows.
template <typename Ops>
inline void rows_times_weight(int rows, const typename Ops::in_t* const* src, const typename Ops::weight_t* w,
                              int64_t C, int64_t Dp, typename Ops::acc_t* const* dst) {
  over_tiles<Ops>(rows, Dp, [&](auto r, int64_t d0, auto nw, auto nh) {
    rows_times_weight_chunk<Ops, decltype(r)::value, decltype(nw)::value, decltype(nh)::value>(src, w, C, Dp, d0,
                                                                                                 dst);
  });
}

}  // namespace radarseg_kernels
