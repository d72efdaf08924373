// The broad phase of the compiled contact operators (contact_box_pairs, cpu_contact.h): pairs of overlapping padded
// boxes by a uniform grid (a dense table of its cells where it is small, else a hash of the cell keys), each box of
// B filed under its lower corner's cell and each box of A tested against the 27 cells around its own.
#include <algorithm>
#include <cstdint>
#include <limits>
#include <vector>

#include "cpu_contact.h"
#include "cpu_tiles.h"

namespace torchbend {
namespace cpu {

namespace ck = torchbend::checks;

// ---- broad phase ---------------------------------------------------------------------------------
namespace {

// open-addressing map from a cell key to the range [start, end) of the boxes filed under it
struct CellMap {
  std::vector<int64_t> keys;
  std::vector<int64_t> start, end;
  uint64_t mask = 0;
  static uint64_t mix(int64_t k) {
    uint64_t z = uint64_t(k) + 0x9e3779b97f4a7c15ull;
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
  }
  void init(int64_t n) {
    uint64_t cap = 16;
    while (cap < uint64_t(2 * n + 1)) cap <<= 1;
    mask = cap - 1;
    keys.assign(cap, INT64_MIN);
    start.assign(cap, 0);
    end.assign(cap, 0);
  }
  int64_t slot(int64_t k) const {
    uint64_t s = mix(k) & mask;
    while (keys[s] != INT64_MIN && keys[s] != k) s = (s + 1) & mask;
    return int64_t(s);
  }
};

template <typename T>
void box_pairs_impl(const T* loA, const T* hiA, int64_t nA, const T* loB, const T* hiB, int64_t nB, T pad, bool upper,
                    const int64_t* idsA, int64_t kA, const int64_t* idsB, int64_t kB, std::vector<int64_t>& out) {
  T ext = 0, org[3];
  for (int i = 0; i < 3; ++i) org[i] = std::numeric_limits<T>::max();
  for (int64_t a = 0; a < nA; ++a)
    for (int i = 0; i < 3; ++i) { ext = std::max(ext, hiA[3 * a + i] - loA[3 * a + i]); org[i] = std::min(org[i], loA[3 * a + i]); }
  for (int64_t b = 0; b < nB; ++b)
    for (int i = 0; i < 3; ++i) { ext = std::max(ext, hiB[3 * b + i] - loB[3 * b + i]); org[i] = std::min(org[i], loB[3 * b + i]); }
  double h = double(ext) + 2 * double(pad);
  if (!(h > 0)) h = 1;
  auto cell = [&](const T* lo, int64_t c[3]) {
    for (int i = 0; i < 3; ++i) c[i] = int64_t(std::floor((double(lo[i]) - double(org[i])) / h));
  };
  // the cells' keys: (c + 1) in [0, 2^21) per axis (a grid of more cells per axis falls back to hashing
  // the wrapped coordinates: equal keys then only mean more candidates, never lost ones)
  auto key = [](int64_t cx, int64_t cy, int64_t cz) {
    return ((cx + 1) & 0x1fffff) << 42 | ((cy + 1) & 0x1fffff) << 21 | ((cz + 1) & 0x1fffff);
  };
  // the cells of B's boxes: a dense table of the grid's cells where it is small (a flat cloth's grid is), else an
  // open-addressing hash of the cell keys; each maps a cell to the range of its boxes in `order`
  int64_t lo_c[3] = {INT64_MAX, INT64_MAX, INT64_MAX}, hi_c[3] = {INT64_MIN, INT64_MIN, INT64_MIN};
  std::vector<int64_t> cb(3 * nB);
  for (int64_t b = 0; b < nB; ++b) {
    cell(loB + 3 * b, &cb[3 * b]);
    for (int i = 0; i < 3; ++i) { lo_c[i] = std::min(lo_c[i], cb[3 * b + i]); hi_c[i] = std::max(hi_c[i], cb[3 * b + i]); }
  }
  int64_t dims[3];
  double cells = 1;
  for (int i = 0; i < 3; ++i) { dims[i] = hi_c[i] - lo_c[i] + 1; cells *= double(dims[i]); }
  const bool dense = cells <= double(4 * (nA + nB) + 4096);
  std::vector<int64_t> kb(nB), order(nB);
  for (int64_t b = 0; b < nB; ++b) {
    const int64_t* c = &cb[3 * b];
    kb[b] = dense ? ((c[0] - lo_c[0]) * dims[1] + (c[1] - lo_c[1])) * dims[2] + (c[2] - lo_c[2]) : key(c[0], c[1], c[2]);
    order[b] = b;
  }
  std::sort(order.begin(), order.end(), [&](int64_t u, int64_t v) { return kb[u] < kb[v] || (kb[u] == kb[v] && u < v); });
  CellMap map;
  std::vector<int64_t> dstart, dend;
  if (dense) { dstart.assign(int64_t(cells), 0); dend.assign(int64_t(cells), 0); }
  else map.init(nB);
  for (int64_t i = 0; i < nB;) {
    int64_t j = i, k = kb[order[i]];
    while (j < nB && kb[order[j]] == k) ++j;
    if (dense) { dstart[k] = i; dend[k] = j; }
    else {
      int64_t s = map.slot(k);
      map.keys[s] = k; map.start[s] = i; map.end[s] = j;
    }
    i = j;
  }
  // the range of B's boxes filed under cell (cx, cy, cz): false if none
  auto range = [&](int64_t cx, int64_t cy, int64_t cz, int64_t& q0, int64_t& q1) {
    if (dense) {
      if (cx < lo_c[0] || cx > hi_c[0] || cy < lo_c[1] || cy > hi_c[1] || cz < lo_c[2] || cz > hi_c[2]) return false;
      const int64_t k = ((cx - lo_c[0]) * dims[1] + (cy - lo_c[1])) * dims[2] + (cz - lo_c[2]);
      q0 = dstart[k]; q1 = dend[k];
      return q1 > q0;
    }
    int64_t s = map.slot(key(cx, cy, cz));
    if (map.keys[s] == INT64_MIN) return false;
    q0 = map.start[s]; q1 = map.end[s];
    return true;
  };
  const T two_pad = 2 * pad;
  const int nt = std::max(1, std::min<int>(at::get_num_threads(), int((nA + 1023) / 1024)));
  std::vector<std::vector<int64_t>> parts(nt);
  at::parallel_for(0, nt, 1, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      auto& o = parts[t];
      int64_t a0 = nA * t / nt, a1 = nA * (t + 1) / nt;
      std::vector<int64_t> hits;
      for (int64_t a = a0; a < a1; ++a) {
        int64_t c[3];
        cell(loA + 3 * a, c);
        hits.clear();
        for (int dx = -1; dx <= 1; ++dx)
          for (int dy = -1; dy <= 1; ++dy)
            for (int dz = -1; dz <= 1; ++dz) {
              int64_t q0, q1;
              if (!range(c[0] + dx, c[1] + dy, c[2] + dz, q0, q1)) continue;
              for (int64_t q = q0; q < q1; ++q) {
                int64_t b = order[q];
                if (upper && b <= a) continue;
                const T *la = loA + 3 * a, *ha = hiA + 3 * a, *lb = loB + 3 * b, *hb = hiB + 3 * b;
                if (!(la[0] <= hb[0] + two_pad && ha[0] + two_pad >= lb[0] && la[1] <= hb[1] + two_pad &&
                      ha[1] + two_pad >= lb[1] && la[2] <= hb[2] + two_pad && ha[2] + two_pad >= lb[2]))
                  continue;
                bool shared = false;
                for (int64_t i = 0; i < kA && !shared; ++i)
                  for (int64_t j = 0; j < kB; ++j)
                    if (idsA[kA * a + i] == idsB[kB * b + j]) { shared = true; break; }
                if (!shared) hits.push_back(b);
              }
            }
        std::sort(hits.begin(), hits.end());  // a box's partners in order (the same list for any grid)
        for (int64_t b : hits) { o.push_back(a); o.push_back(b); }
      }
    }
  });
  size_t total = 0;
  for (auto& p : parts) total += p.size();
  out.reserve(total);
  for (auto& p : parts) out.insert(out.end(), p.begin(), p.end());
}

}  // namespace

torch::Tensor contact_box_pairs(torch::Tensor lo_a, torch::Tensor hi_a, torch::Tensor lo_b, torch::Tensor hi_b,
                                double pad, bool upper, torch::Tensor ids_a, torch::Tensor ids_b) {
  const char* op = "contact_box_pairs";
  for (const auto* t : {&lo_a, &hi_a, &lo_b, &hi_b})
    ck::require(t->device().is_cpu() && t->dim() == 2 && t->size(1) == 3 && t->is_floating_point(), op,
                "the boxes' corners must be CPU (n, 3) float tensors, got ", ck::shape_str(*t));
  ck::require(lo_a.sizes() == hi_a.sizes() && lo_b.sizes() == hi_b.sizes(), op, "lower and upper corners differ in shape");
  ck::require(lo_a.scalar_type() == lo_b.scalar_type() && hi_a.scalar_type() == lo_a.scalar_type() &&
              hi_b.scalar_type() == lo_a.scalar_type(), op, "the boxes' corners must share one dtype");
  ck::require(pad >= 0 && std::isfinite(pad), op, "pad must be finite and >= 0, got ", pad);
  const int64_t nA = lo_a.size(0), nB = lo_b.size(0);
  const bool ids = ids_a.numel() > 0 || ids_b.numel() > 0;
  if (ids) {
    ids_a = ck::index_tensor(op, "ids_a", ids_a, lo_a.device());
    ids_b = ck::index_tensor(op, "ids_b", ids_b, lo_a.device());
    ck::require(ids_a.dim() == 2 && ids_a.size(0) == nA && ids_b.dim() == 2 && ids_b.size(0) == nB, op,
                "ids_a and ids_b must have one row per box, got ", ck::shape_str(ids_a), " and ", ck::shape_str(ids_b));
  }
  ck::require(!upper || nA == nB, op, "upper pairs need one set of boxes (A = B)");
  lo_a = lo_a.contiguous(); hi_a = hi_a.contiguous(); lo_b = lo_b.contiguous(); hi_b = hi_b.contiguous();
  ck::require(finite_status(lo_a, 1) == 0 && finite_status(hi_a, 1) == 0 && finite_status(lo_b, 1) == 0 &&
              finite_status(hi_b, 1) == 0, op, "the boxes' corners must be finite");
  std::vector<int64_t> pairs;
  if (nA > 0 && nB > 0) {
    AT_DISPATCH_FLOATING_TYPES(lo_a.scalar_type(), "contact", [&] {
      box_pairs_impl<scalar_t>(lo_a.data_ptr<scalar_t>(), hi_a.data_ptr<scalar_t>(), nA, lo_b.data_ptr<scalar_t>(),
                               hi_b.data_ptr<scalar_t>(), nB, scalar_t(pad), upper,
                               ids ? ids_a.data_ptr<int64_t>() : nullptr, ids ? ids_a.size(1) : 0,
                               ids ? ids_b.data_ptr<int64_t>() : nullptr, ids ? ids_b.size(1) : 0, pairs);
    });
  }
  auto out = torch::empty({int64_t(pairs.size() / 2), 2}, lo_a.options().dtype(torch::kLong));
  std::copy(pairs.begin(), pairs.end(), out.data_ptr<int64_t>());
  return out;
}

}  // namespace cpu
}  // namespace torchbend
