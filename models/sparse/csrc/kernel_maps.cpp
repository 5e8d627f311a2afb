// A voxel pyramid's kernel maps in one compiled pass (models/sparse/compiled.py builds this file with
// sparse_conv.cpp into one module; models/sparse/tensor.py's KernelMapCache.build_pyramid calls it).
//
// pyramid_maps(coords (N, 4) int64 (batch, x, y, z) sorted by key and unique, levels L, max_cells)
//   -> for each level l = 0 .. L-1 (tensor stride 2^l, level 0 = `coords`), five tensors:
//        coords_l      (N_l, 4) int64, unique(floor(coords_{l-1} / 2)) sorted by key (level 0: `coords` itself);
//        sub_l         (N_l, 27) int64, the 3^3 submanifold neighbour table (N_l where a neighbour is absent);
//        sub_counts_l  (27,) int64 pairs per offset;
//        down_l        (N_{l+1}, 8) int64, the 2^3 stride-2 map from level l to l+1 (rows of level l, N_l where
//                      absent; empty at the last level);
//        down_counts_l (8,) int64.
//   Offsets in weight order (itertools.product over x, y, z), as models/sparse/kernel_map.py builds them, so the
//   tables equal build_kernel_map's. An empty list where the input is not sorted and unique, or where a level's
//   column index would exceed max_cells: the caller then builds the maps one by one.
//
// Design: a level's voxels sorted by (batch, x, y, z) form columns of equal (batch, x, y) with z ascending. A dense
// 2-D index over the padded (batch, x, y) box gives each column's range (boxes are R x A, not R x A x D: 66 k cells
// for a `small` ROI instead of the 3-D grid's 4 M). For each column and each of the 9 (dx, dy) columns beside it, a
// z-indexed table of the neighbour column's rows answers z - 1, z, z + 1 for every voxel without a branch. The next level is built column by column from
// the (at most 4) fine columns under each coarse one, in key order without a sort.

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>

#include <algorithm>
#include <cstdint>
#include <vector>

namespace radarseg {
namespace {

constexpr int64_t kBits = 16;
constexpr int64_t kBias = int64_t{1} << (kBits - 1);

inline int64_t pack(int64_t b, int64_t x, int64_t y, int64_t z) {
  return (((((b << kBits) | (x + kBias)) << kBits) | (y + kBias)) << kBits) | (z + kBias);
}

// Columns of a sorted level: start row of each, and a dense (batch, x, y) index of column ids (-1: none).
struct Columns {
  std::vector<int64_t> start;  // ncols + 1
  std::vector<int32_t> grid;
  int64_t b0 = 0, x0 = 0, y0 = 0, nx = 0, ny = 0;

  size_t cell(int64_t b, int64_t x, int64_t y) const {
    return static_cast<size_t>(((b - b0) * nx + (x - x0)) * ny + (y - y0));
  }
  int32_t at(int64_t b, int64_t x, int64_t y) const { return grid[cell(b, x, y)]; }
};

bool build_columns(const int64_t* c, int64_t n, int64_t max_cells, Columns& cols) {
  int64_t b_lo = c[0], b_hi = c[0], x_lo = c[1], x_hi = c[1], y_lo = c[2], y_hi = c[2];
  for (int64_t i = 1; i < n; ++i) {
    b_lo = std::min(b_lo, c[4 * i]);
    b_hi = std::max(b_hi, c[4 * i]);
    x_lo = std::min(x_lo, c[4 * i + 1]);
    x_hi = std::max(x_hi, c[4 * i + 1]);
    y_lo = std::min(y_lo, c[4 * i + 2]);
    y_hi = std::max(y_hi, c[4 * i + 2]);
  }
  cols.b0 = b_lo;
  cols.x0 = x_lo - 1;
  cols.y0 = y_lo - 1;
  cols.nx = x_hi - x_lo + 3;
  cols.ny = y_hi - y_lo + 3;
  const int64_t cells = (b_hi - b_lo + 1) * cols.nx * cols.ny;
  if (cells > max_cells) return false;
  cols.grid.assign(static_cast<size_t>(cells), -1);
  cols.start.clear();
  for (int64_t i = 0; i < n; ++i) {
    const int64_t* v = c + 4 * i;
    if (i == 0 || v[0] != v[-4] || v[1] != v[-3] || v[2] != v[-2]) {
      cols.grid[cols.cell(v[0], v[1], v[2])] = static_cast<int32_t>(cols.start.size());
      cols.start.push_back(i);
    }
  }
  cols.start.push_back(n);
  return true;
}

// The 3^3 submanifold table of one level: out[j * 27 + k] with k = (dx + 1) * 9 + (dy + 1) * 3 + (dz + 1). For each
// column and each of its 9 neighbour columns, the neighbour's rows are written into a table indexed by z (one slot of
// padding at each end), the column's voxels read z - 1, z, z + 1 from it without a branch, and the slots are reset.
void submanifold(const int64_t* c, int64_t n, const Columns& cols, int64_t* out) {
  const int64_t ncols = static_cast<int64_t>(cols.start.size()) - 1;
  int64_t z_lo = c[3], z_hi = c[3];
  for (int64_t i = 1; i < n; ++i) {
    z_lo = std::min(z_lo, c[4 * i + 3]);
    z_hi = std::max(z_hi, c[4 * i + 3]);
  }
  const int64_t z0 = z_lo - 1;  // slot of z is z - z0
  at::parallel_for(0, ncols, 64, [&](int64_t begin, int64_t end) {
    std::vector<int64_t> slot(static_cast<size_t>(z_hi - z0 + 2), n);
    for (int64_t col = begin; col < end; ++col) {
      const int64_t first = cols.start[col], last = cols.start[col + 1];
      const int64_t b = c[4 * first], x = c[4 * first + 1], y = c[4 * first + 2];
      for (int dx = -1; dx <= 1; ++dx) {
        for (int dy = -1; dy <= 1; ++dy) {
          const int64_t k0 = (dx + 1) * 9 + (dy + 1) * 3;
          const int32_t other = cols.at(b, x + dx, y + dy);
          const int64_t o_first = other < 0 ? 0 : cols.start[other], o_last = other < 0 ? 0 : cols.start[other + 1];
          for (int64_t r = o_first; r < o_last; ++r) slot[c[4 * r + 3] - z0] = r;
          for (int64_t j = first; j < last; ++j) {
            const int64_t* s = slot.data() + (c[4 * j + 3] - z0);
            int64_t* o = out + j * 27 + k0;
            o[0] = s[-1];
            o[1] = s[0];
            o[2] = s[1];
          }
          for (int64_t r = o_first; r < o_last; ++r) slot[c[4 * r + 3] - z0] = n;
        }
      }
    }
  });
}

// The next level's voxels and the stride-2 map onto them: down[parent * 8 + k] = fine row, k = (x&1)*4 + (y&1)*2 + (z&1).
// Coarse columns (b, X, Y) are visited in order; each gathers the (at most 4) fine columns (2X + i, 2Y + j), whose
// floor(z / 2) values, sorted and made unique, are its voxels: the coarse level comes out sorted without a sort.
at::Tensor coarser(const int64_t* c, int64_t n, const Columns& cols, at::Tensor& down) {
  std::vector<int64_t> coarse;  // (b, X, Y, Z) rows
  coarse.reserve(static_cast<size_t>(4 * (n / 2 + 1)));
  std::vector<int64_t> parent(static_cast<size_t>(n));
  std::vector<int64_t> zs;
  const int64_t b_hi = cols.b0 + static_cast<int64_t>(cols.grid.size()) / (cols.nx * cols.ny) - 1;
  const int64_t x_lo = (cols.x0 + 1) >> 1, x_hi = (cols.x0 + cols.nx - 2) >> 1;
  const int64_t y_lo = (cols.y0 + 1) >> 1, y_hi = (cols.y0 + cols.ny - 2) >> 1;
  for (int64_t b = cols.b0; b <= b_hi; ++b) {
    for (int64_t X = x_lo; X <= x_hi; ++X) {
      for (int64_t Y = y_lo; Y <= y_hi; ++Y) {
        int32_t fine[4];
        int count = 0;
        zs.clear();
        for (int i = 0; i < 2; ++i)
          for (int j = 0; j < 2; ++j) {
            const int32_t col = cols.at(b, 2 * X + i, 2 * Y + j);
            if (col < 0) continue;
            fine[count++] = col;
            for (int64_t r = cols.start[col]; r < cols.start[col + 1]; ++r) zs.push_back(c[4 * r + 3] >> 1);
          }
        if (count == 0) continue;
        std::sort(zs.begin(), zs.end());
        zs.erase(std::unique(zs.begin(), zs.end()), zs.end());
        const int64_t base = static_cast<int64_t>(coarse.size()) / 4;
        for (const int64_t z : zs) coarse.insert(coarse.end(), {b, X, Y, z});
        for (int f = 0; f < count; ++f) {
          size_t p = 0;  // the column's z ascend, so the parent's index only moves forward
          for (int64_t r = cols.start[fine[f]]; r < cols.start[fine[f] + 1]; ++r) {
            const int64_t z = c[4 * r + 3] >> 1;
            while (zs[p] < z) ++p;
            parent[r] = base + static_cast<int64_t>(p);
          }
        }
      }
    }
  }
  const int64_t m = static_cast<int64_t>(coarse.size()) / 4;
  auto coords = at::empty({m, 4}, at::kLong);
  std::copy(coarse.begin(), coarse.end(), coords.data_ptr<int64_t>());
  down = at::empty({m, 8}, at::kLong);
  int64_t* d = down.data_ptr<int64_t>();
  std::fill(d, d + m * 8, n);
  for (int64_t i = 0; i < n; ++i) {
    const int64_t* v = c + 4 * i;
    d[parent[i] * 8 + (v[1] & 1) * 4 + (v[2] & 1) * 2 + (v[3] & 1)] = i;
  }
  return coords;
}

at::Tensor count_pairs(const at::Tensor& table, int64_t missing) {
  const int64_t rows = table.size(0), k = table.size(1);
  auto counts = at::empty({k}, at::kLong);
  int64_t* out = counts.data_ptr<int64_t>();
  std::fill(out, out + k, 0);
  const int64_t* t = table.data_ptr<int64_t>();
  for (int64_t j = 0; j < rows; ++j)
    for (int64_t i = 0; i < k; ++i) out[i] += t[j * k + i] != missing;
  return counts;
}

}  // namespace

std::vector<at::Tensor> pyramid_maps(at::Tensor coords, int64_t levels, int64_t max_cells) {
  TORCH_CHECK(coords.device().is_cpu() && coords.scalar_type() == at::kLong && coords.dim() == 2 &&
                  coords.size(1) == 4 && coords.is_contiguous(),
              "pyramid_maps: contiguous (N, 4) int64 CPU coordinates expected");
  TORCH_CHECK(levels >= 1, "pyramid_maps: levels must be >= 1");
  const int64_t n0 = coords.size(0);
  if (n0 == 0) return {};
  const int64_t* c0 = coords.data_ptr<int64_t>();
  for (int64_t i = 1; i < n0; ++i) {  // sorted by key and unique
    if (pack(c0[4 * i], c0[4 * i + 1], c0[4 * i + 2], c0[4 * i + 3]) <=
        pack(c0[4 * i - 4], c0[4 * i - 3], c0[4 * i - 2], c0[4 * i - 1]))
      return {};
  }
  at::Tensor level = coords;
  std::vector<at::Tensor> out;
  Columns cols;
  for (int64_t l = 0; l < levels; ++l) {
    const int64_t n = level.size(0);
    const int64_t* c = level.data_ptr<int64_t>();
    if (!build_columns(c, n, max_cells, cols)) return {};
    auto sub = at::empty({n, 27}, at::kLong);
    submanifold(c, n, cols, sub.data_ptr<int64_t>());
    at::Tensor down = at::empty({0, 8}, at::kLong);
    at::Tensor next;
    if (l + 1 < levels) next = coarser(c, n, cols, down);
    out.push_back(level);
    out.push_back(sub);
    out.push_back(count_pairs(sub, n));
    out.push_back(down);
    out.push_back(count_pairs(down, n));
    if (l + 1 < levels) level = next;
  }
  return out;
}

}  // namespace radarseg
