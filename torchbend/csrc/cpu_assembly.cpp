// The sparse assembly of the Hessian of one mesh (assemble).
#include <algorithm>
#include <atomic>

#include "cpu_ops.h"
#include "cpu_tiles.h"

namespace torchbend {
namespace cpu {
// ----------------------------------------------------------------------------------------------
// Sparse assembly of the Hessian of one mesh into CSR values, both ways of
// torchbend.energies.bending_hessian.assemble: per hinge (scatter of the 12x12 blocks) and per
// triangle (paper sec. 4.1-4.2: psi'' g g^T per hinge, plus sum_h psi'_h Hess(theta_h) as one 9x9
// block per triangle, eq. 7 with the conditional transpose: face_block_tile).  The angles, psi', psi'' and
// angle gradients of W hinges and the face blocks of W triangles are computed across the lanes of a tile (as the
// other operators do); each triangle's block waits in a queue of W for the group of tiles that completes its
// hinges.  In parts over the rows, one per thread (assemble_impl): the same sums for any number of threads.

// names the first base bp[i] of an element (vertices ev[0 .. m)) outside the first scalar row of its block row
// ev[i / m] with its 3 columns (so that the block's rows base + p row_len (p < 3) would leave that block row)
template <int m>
[[noreturn, gnu::cold, gnu::noinline]] static void report_element_bases(const char* name, int64_t e, const int64_t* bp, const int64_t* ev,
                                              const int64_t* rs, const int64_t* rl) {
  for (int i = 0; i < m * m; ++i) {
    int64_t v = ev[i / m], r0 = rs[v];
    if (bp[i] < r0 || bp[i] > r0 + rl[v] - 3)
      torchbend::checks::fail("assemble", name, "[", e, ", ", i, "] = ", bp[i], " is not a block of row ", v,
                              " of the pattern (its first scalar row spans [", r0, ", ", r0 + rl[v], "))");
  }
  torchbend::checks::fail("assemble", name, "[", e, "]: a block base outside its block row");
}

// the block bases bp[0 .. m m) of an element checked against its block rows (checked by the assembly as it reads
// them, before their scatter; the hinges' check is fused into the assembly's reach loop)
template <int m>
static inline void check_element_bases(const char* name, int64_t e, const int64_t* bp, const int64_t* ev,
                                       const int64_t* rs, const int64_t* rl) {
  if (!torchbend::checks::kChecked) return;
  int bad = 0;
  for (int a = 0; a < m; ++a) {
    const int64_t lo = rs[ev[a]], hi = lo + rl[ev[a]] - 3;
    for (int b = 0; b < m; ++b) bad |= int(bp[m * a + b] < lo) | int(bp[m * a + b] > hi);
  }
  if (bad) report_element_bases<m>(name, e, bp, ev, rs, rl);
}

// the failure paths of assemble_impl's fused index checks, out of line (the hot loop keeps only the tests)
static torch::Tensor index_view(const int64_t* p, int64_t n, int64_t m) {  // the caller's array as a tensor (no copy)
  return torch::from_blob(const_cast<int64_t*>(p), {n, m}, torch::kLong);
}

[[gnu::cold, gnu::noinline]] static void assemble_bad_hinges(const int64_t* hinges, int64_t H, int64_t V) {
  check_hinge_range("assemble", index_view(hinges, H, 4), V);
}

[[gnu::cold, gnu::noinline]] static void assemble_bad_faces(const int64_t* faces, const int64_t* fes, int64_t F, int64_t V) {
  namespace ck = torchbend::checks;
  ck::check_range("assemble", "faces", index_view(faces, F, 3), 0, V, "x has V = " + std::to_string(V) + " vertices");
  for (int64_t i = 0; i < 3 * F; ++i)
    if (fes[i] != 1 && fes[i] != -1)
      ck::fail("assemble", "face_edge_signs[", i / 3, ", ", i % 3, "] = ", fes[i], " must be +1 or -1");
}

// the first hinge (in memory order) with a block base outside its block row, named (the cold path of the fused
// checks: a part that meets one skips the element and the assembly reports it here, the same for any thread count)
[[gnu::cold, gnu::noinline]] static void report_first_bad_bases(const int64_t* hinges, const int64_t* hblk, int64_t H,
                                                                const int64_t* faces, const int64_t* fblk, int64_t F,
                                                                const int64_t* rs, const int64_t* row_len) {
  for (int64_t h = 0; h < H; ++h) check_element_bases<4>("hinge_blocks", h, hblk + 16 * h, hinges + 4 * h, rs, row_len);
  for (int64_t f = 0; f < F; ++f) check_element_bases<3>("face_blocks", f, fblk + 9 * f, faces + 3 * f, rs, row_len);
}

// values += the block rows a of the local (3m x 3m) matrix `loc` of an element with vertices v[0..m) whose vertex
// v[a] lies in [v0, v1) (a part's rows): vertex block (a, b) starts at CSR position base[m a + b], its row p at
// base + p row_len[v[a]] (torchbend.energies.sparse.StencilPattern)
template <typename T, int m>
static inline void scatter_rows(T* values, const int64_t* base, const int64_t* v, const int64_t* row_len, const T* loc,
                                int64_t v0, int64_t v1) {
  for (int a = 0; a < m; ++a) {
    if (v[a] < v0 || v[a] >= v1) continue;
    const int64_t rl = row_len[v[a]];
    for (int b = 0; b < m; ++b) {
      T* dst = values + base[m * a + b];
      for (int p = 0; p < 3; ++p, dst += rl) {
        const T* src = loc + 3 * m * (3 * a + p) + 3 * b;
        dst[0] += src[0]; dst[1] += src[1]; dst[2] += src[2];
      }
    }
  }
}

// The assembly runs in parts, one per thread, each owning a range of block rows [v0, v1) (and so a range of the
// values): a part computes the hinges that hold a vertex of its rows and the faces that do, and adds only their
// blocks' rows in its range.  Every value is added to by one part, in one order: the hinges in order, and each
// face's block after the hinges of its last hinge's group of kGroup tiles (per triangle) -- the same sums for any
// number of parts.  A hinge that straddles two parts is computed by both (a thin seam on a mesh in any sensible
// vertex order).
constexpr int64_t kGroup = 3;  // tiles of hinges per group: a group's faces fill whole face tiles (F ~ 2H / 3)

template <typename T, int M, bool damped>
[[gnu::flatten]] static void assemble_impl(const T* x, const int64_t* hinges, int64_t H, Param<T> a, Param<T> k, Param<T> rest,
                          Param<T> c, Param<T> prev, const int64_t* hblk,
                          const int64_t* faces, const int64_t* feh, const int64_t* fes, const int64_t* fblk,
                          const int64_t* row_len, const int64_t* rs, int64_t V, int64_t F, bool per_triangle,
                          T* values, int64_t nnz, T* thout) {
  namespace ck = torchbend::checks;
  if (per_triangle && ck::kChecked) {
    int bad = 0;
    for (int64_t i = 0; i < 3 * F; ++i) bad |= int(feh[i] < -1) | int(feh[i] >= H);
    for (int64_t i = 0; bad && i < 3 * F; ++i)
      if (feh[i] < -1 || feh[i] >= H)
        ck::fail("assemble", "face_edge_hinges[", i / 3, ", ", i % 3, "] = ", feh[i], " is out of range [-1, ", H,
                 ") (hinge indices of H = ", H, " hinges, -1 on the boundary)");
  }
  // first[h] -> next[f] -> ...: the faces whose last hinge is h
  std::vector<int64_t> first(per_triangle ? H : 0, -1), next(per_triangle ? F : 0, -1);
  for (int64_t f = per_triangle ? F : 0; f-- > 0;) {
    const int64_t* fh = feh + 3 * f;
    int64_t last = std::max(fh[0], std::max(fh[1], fh[2]));
    if (last >= 0) { next[f] = first[last]; first[last] = f; }
  }
  // the parts: block rows split where the values are split evenly
  const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), H / 16384));
  std::vector<int64_t> vs(parts + 1, V);
  vs[0] = 0;
  for (int64_t t = 1; t < parts; ++t)
    vs[t] = std::lower_bound(rs, rs + V, nnz * t / parts) - rs;
  std::atomic<int> bad_index{0}, bad_base{0};
  constexpr int64_t GW = kGroup * W;
  auto part = [&](int64_t t) {
    const int64_t v0 = vs[t], v1 = vs[t + 1];
    const int64_t end = v1 < V ? rs[v1] : nnz;
    std::vector<T> d1s(per_triangle ? H : 0);
    // faces queued for their blocks, W at a time (face_block_tile), each added right after
    int64_t fq[W];
    int nq = 0;
    alignas(64) T FP[9][W], FC[3][W], FS[3][W], FO[81][W];
    auto face_tile = [&]() {
      for (int l = nq; l < W; ++l) {  // unused lanes: a degenerate triangle (zeros)
        for (int mm = 0; mm < 9; ++mm) FP[mm][l] = T(0);
        for (int kk = 0; kk < 3; ++kk) { FC[kk][l] = T(0); FS[kk][l] = T(1); }
      }
      face_block_tile<T, W>(FP, FC, FS, FO);
      for (int l = 0; l < nq; ++l) {
        T blk[81];
        for (int mm = 0; mm < 81; ++mm) blk[mm] = FO[mm][l];
        scatter_rows<T, 3>(values, fblk + 9 * fq[l], faces + 3 * fq[l], row_len, blk, v0, v1);
      }
      nq = 0;
    };
    // the faces of this part whose last hinge lies in groups done + 1 .. g, added
    int64_t done = -1;
    auto faces_through = [&](int64_t g) {
      for (; done < g; ++done) {
        const int64_t h1 = std::min(H, (done + 2) * GW);
        for (int64_t h = (done + 1) * GW; h < h1; ++h)
          for (int64_t f = first[h]; f >= 0; f = next[f]) {
            const int64_t* fv = faces + 3 * f;
            const int64_t* fs = fes + 3 * f;
            if (ck::kChecked && (uint64_t(fv[0]) >= uint64_t(V) || uint64_t(fv[1]) >= uint64_t(V) ||
                                 uint64_t(fv[2]) >= uint64_t(V) || (fs[0] != 1 && fs[0] != -1) ||
                                 (fs[1] != 1 && fs[1] != -1) || (fs[2] != 1 && fs[2] != -1))) {
              bad_index = 1;
              continue;
            }
            if ((fv[0] < v0 || fv[0] >= v1) && (fv[1] < v0 || fv[1] >= v1) && (fv[2] < v0 || fv[2] >= v1)) continue;
            if (ck::kChecked) {
              int bad = 0;
              for (int aa = 0; aa < 3; ++aa) {
                const int64_t lo = rs[fv[aa]], hi = lo + row_len[fv[aa]] - 3;
                for (int bb = 0; bb < 3; ++bb) bad |= int(fblk[9 * f + 3 * aa + bb] < lo) | int(fblk[9 * f + 3 * aa + bb] > hi);
              }
              if (bad) { bad_base = 1; continue; }
            }
            const int64_t* fh = feh + 3 * f;
            fq[nq] = f;
            for (int kk = 0; kk < 3; ++kk) { FC[kk][nq] = fh[kk] >= 0 ? d1s[fh[kk]] : T(0); FS[kk][nq] = T(fs[kk]); }
            for (int mm = 0; mm < 9; ++mm) FP[mm][nq] = x[3 * fv[mm / 3] + mm % 3];
            if (++nq == W) face_tile();
          }
        if (nq) face_tile();  // a group's faces before the next group's hinges
      }
    };
    alignas(64) T buf[W][144];
    T gbuf[W][12];
    alignas(64) T X[12][W];
    alignas(64) T TH[W], D1[W], D2[W], G[12][W];
    HingeTile<T, W> Q;
    Blocks<T, W> tile;
    T* op[W]; T* gp[W];
    for (int l = 0; l < W; ++l) { op[l] = buf[l]; gp[l] = gbuf[l]; }
    // `values` [v0's start, end) comes uninitialised and is zeroed just ahead of the adds: before a tile, up to
    // the last position the tile touches (first touches come after, and in cache)
    int64_t zeroed = v0 < V ? rs[v0] : nnz;
    int64_t hs[W];
    int nl = 0;
    auto hinge_tile = [&]() {
      int64_t reach = zeroed;
      for (int l = 0; l < W; ++l) {
        if (l >= nl) { for (int mm = 0; mm < 12; ++mm) X[mm][l] = T(0); zero_params<T, W>(l, Q); continue; }
        const int64_t h = hs[l];
        const int64_t* q = hinges + 4 * h;
        load_hinge<T, W>(x, q, X, l);
        Q.a[l] = a(0, h); Q.k[l] = k(0, h); Q.rest[l] = rest(0, h);
        Q.c[l] = damped ? c(0, h) : T(0); Q.prev[l] = damped ? prev(0, h) : T(0);
        for (int va = 0; va < 4; ++va)  // the reach of the hinge's blocks in this part's rows
          if (q[va] >= v0 && q[va] < v1) {
            const int64_t* base = hblk + 16 * h + 4 * va;
            reach = std::max(reach, std::max(std::max(base[0], base[1]), std::max(base[2], base[3])) + 2 * row_len[q[va]] + 3);
          }
      }
      theta_tile<T, W>(X, TH);
      TB_LANES_AGG(W) {
        T psi;
        psi_lane<M, damped>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], psi, D1[l], D2[l], static_cast<T*>(nullptr));
      }
      for (int l = 0; l < nl; ++l)
        if (hinges[4 * hs[l]] >= v0 && hinges[4 * hs[l]] < v1) thout[hs[l]] = TH[l];  // one writer per hinge
      if (reach > zeroed) { std::fill(values + zeroed, values + reach, T(0)); zeroed = reach; }
      if (!per_triangle) {
        block_tile<T, W>(X, D1, D2, tile);
        write_tile<T, false>(tile, nl, op, gp);
        for (int l = 0; l < nl; ++l)
          scatter_rows<T, 4>(values, hblk + 16 * hs[l], hinges + 4 * hs[l], row_len, buf[l], v0, v1);
      } else {
        grad_tile<T, W>(X, G);
        for (int l = 0; l < nl; ++l) d1s[hs[l]] = D1[l];
        for (int l = 0; l < nl; ++l) {
          faces_through(hs[l] / GW - 1);  // the earlier groups' faces come before this hinge
          T gg[144];
          for (int r = 0; r < 12; ++r) {
            T gr = D2[l] * G[r][l];
            for (int cc = 0; cc < 12; ++cc) gg[12 * r + cc] = gr * G[cc][l];
          }
          scatter_rows<T, 4>(values, hblk + 16 * hs[l], hinges + 4 * hs[l], row_len, gg, v0, v1);
        }
      }
      nl = 0;
    };
    for (int64_t h = 0; h < H; ++h) {
      const int64_t* q = hinges + 4 * h;
      if (ck::kChecked && (uint64_t(q[0]) >= uint64_t(V) || uint64_t(q[1]) >= uint64_t(V) ||
                           uint64_t(q[2]) >= uint64_t(V) || uint64_t(q[3]) >= uint64_t(V))) {
        bad_index = 1;
        continue;
      }
      bool mine = false;
      int bad = 0;
      for (int va = 0; va < 4; ++va) {
        if (q[va] < v0 || q[va] >= v1) continue;
        mine = true;
        if (ck::kChecked) {  // the hinge's bases of this part's rows lie in their block rows
          const int64_t* base = hblk + 16 * h + 4 * va;
          const int64_t lo = std::min(std::min(base[0], base[1]), std::min(base[2], base[3]));
          const int64_t hi = std::max(std::max(base[0], base[1]), std::max(base[2], base[3]));
          bad |= int(lo < rs[q[va]]) | int(hi > rs[q[va]] + row_len[q[va]] - 3);
        }
      }
      if (bad) { bad_base = 1; continue; }
      if (!mine) continue;
      hs[nl++] = h;
      if (nl == W) hinge_tile();
    }
    if (nl) hinge_tile();
    if (per_triangle) faces_through((H + GW - 1) / GW - 1);
    if (end > zeroed) std::fill(values + zeroed, values + end, T(0));  // blocks of no hinge (none in a bending pattern)
  };
  if (parts == 1) part(0);
  else at::parallel_for(0, parts, 1, [&](int64_t t0, int64_t t1) { for (int64_t t = t0; t < t1; ++t) part(t); });
  if (bad_index) {  // the first offending entry in memory order, named
    assemble_bad_hinges(hinges, H, V);
    assemble_bad_faces(faces, fes, F, V);
  }
  if (bad_base) report_first_bad_bases(hinges, hblk, H, faces, fblk, per_triangle ? F : 0, rs, row_len);
}

// the arguments of `assemble` checked before any work (checks.h); returns them prepared (contiguous)
struct AssembleArgs {
  Prepared P;
  torch::Tensor faces, face_edge_hinges, face_edge_signs, face_blocks, hinge_blocks, row_len;
  std::vector<int64_t> rs;  // per vertex v, the CSR position of its block row's first entry (V + 1 values)
};


static AssembleArgs assemble_args(torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k,
                                  torch::Tensor rest, const c10::optional<torch::Tensor>& c_,
                                  const c10::optional<torch::Tensor>& prev_, int64_t model, torch::Tensor hinge_blocks,
                                  torch::Tensor faces, torch::Tensor face_edge_hinges, torch::Tensor face_edge_signs,
                                  torch::Tensor face_blocks, torch::Tensor row_len, int64_t nnz, bool per_triangle) {
  const char* op = "assemble";
  namespace ck = torchbend::checks;
  ck::require(x.device().is_cpu() && x.dim() == 2 && x.size(1) == 3, op, "x must be a CPU (V, 3) tensor (one mesh), got ",
              ck::shape_str(x), " on ", x.device());
  Prepared P = prepare(op, x, hinges, a, k, rest, c_, prev_, model, false, false);
  hinges = P.hinges;
  const int64_t V = P.V, H = P.H;
  auto dev = x.device();
  faces = ck::index_tensor(op, "faces", faces, dev, 3);
  const int64_t F = faces.size(0);
  auto per_face = [&](torch::Tensor t, const char* name, int64_t cols) {
    t = ck::index_tensor(op, name, t, dev, cols);
    ck::require(t.size(0) == F, op, name, " must have F = ", F, " rows (one per face), got ", t.size(0));
    return t;
  };
  face_edge_hinges = per_face(face_edge_hinges, "face_edge_hinges", 3);
  face_edge_signs = per_face(face_edge_signs, "face_edge_signs", 3);
  face_blocks = per_face(face_blocks, "face_blocks", 9);
  hinge_blocks = ck::index_tensor(op, "hinge_blocks", hinge_blocks, dev, 16);
  ck::require(hinge_blocks.size(0) == H, op, "hinge_blocks must have H = ", H, " rows (one per hinge), got ",
              hinge_blocks.size(0));
  row_len = ck::index_tensor(op, "row_len", row_len, dev);
  ck::require(row_len.dim() == 1 && row_len.size(0) == V, op, "row_len must have shape (V,) = (", V, ",), got ",
              ck::shape_str(row_len));
  // hinges, faces, face-edge hinges and signs: checked by the assembly as it reads them (assemble_impl)
  // the pattern: row_len[v] = 3 x (vertex blocks in block row v), nnz = 3 sum(row_len); each block base of an
  // element's vertex pair (a, b) lies in the first scalar row of block row v_a with its 3 columns, so that the
  // block's rows base + p row_len[v_a] (p < 3) stay inside that block row
  ck::check_range(op, "row_len", row_len, 0, 3 * V + 1, "3 x the vertex blocks of a row of V = " +
                  std::to_string(V) + " vertices");
  const int64_t* rl = row_len.data_ptr<int64_t>();
  std::vector<int64_t> rs(size_t(V) + 1, 0);
  for (int64_t v = 0; v < V; ++v) {
    if (rl[v] % 3) ck::fail(op, "row_len[", v, "] = ", rl[v], " must be a multiple of 3");
    rs[size_t(v) + 1] = rs[size_t(v)] + 3 * rl[v];
  }
  ck::require(nnz == rs[size_t(V)], op, "nnz = ", nnz, " does not match the pattern: 3 sum(row_len) = ", rs[size_t(V)]);
  return AssembleArgs{P, faces, face_edge_hinges, face_edge_signs, face_blocks, hinge_blocks, row_len, std::move(rs)};
}

// a caller's buffer of the CSR values (out=): a contiguous CPU tensor of x's dtype and shape (nnz,), not
// overlapping x; else the ValueError naming it
static torch::Tensor out_values(const torch::Tensor& t, const torch::Tensor& x, int64_t nnz) {
  namespace ck = torchbend::checks;
  const char* op = "assemble";
  ck::require(t.device() == x.device(), op, "out must be on x's device (", x.device(), "), got ", t.device());
  ck::require(t.scalar_type() == x.scalar_type(), op, "out must have x's dtype (", x.scalar_type(), "), got ",
              t.scalar_type());
  ck::require(t.dim() == 1 && t.size(0) == nnz, op, "out must have shape (nnz,) = (", nnz, ",), got ",
              ck::shape_str(t));
  ck::require(t.is_contiguous(), op, "out must be contiguous");
  ck::require(disjoint(t, x), op, "out overlaps x");
  return t;
}

// (CSR values (nnz,) of the Hessian of one mesh x (V, 3), theta (H,), status); parameters as in
// bending_hessians, the pattern as block bases (torchbend.energies.sparse.StencilPattern: hinge_blocks (H, 16),
// face_blocks (F, 9), row_len (V,)), x finite (the caller checks)
std::tuple<torch::Tensor, torch::Tensor, int64_t> assemble(torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest,
                       c10::optional<torch::Tensor> c_, c10::optional<torch::Tensor> prev_, int64_t model,
                       torch::Tensor hinge_blocks, torch::Tensor faces, torch::Tensor face_edge_hinges,
                       torch::Tensor face_edge_signs, torch::Tensor face_blocks, torch::Tensor row_len, int64_t nnz,
                       bool per_triangle, c10::optional<torch::Tensor> out) {
  AssembleArgs A = assemble_args(x, hinges, a, k, rest, c_, prev_, model, hinge_blocks, faces, face_edge_hinges,
                                 face_edge_signs, face_blocks, row_len, nnz, per_triangle);
  const Prepared& P = A.P;
  x = P.x; hinges = P.hinges;
  const int64_t H = P.H, F = A.faces.size(0);
  faces = A.faces; face_edge_hinges = A.face_edge_hinges; face_edge_signs = A.face_edge_signs;
  face_blocks = A.face_blocks; hinge_blocks = A.hinge_blocks; row_len = A.row_len;
  const bool damped = P.damped;
  a = P.a; k = P.k; rest = P.rest;
  torch::Tensor c = P.c, prev = P.prev;
  auto values = out.has_value() ? out_values(*out, x, nnz) : pooled_empty({nnz}, x.options());  // zeroed in the pass
  auto theta = torch::empty({H}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "assemble", [&] {
    Param<scalar_t> none{nullptr, 0, H};
    with_model(int(model), damped, [&](auto M_, auto D_) {
      assemble_impl<scalar_t, decltype(M_)::value, decltype(D_)::value>(
          x.data_ptr<scalar_t>(), hinges.data_ptr<int64_t>(), H, param<scalar_t>(a, H), param<scalar_t>(k, H),
          param<scalar_t>(rest, H), damped ? param<scalar_t>(c, H) : none, damped ? param<scalar_t>(prev, H) : none,
          hinge_blocks.data_ptr<int64_t>(), faces.data_ptr<int64_t>(), face_edge_hinges.data_ptr<int64_t>(),
          face_edge_signs.data_ptr<int64_t>(), face_blocks.data_ptr<int64_t>(), row_len.data_ptr<int64_t>(),
          A.rs.data(), P.V, F, per_triangle, values.data_ptr<scalar_t>(), nnz, theta.data_ptr<scalar_t>());
    });
  });
  return {values, theta, fold_status(theta, model)};
}


}  // namespace cpu
}  // namespace torchbend
