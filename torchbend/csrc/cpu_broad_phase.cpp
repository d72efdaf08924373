// The broad phase of the compiled contact operators (contact_box_pairs, cpu_contact.h): pairs of overlapping padded
// boxes by a uniform grid (a dense table of its cells where it is small, else a hash of the cell keys) of about the
// boxes' mean size, each box of B filed under every cell it covers and each box of A tested against those of the
// cells it covers, each pair in the first cell the two share.  Long boxes (a step's swept boxes) cover more cells
// and leave the others' cost alone.
#include <algorithm>
#include <cstdint>
#include <limits>
#include <tuple>
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
  // the cell size: B's boxes' mean largest extent (at least a 32nd of the largest box's) plus 2 pad, so that long
  // boxes (a step's swept boxes) span a few cells instead of setting the size of all
  double ext_sum = 0, ext_max = 0, org[3];
  for (int i = 0; i < 3; ++i) org[i] = std::numeric_limits<double>::max();
  auto scan = [&](const T* lo, const T* hi, int64_t n) {
    for (int64_t b = 0; b < n; ++b) {
      double e = 0;
      for (int i = 0; i < 3; ++i) {
        e = std::max(e, double(hi[3 * b + i]) - double(lo[3 * b + i]));
        org[i] = std::min(org[i], double(lo[3 * b + i]));
      }
      ext_sum += e;
      ext_max = std::max(ext_max, e);
    }
  };
  scan(loB, hiB, nB);
  const double ext_b = ext_sum / double(nB);
  scan(loA, hiA, nA);
  // cells cover the boxes padded by a little more than pad, and more than the rounding of the final test in T (a
  // sum of a coordinate and 2 pad: half an ulp of the largest coordinate): a pair that passes it shares a cell
  double big = 0;
  for (int64_t i = 0; i < 3 * nA; ++i) big = std::max(big, std::max(std::fabs(double(loA[i])), std::fabs(double(hiA[i]))));
  for (int64_t i = 0; i < 3 * nB; ++i) big = std::max(big, std::max(std::fabs(double(loB[i])), std::fabs(double(hiB[i]))));
  const double cpad = double(pad) * (1 + 1e-6) + 4 * double(std::numeric_limits<T>::epsilon()) * (big + double(pad)) +
                      1e-300;
  double h = std::max(ext_b, ext_max / 32) + 2 * cpad;
  if (!(h > 0) || !std::isfinite(h)) h = 1;
  for (int i = 0; i < 3; ++i) org[i] -= 2 * cpad;
  auto cells_of = [&](const T* lo, const T* hi, int64_t c[6]) {
    for (int i = 0; i < 3; ++i) {
      c[i] = int64_t(std::floor((double(lo[i]) - cpad - org[i]) / h));
      c[3 + i] = int64_t(std::floor((double(hi[i]) + cpad - org[i]) / h));
    }
  };
  // the cells' keys: c in [0, 2^21) per axis (a grid of more cells per axis falls back to hashing the wrapped
  // coordinates: equal keys then only mean more candidates, never lost ones)
  auto key = [](int64_t cx, int64_t cy, int64_t cz) {
    return (cx & 0x1fffff) << 42 | (cy & 0x1fffff) << 21 | (cz & 0x1fffff);
  };
  // B's boxes filed under every cell they cover: a dense table of the grid's cells where it is small (a flat
  // cloth's grid is), else an open-addressing hash of the cell keys; each maps a cell to its range in `order`
  std::vector<int64_t> cb(6 * nB);
  int64_t hi_c[3] = {0, 0, 0}, entries = 0;
  for (int64_t b = 0; b < nB; ++b) {
    int64_t* c = &cb[6 * b];
    cells_of(loB + 3 * b, hiB + 3 * b, c);
    int64_t k = 1;
    for (int i = 0; i < 3; ++i) { hi_c[i] = std::max(hi_c[i], c[3 + i]); k *= c[3 + i] - c[i] + 1; }
    entries += k;
  }
  int64_t dims[3];
  double cells = 1;
  for (int i = 0; i < 3; ++i) { dims[i] = hi_c[i] + 1; cells *= double(dims[i]); }
  const bool dense = cells <= double(4 * (nA + entries) + 4096);
  auto cell_key = [&](int64_t cx, int64_t cy, int64_t cz) {
    return dense ? (cx * dims[1] + cy) * dims[2] + cz : key(cx, cy, cz);
  };
  // `filed`: the boxes by cell (counting sort over the dense table; sorted keys for the hash)
  std::vector<int64_t> filed(size_t(entries), 0);
  CellMap map;
  std::vector<int64_t> dstart, dend;
  auto each_entry = [&](auto&& f) {
    for (int64_t b = 0; b < nB; ++b) {
      const int64_t* c = &cb[6 * b];
      for (int64_t x = c[0]; x <= c[3]; ++x)
        for (int64_t y = c[1]; y <= c[4]; ++y)
          for (int64_t z = c[2]; z <= c[5]; ++z) f(cell_key(x, y, z), b);
    }
  };
  if (dense) {
    dstart.assign(int64_t(cells) + 1, 0);
    each_entry([&](int64_t k, int64_t) { ++dstart[k + 1]; });
    for (int64_t k = 0; k < int64_t(cells); ++k) dstart[k + 1] += dstart[k];
    dend.assign(dstart.begin(), dstart.end() - 1);
    each_entry([&](int64_t k, int64_t b) { filed[size_t(dend[k]++)] = b; });
  } else {
    std::vector<std::pair<int64_t, int64_t>> kb;  // (cell key, box)
    kb.reserve(size_t(entries));
    each_entry([&](int64_t k, int64_t b) { kb.emplace_back(k, b); });
    std::sort(kb.begin(), kb.end());
    map.init(entries);
    for (int64_t i = 0; i < entries;) {
      int64_t j = i, k = kb[size_t(i)].first;
      for (; j < entries && kb[size_t(j)].first == k; ++j) filed[size_t(j)] = kb[size_t(j)].second;
      int64_t s = map.slot(k);
      map.keys[s] = k; map.start[s] = i; map.end[s] = j;
      i = j;
    }
  }
  // the range of B's boxes filed under cell (cx, cy, cz): false if none
  auto range = [&](int64_t cx, int64_t cy, int64_t cz, int64_t& q0, int64_t& q1) {
    if (dense) {
      if (cx > hi_c[0] || cy > hi_c[1] || cz > hi_c[2]) return false;
      const int64_t k = cell_key(cx, cy, cz);
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
        int64_t c[6];
        cells_of(loA + 3 * a, hiA + 3 * a, c);
        hits.clear();
        for (int64_t cx = c[0]; cx <= c[3]; ++cx)
          for (int64_t cy = c[1]; cy <= c[4]; ++cy)
            for (int64_t cz = c[2]; cz <= c[5]; ++cz) {
              int64_t q0, q1;
              if (!range(cx, cy, cz, q0, q1)) continue;
              for (int64_t q = q0; q < q1; ++q) {
                const int64_t b = filed[size_t(q)];
                if (upper && b <= a) continue;
                // each pair once: in the first cell both cover (every pair that overlaps after padding shares it)
                const int64_t* d = &cb[6 * b];
                if (std::max(c[0], d[0]) != cx || std::max(c[1], d[1]) != cy || std::max(c[2], d[2]) != cz) continue;
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

// the candidate stencils of a mesh over its vertices' boxes (lo, hi): each vertex against each face without it and
// each edge against each later edge sharing no vertex, whose boxes (a primitive's: its vertices') come within radius
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> contact_candidates(torch::Tensor lo, torch::Tensor hi,
                                                                           torch::Tensor faces, torch::Tensor edges,
                                                                           double radius) {
  const char* op = "contact_candidates";
  ck::require(lo.device().is_cpu() && lo.dim() == 2 && lo.size(1) == 3 && lo.is_floating_point() &&
              hi.sizes() == lo.sizes() && hi.scalar_type() == lo.scalar_type() && hi.device().is_cpu(), op,
              "lo and hi must be CPU (V, 3) float tensors of one dtype, got ", ck::shape_str(lo), " and ",
              ck::shape_str(hi));
  ck::require(radius >= 0 && std::isfinite(radius), op, "radius must be finite and >= 0, got ", radius);
  const int64_t V = lo.size(0);
  faces = ck::index_tensor(op, "faces", faces, lo.device());
  edges = ck::index_tensor(op, "edges", edges, lo.device());
  ck::require(faces.dim() == 2 && faces.size(1) == 3 && edges.dim() == 2 && edges.size(1) == 2, op,
              "faces must be (F, 3) and edges (E, 2), got ", ck::shape_str(faces), " and ", ck::shape_str(edges));
  ck::check_range(op, "faces", faces, 0, V, "vertex indices");
  ck::check_range(op, "edges", edges, 0, V, "vertex indices");
  lo = lo.contiguous(); hi = hi.contiguous();
  ck::require(finite_status(lo, 1) == 0 && finite_status(hi, 1) == 0, op, "the boxes' corners must be finite");
  const int64_t F = faces.size(0), E = edges.size(0);
  const int64_t* pf = faces.data_ptr<int64_t>();
  const int64_t* pe = edges.data_ptr<int64_t>();
  std::vector<int64_t> pt, ee;
  AT_DISPATCH_FLOATING_TYPES(lo.scalar_type(), "contact", [&] {
    using T = scalar_t;
    const T* pl = lo.data_ptr<T>();
    const T* ph = hi.data_ptr<T>();
    auto boxes = [&](const int64_t* prim, int64_t n, int k, std::vector<T>& bl, std::vector<T>& bh) {
      bl.resize(3 * n); bh.resize(3 * n);
      for (int64_t i = 0; i < n; ++i)
        for (int c = 0; c < 3; ++c) {
          T a = pl[3 * prim[k * i] + c], b = ph[3 * prim[k * i] + c];
          for (int j = 1; j < k; ++j) {
            a = std::min(a, pl[3 * prim[k * i + j] + c]);
            b = std::max(b, ph[3 * prim[k * i + j] + c]);
          }
          bl[3 * i + c] = a; bh[3 * i + c] = b;
        }
    };
    std::vector<T> fl, fh, el, eh;
    boxes(pf, F, 3, fl, fh);
    boxes(pe, E, 2, el, eh);
    std::vector<int64_t> ids(V);
    for (int64_t v = 0; v < V; ++v) ids[v] = v;
    const T pad = T(0.5 * radius);
    if (V > 0 && F > 0) box_pairs_impl<T>(pl, ph, V, fl.data(), fh.data(), F, pad, false, ids.data(), 1, pf, 3, pt);
    if (E > 0) box_pairs_impl<T>(el.data(), eh.data(), E, el.data(), eh.data(), E, pad, true, pe, 2, pe, 2, ee);
  });
  const int64_t P = int64_t(pt.size() / 2), Q = int64_t(ee.size() / 2);
  auto opt = faces.options();
  auto st_pt = torch::empty({P, 4}, opt), st_ee = torch::empty({Q, 4}, opt), pairs = torch::empty({Q, 2}, opt);
  int64_t* a = st_pt.data_ptr<int64_t>();
  for (int64_t i = 0; i < P; ++i) {
    const int64_t f = pt[2 * i + 1];
    a[4 * i] = pt[2 * i]; a[4 * i + 1] = pf[3 * f]; a[4 * i + 2] = pf[3 * f + 1]; a[4 * i + 3] = pf[3 * f + 2];
  }
  int64_t* b = st_ee.data_ptr<int64_t>();
  int64_t* c = pairs.data_ptr<int64_t>();
  for (int64_t i = 0; i < Q; ++i) {
    const int64_t e0 = ee[2 * i], e1 = ee[2 * i + 1];
    b[4 * i] = pe[2 * e0]; b[4 * i + 1] = pe[2 * e0 + 1]; b[4 * i + 2] = pe[2 * e1]; b[4 * i + 3] = pe[2 * e1 + 1];
    c[2 * i] = e0; c[2 * i + 1] = e1;
  }
  return {st_pt, st_ee, pairs};
}

}  // namespace cpu
}  // namespace torchbend
