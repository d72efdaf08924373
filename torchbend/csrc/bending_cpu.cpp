// Compiled CPU kernels of torchbend's bending Hessians (built by torchbend/backends/native.py).
// The per-hinge mathematics mirrors the eager reference in torchbend/ops (hinge.py, psi.py,
// triangle.py), which the tests compare against.
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <cmath>
#include <limits>
#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <cstdint>
#ifdef __AVX__
#include <immintrin.h>
#endif
template <typename T> static inline void cross(const T* u, const T* v, T* o) {
  o[0] = u[1] * v[2] - u[2] * v[1]; o[1] = u[2] * v[0] - u[0] * v[2]; o[2] = u[0] * v[1] - u[1] * v[0];
}
template <typename T> static inline T dot(const T* u, const T* v) { return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]; }

// Hinges are processed in tiles of W, every quantity stored as [component][lane] so that the
// compiler vectorizes each formula across the hinges of a tile (about 1.5x over one hinge at a time).
constexpr int W = 8;
#define LANES _Pragma("omp simd") for (int l = 0; l < W; ++l)

// one half-hinge (a, b, c) = (x0, x1, wing) of W hinges: rho_k, unit normal n, mh[k] = m_k / h_k,
// mc = m_c / (h_c |e|^2); degenerate (collinear) triangles give zeros (torchbend.geometry's policy)
template <typename T> struct Half { T rho[3][W], n[3][W], mh[3][3][W], mc[3][W]; };

template <typename T>
static inline void half_tile(const T (*A)[W], const T (*Bv)[W], const T (*C)[W], const T (*E)[W], Half<T>& o) {
  const T eps = std::numeric_limits<T>::epsilon();
  LANES {
    T e0 = E[0][l], e1 = E[1][l], e2 = E[2][l];
    T u0 = C[0][l] - A[0][l], u1 = C[1][l] - A[1][l], u2 = C[2][l] - A[2][l];
    T w0 = C[0][l] - Bv[0][l], w1 = C[1][l] - Bv[1][l], w2 = C[2][l] - Bv[2][l];
    T N0 = e1 * u2 - e2 * u1, N1 = e2 * u0 - e0 * u2, N2 = e0 * u1 - e1 * u0;
    T ee = e0 * e0 + e1 * e1 + e2 * e2, uu = u0 * u0 + u1 * u1 + u2 * u2, ww = w0 * w0 + w1 * w1 + w2 * w2;
    T area2 = std::sqrt(N0 * N0 + N1 * N1 + N2 * N2), elen = std::sqrt(ee);
    bool valid = area2 > eps * std::max(std::max(ee, uu), ww);
    T ia = (valid ? T(1) : T(0)) / (valid ? area2 : T(1));
    T ie = (valid ? T(1) : T(0)) / (valid ? elen : T(1));
    T s = ie * ia;
    o.rho[0][l] = -(e0 * w0 + e1 * w1 + e2 * w2) * s;
    o.rho[1][l] = (e0 * u0 + e1 * u1 + e2 * u2) * s;
    o.rho[2][l] = -elen * ia;
    T n0 = N0 * ia, n1 = N1 * ia, n2 = N2 * ia;
    o.n[0][l] = n0; o.n[1][l] = n1; o.n[2][l] = n2;
    o.mh[0][0][l] = (w1 * n2 - w2 * n1) * ia; o.mh[0][1][l] = (w2 * n0 - w0 * n2) * ia; o.mh[0][2][l] = (w0 * n1 - w1 * n0) * ia;
    o.mh[1][0][l] = (n1 * u2 - n2 * u1) * ia; o.mh[1][1][l] = (n2 * u0 - n0 * u2) * ia; o.mh[1][2][l] = (n0 * u1 - n1 * u0) * ia;
    T t0 = e1 * n2 - e2 * n1, t1 = e2 * n0 - e0 * n2, t2 = e0 * n1 - e1 * n0, ie3 = ie * ie * ie;
    o.mh[2][0][l] = t0 * ia; o.mh[2][1][l] = t1 * ia; o.mh[2][2][l] = t2 * ia;
    o.mc[0][l] = t0 * ie3; o.mc[1][l] = t1 * ie3; o.mc[2][l] = t2 * ie3;
  }
}

// Each block is written once and not read again here: streaming (non-temporal) stores skip the
// read-for-ownership of every output cache line, which otherwise doubles the memory traffic of this
// memory-bound kernel.  Callers issue a fence (sfence) after the loop.
template <typename T> static inline void store_block(T* dst, const T* src) {
#ifdef __AVX__
  if ((reinterpret_cast<uintptr_t>(dst) & 31) == 0) {
    constexpr int n = int(144 * sizeof(T) / 32);
    for (int v = 0; v < n; ++v)
      _mm256_stream_si256(reinterpret_cast<__m256i*>(dst) + v, _mm256_load_si256(reinterpret_cast<const __m256i*>(src) + v));
    return;
  }
#endif
  std::memcpy(dst, src, 144 * sizeof(T));
}

static inline void store_fence() {
#ifdef __AVX__
  _mm_sfence();
#endif
}

// both half-hinges (triangles A = x0 x1 x2, B = x0 x1 x3) of W stencils X[3 * vertex + axis][lane]
template <typename T> static inline void halves_tile(const T (*X)[W], Half<T>& hA, Half<T>& hB) {
  T E[3][W];
  for (int p = 0; p < 3; ++p) LANES E[p][l] = X[3 + p][l] - X[p][l];
  half_tile(X, X + 3, X + 6, E, hA);
  half_tile(X, X + 3, X + 9, E, hB);
}

// The 12x12 blocks of W hinges from their stencils X[3 * vertex + axis][lane] and psi' (d1), psi''
// (d2); written for the first nl lanes to out[l] (144 values) and the angle gradients to gout[l].
template <typename T, bool stream = true>
static inline void block_tile(const T (*X)[W], const T* d1, const T* d2, int nl, T* const* out, T* const* gout) {
  Half<T> hA, hB;
  halves_tile(X, hA, hB);
  // coefficients per stencil vertex: rho (times psi'), mh; vertex 3 is not in triangle A, 2 not in B
  T RA[4][W], RB[4][W], MA[4][3][W], MB[4][3][W], G[12][W];
  const int ia_[4] = {0, 1, 2, -1}, ib_[4] = {0, 1, -1, 2};
  for (int i = 0; i < 4; ++i) {
    int sa = ia_[i], sb = ib_[i];
    LANES {
      RA[i][l] = sa < 0 ? T(0) : d1[l] * hA.rho[sa][l];
      RB[i][l] = sb < 0 ? T(0) : d1[l] * hB.rho[sb][l];
    }
    for (int p = 0; p < 3; ++p) LANES {
      MA[i][p][l] = sa < 0 ? T(0) : hA.mh[sa][p][l];
      MB[i][p][l] = sb < 0 ? T(0) : hB.mh[sb][p][l];
      G[3 * i + p][l] = (sa < 0 ? T(0) : hA.rho[sa][l] * hA.n[p][l]) - (sb < 0 ? T(0) : hB.rho[sb][l] * hB.n[p][l]);
    }
  }
  // H[(i,p),(j,q)] = psi' (rhoA_i mhA_j[p] nA_q + rhoA_j mhA_i[q] nA_p - (same for B)) + psi'' g g^T
  // (upper triangle, r <= c, mirrored on output), plus the B terms on the (x0, x1) blocks
  // [[-B, B], [B^T, -B]]
  T O[144][W];
  for (int r = 0; r < 12; ++r) {
    int i = r / 3, p = r % 3;
    for (int c = r; c < 12; ++c) {
      int j = c / 3, q = c % 3;
      LANES O[12 * r + c][l] = RA[i][l] * MA[j][p][l] * hA.n[q][l] + RA[j][l] * MA[i][q][l] * hA.n[p][l]
                             - RB[i][l] * MB[j][p][l] * hB.n[q][l] - RB[j][l] * MB[i][q][l] * hB.n[p][l]
                             + d2[l] * G[r][l] * G[c][l];
    }
  }
  // B = psi' (nA mcA^T - nB mcB^T); symmetric only when both halves are valid, so it is applied as
  // is (as torchbend.geometry does) rather than mirrored
  T Bm[3][3][W];
  for (int p = 0; p < 3; ++p)
    for (int q = 0; q < 3; ++q) LANES Bm[p][q][l] = d1[l] * (hA.n[p][l] * hA.mc[q][l] - hB.n[p][l] * hB.mc[q][l]);
  for (int l = 0; l < nl; ++l) {
    alignas(64) T o[144];
    for (int r = 0; r < 12; ++r) {
      for (int c = 0; c < r; ++c) o[12 * r + c] = O[12 * c + r][l];
      for (int c = r; c < 12; ++c) o[12 * r + c] = O[12 * r + c][l];
    }
    for (int p = 0; p < 3; ++p)
      for (int q = 0; q < 3; ++q) {
        T B = Bm[p][q][l];
        o[12 * p + q] -= B;
        o[12 * p + 3 + q] += B;
        o[12 * (3 + q) + p] += B;
        o[12 * (3 + p) + 3 + q] -= B;
      }
    if (stream) store_block(out[l], o); else std::memcpy(out[l], o, sizeof(o));
    for (int k = 0; k < 12; ++k) gout[l][k] = G[k][l];
  }
}

template <typename T>
static void kernel(const T* x, const T* d1, const T* d2, T* out, T* gout, int64_t H) {
  int64_t tiles = (H + W - 1) / W;
  at::parallel_for(0, tiles, 32, [&](int64_t begin, int64_t end) {
    T X[12][W], a[W], b[W];
    T* op[W]; T* gp[W];
    for (int64_t t = begin; t < end; ++t) {
      int64_t h0 = t * W;
      int nl = int(std::min<int64_t>(W, H - h0));
      for (int l = 0; l < W; ++l) {
        bool live = l < nl;
        for (int k = 0; k < 12; ++k) X[k][l] = live ? x[12 * (h0 + l) + k] : T(0);
        a[l] = live ? d1[h0 + l] : T(0); b[l] = live ? d2[h0 + l] : T(0);
        op[l] = out + 144 * (h0 + l); gp[l] = gout + 12 * (h0 + l);
      }
      block_tile<T>(X, a, b, nl, op, gp);
    }
    store_fence();
  });
}

// phi(theta) and its first two derivatives (torchbend.models.phi): 0 quadratic, 1 tan, 2 sin
template <typename T> static inline void phi(int model, T t, T& f, T& f1, T& f2) {
  if (model == 0) { f = t; f1 = T(1); f2 = T(0); }
  else if (model == 1) { T u = std::tan(T(0.5) * t), s2 = T(1) + u * u; f = T(2) * u; f1 = s2; f2 = s2 * u; }
  else { T sn = std::sin(T(0.5) * t), cs = std::cos(T(0.5) * t); f = T(2) * sn; f1 = cs; f2 = T(-0.5) * sn; }
}
template <typename T> static inline T phi0(int model, T t) {
  if (model == 0) return t;
  if (model == 1) return T(2) * std::tan(T(0.5) * t);
  return T(2) * std::sin(T(0.5) * t);
}

// a per-hinge parameter given as a scalar (n == 1), one per hinge (n == H) or one per sample and hinge
template <typename T> struct Param {
  const T* p; int64_t n, H;
  inline T operator()(int64_t b, int64_t h) const { return n == 1 ? p[0] : (n == H ? p[h] : p[b * H + h]); }
};

// Stencil of one hinge into lane l of X; then psi' and psi'' of that lane at its bend angle
// theta = atan2(e_hat . (nA x nB), nA . nB), nA = e x (x2 - x0), nB = (x3 - x0) x e (SPEC formula, as
// torchbend.geometry; psi as torchbend.models.psi_theta_derivatives)
template <typename T> static inline void load_hinge(const T* xb, const int64_t* st, T (*X)[W], int l) {
  for (int v = 0; v < 4; ++v)
    for (int m = 0; m < 3; ++m) X[3 * v + m][l] = xb[3 * st[v] + m];
}

template <typename T>
static inline void hinge_psi(const T (*X)[W], int l, int model, T a, T k, T rest, bool damped, T c, T prev, T& d1, T& d2) {
  T e[3], u[3], w[3];
  for (int m = 0; m < 3; ++m) {
    e[m] = X[3 + m][l] - X[m][l]; u[m] = X[6 + m][l] - X[m][l]; w[m] = X[9 + m][l] - X[m][l];
  }
  T NA[3], NB[3], NN[3];
  cross(e, u, NA); cross(w, e, NB); cross(NA, NB, NN);
  T elen = std::sqrt(dot(e, e));
  T inv = elen > T(0) ? T(1) / elen : T(0);
  T theta = std::atan2(dot(e, NN) * inv, dot(NA, NB));
  T f, f1, f2;
  phi(model, theta, f, f1, f2);
  T s = k * (f - phi0(model, rest)), kc = k;
  if (damped) { s += c * (f - phi0(model, prev)); kc += c; }
  T two_a = T(2) * a;
  d1 = two_a * s * f1;
  d2 = two_a * (kc * f1 * f1 + s * f2);
}

// Everything in one pass: gather the stencil from x, theta (SPEC formula, as torchbend.geometry),
// psi' and psi'' (torchbend.models.psi_theta_derivatives), the block and the angle gradient.
template <typename T>
static void fused(const T* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H, Param<T> a, Param<T> k,
                  Param<T> rest, Param<T> c, Param<T> prev, bool damped, int model, T* out, T* gout, T* d2out) {
  int64_t tiles = (B * H + W - 1) / W;
  at::parallel_for(0, tiles, 32, [&](int64_t begin, int64_t end) {
    T X[12][W], D1[W], D2[W];
    T* op[W]; T* gp[W];
    for (int64_t t = begin; t < end; ++t) {
      int64_t bh0 = t * W;
      int nl = int(std::min<int64_t>(W, B * H - bh0));
      int64_t b = bh0 / H, h = bh0 - b * H - 1;  // sample and hinge of lane 0 (one division per tile)
      for (int l = 0; l < W; ++l) {
        if (l >= nl) {
          for (int m = 0; m < 12; ++m) X[m][l] = T(0);
          D1[l] = D2[l] = T(0);
          continue;
        }
        if (++h == H) { h = 0; ++b; }
        int64_t bh = bh0 + l;
        load_hinge(x + 3 * V * b, hinges + 4 * h, X, l);
        T c0 = damped ? c(b, h) : T(0), p0 = damped ? prev(b, h) : T(0);
        hinge_psi(X, l, model, a(b, h), k(b, h), rest(b, h), damped, c0, p0, D1[l], D2[l]);
        d2out[bh] = D2[l];
        op[l] = out + 144 * bh; gp[l] = gout + 12 * bh;
      }
      block_tile<T>(X, D1, D2, nl, op, gp);
    }
    store_fence();
  });
}

std::vector<torch::Tensor> hinge_hessians(torch::Tensor x4, torch::Tensor d1, torch::Tensor d2) {
  TORCH_CHECK(x4.device().is_cpu() && x4.is_contiguous() && x4.dim() == 3 && x4.size(1) == 4 && x4.size(2) == 3,
              "x4 must be a contiguous CPU (H, 4, 3) tensor");
  int64_t H = x4.size(0);
  TORCH_CHECK(d1.is_contiguous() && d2.is_contiguous() && d1.numel() == H && d2.numel() == H, "d1, d2 must be (H,)");
  auto out = torch::empty({H, 12, 12}, x4.options());
  auto g = torch::empty({H, 12}, x4.options());
  AT_DISPATCH_FLOATING_TYPES(x4.scalar_type(), "hinge_hessians", [&] {
    kernel<scalar_t>(x4.data_ptr<scalar_t>(), d1.data_ptr<scalar_t>(), d2.data_ptr<scalar_t>(),
                     out.data_ptr<scalar_t>(), g.data_ptr<scalar_t>(), H);
  });
  return {out, g};
}

template <typename T> static Param<T> param(const torch::Tensor& t, int64_t H) {
  return Param<T>{t.data_ptr<T>(), t.numel(), H};
}

// Positions x (..., V, 3); per-hinge parameters given as scalars, (H,) or (..., H) like x's batch;
// c and prev None without damping.  Returns (blocks (..., H, 12, 12), angle gradients (..., H, 12),
// psi'' (..., H), whether every coordinate of x is finite).
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, bool> bending_hessians(
    torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest,
    c10::optional<torch::Tensor> c_, c10::optional<torch::Tensor> prev_, int64_t model) {
  TORCH_CHECK(x.device().is_cpu() && x.dim() >= 2 && x.size(-1) == 3, "x must be a CPU (..., V, 3) tensor");
  TORCH_CHECK(hinges.dim() == 2 && hinges.size(1) == 4 && hinges.scalar_type() == torch::kLong,
              "hinges must be an int64 (H, 4) tensor");
  x = x.contiguous();
  hinges = hinges.contiguous();
  std::vector<int64_t> batch(x.sizes().begin(), x.sizes().end() - 2);
  int64_t V = x.size(-2), H = hinges.size(0), B = 1;
  for (auto s : batch) B *= s;
  bool damped = c_.has_value();
  auto prep = [&](torch::Tensor t) {
    t = t.to(x.scalar_type()).contiguous();
    int64_t n = t.numel();
    TORCH_CHECK(n == 1 || n == H || n == B * H, "a per-hinge parameter has ", n, " values; expected 1, H or B*H");
    return t;
  };
  a = prep(a); k = prep(k); rest = prep(rest);
  torch::Tensor c, prev;
  if (damped) { c = prep(*c_); prev = prep(*prev_); }
  std::vector<int64_t> sb = batch, sg = batch, sd = batch;
  sb.insert(sb.end(), {H, 12, 12}); sg.insert(sg.end(), {H, 12}); sd.push_back(H);
  auto out = torch::empty(sb, x.options());
  auto g = torch::empty(sg, x.options());
  auto d2 = torch::empty(sd, x.options());
  bool finite = true;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "bending_hessians", [&] {
    const scalar_t* xp = x.data_ptr<scalar_t>();
    for (int64_t i = 0, n = x.numel(); i < n; ++i) finite = finite && std::isfinite(xp[i]);
    Param<scalar_t> none{nullptr, 0, H};
    fused<scalar_t>(xp, hinges.data_ptr<int64_t>(), B, V, H, param<scalar_t>(a, H),
                    param<scalar_t>(k, H), param<scalar_t>(rest, H), damped ? param<scalar_t>(c, H) : none,
                    damped ? param<scalar_t>(prev, H) : none, damped, int(model), out.data_ptr<scalar_t>(),
                    g.data_ptr<scalar_t>(), d2.data_ptr<scalar_t>());
  });
  return {out, g, d2, finite};
}
// ----------------------------------------------------------------------------------------------
// Sparse assembly of the Hessian of one mesh into CSR values, both ways of torchbend.hessian:
// per hinge (scatter of the 12x12 blocks) and per triangle (paper sec. 4.1-4.2: psi'' g g^T per
// hinge, plus sum_h psi'_h Hess(theta_h) as one 9x9 block per triangle, eq. 7 with the conditional
// transpose; formulas in torchbend.hessian's docstring).  Serial: the scatter targets overlap.

// angle gradients of W hinges (G[3 * vertex + axis][lane])
template <typename T> static inline void grad_tile(const T (*X)[W], T (*G)[W]) {
  Half<T> hA, hB;
  halves_tile(X, hA, hB);
  for (int p = 0; p < 3; ++p) LANES {
    G[p][l] = hA.rho[0][l] * hA.n[p][l] - hB.rho[0][l] * hB.n[p][l];
    G[3 + p][l] = hA.rho[1][l] * hA.n[p][l] - hB.rho[1][l] * hB.n[p][l];
    G[6 + p][l] = hA.rho[2][l] * hA.n[p][l];
    G[9 + p][l] = -hB.rho[2][l] * hB.n[p][l];
  }
}

// 9x9 block (flat (3 i + p) * 9 + 3 j + q) of sum_h psi'_h Hess(theta_h) over the hinges of one
// triangle p0 p1 p2; c[k] = psi' of the hinge on edge k (opposite p_k; 0 on the boundary), sg[k] > 0
// where the triangle runs edge k in its global direction
template <typename T> static inline void face_block(const T* P0, const T* P1, const T* P2, const T* c, const int64_t* sg, T* o) {
  const T* P[3] = {P0, P1, P2};
  T e[3][3];
  for (int k = 0; k < 3; ++k)
    for (int m = 0; m < 3; ++m) e[k][m] = P[(k + 2) % 3][m] - P[(k + 1) % 3][m];
  T u[3] = {-e[1][0], -e[1][1], -e[1][2]}, N[3];
  cross(e[2], u, N);
  T ee[3] = {dot(e[0], e[0]), dot(e[1], e[1]), dot(e[2], e[2])};
  T area2 = std::sqrt(dot(N, N));
  bool valid = area2 > std::numeric_limits<T>::epsilon() * std::max(std::max(ee[0], ee[1]), ee[2]);
  if (!valid) { for (int m = 0; m < 81; ++m) o[m] = T(0); return; }
  T ia = T(1) / area2, n[3] = {N[0] * ia, N[1] * ia, N[2] * ia};
  T elen[3], ie[3], en[3][3], mh[3][3];
  for (int k = 0; k < 3; ++k) {
    elen[k] = std::sqrt(ee[k]); ie[k] = T(1) / elen[k];
    cross(e[k], n, en[k]);
    for (int m = 0; m < 3; ++m) mh[k][m] = en[k][m] * ia;
  }
  T cs[3], d[3];
  for (int k = 0; k < 3; ++k) cs[k] = -dot(e[(k + 1) % 3], e[(k + 2) % 3]) * ie[(k + 1) % 3] * ie[(k + 2) % 3];
  for (int k = 0; k < 3; ++k)
    d[k] = (c[(k + 1) % 3] * cs[(k + 2) % 3] + c[(k + 2) % 3] * cs[(k + 1) % 3] - c[k]) * (elen[k] * ia);
  T R[3][3][3];  // R_k = c_k n (e_k x n)^T / |e_k|^3
  for (int k = 0; k < 3; ++k) {
    T s = c[k] * ie[k] * ie[k] * ie[k];
    for (int p = 0; p < 3; ++p)
      for (int q = 0; q < 3; ++q) R[k][p][q] = s * n[p] * en[k][q];
  }
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      for (int p = 0; p < 3; ++p)
        for (int q = 0; q < 3; ++q) {
          T v = d[i] * mh[j][p] * n[q] + d[j] * n[p] * mh[i][q];
          if (i == j) {
            v -= R[(i + 1) % 3][p][q] + R[(i + 2) % 3][p][q];
          } else if (j == (i + 1) % 3) {  // edge k = i + 2 runs p_i -> p_{i+1}: R, or R^T if reversed
            int k = (i + 2) % 3;
            v += sg[k] > 0 ? R[k][p][q] : R[k][q][p];
          } else {  // j = i - 1: the transpose of block (j, i) of edge k = i + 1
            int k = (i + 1) % 3;
            v += sg[k] > 0 ? R[k][q][p] : R[k][p][q];
          }
          o[(3 * i + p) * 9 + 3 * j + q] = v;
        }
}

template <typename T>
static void assemble_impl(const T* x, const int64_t* hinges, int64_t H, Param<T> a, Param<T> k, Param<T> rest,
                          Param<T> c, Param<T> prev, bool damped, int model, const int64_t* hpos,
                          const int64_t* faces, const int64_t* feh, const int64_t* fes, const int64_t* fpos,
                          int64_t F, bool per_triangle, T* values) {
  std::vector<T> d1s(per_triangle ? H : 0);
  alignas(64) T buf[W][144];
  T gbuf[W][12];
  T X[12][W], D1[W], D2[W], G[12][W];
  T* op[W]; T* gp[W];
  for (int l = 0; l < W; ++l) { op[l] = buf[l]; gp[l] = gbuf[l]; }
  for (int64_t h0 = 0; h0 < H; h0 += W) {
    int nl = int(std::min<int64_t>(W, H - h0));
    for (int l = 0; l < W; ++l) {
      if (l >= nl) { for (int m = 0; m < 12; ++m) X[m][l] = T(0); D1[l] = D2[l] = T(0); continue; }
      int64_t h = h0 + l;
      load_hinge(x, hinges + 4 * h, X, l);
      hinge_psi(X, l, model, a(0, h), k(0, h), rest(0, h), damped, damped ? c(0, h) : T(0),
                damped ? prev(0, h) : T(0), D1[l], D2[l]);
    }
    if (!per_triangle) {
      block_tile<T, false>(X, D1, D2, nl, op, gp);
      for (int l = 0; l < nl; ++l) {
        const int64_t* pos = hpos + 144 * (h0 + l);
        for (int m = 0; m < 144; ++m) values[pos[m]] += buf[l][m];
      }
    } else {
      grad_tile(X, G);
      for (int l = 0; l < nl; ++l) {
        d1s[h0 + l] = D1[l];
        const int64_t* pos = hpos + 144 * (h0 + l);
        for (int r = 0; r < 12; ++r) {
          T gr = D2[l] * G[r][l];
          for (int cc = 0; cc < 12; ++cc) values[pos[12 * r + cc]] += gr * G[cc][l];
        }
      }
    }
  }
  if (!per_triangle) return;
  T blk[81];
  for (int64_t f = 0; f < F; ++f) {
    const int64_t* fh = feh + 3 * f;
    if (fh[0] < 0 && fh[1] < 0 && fh[2] < 0) continue;
    T cf[3] = {fh[0] >= 0 ? d1s[fh[0]] : T(0), fh[1] >= 0 ? d1s[fh[1]] : T(0), fh[2] >= 0 ? d1s[fh[2]] : T(0)};
    const int64_t* fv = faces + 3 * f;
    face_block(x + 3 * fv[0], x + 3 * fv[1], x + 3 * fv[2], cf, fes + 3 * f, blk);
    const int64_t* pos = fpos + 81 * f;
    for (int m = 0; m < 81; ++m) values[pos[m]] += blk[m];
  }
}

// CSR values (nnz,) of the Hessian of one mesh x (V, 3); parameters as in bending_hessians
torch::Tensor assemble(torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest,
                       c10::optional<torch::Tensor> c_, c10::optional<torch::Tensor> prev_, int64_t model,
                       torch::Tensor hinge_pos, torch::Tensor faces, torch::Tensor face_edge_hinges,
                       torch::Tensor face_edge_signs, torch::Tensor face_pos, int64_t nnz, bool per_triangle) {
  TORCH_CHECK(x.device().is_cpu() && x.dim() == 2 && x.size(1) == 3, "x must be a CPU (V, 3) tensor");
  x = x.contiguous();
  int64_t H = hinges.size(0), F = faces.size(0);
  auto prep = [&](torch::Tensor t) {
    t = t.to(x.scalar_type()).contiguous();
    TORCH_CHECK(t.numel() == 1 || t.numel() == H, "a per-hinge parameter has ", t.numel(), " values; expected 1 or H");
    return t;
  };
  auto idx = [](torch::Tensor t) { TORCH_CHECK(t.scalar_type() == torch::kLong, "index tensors must be int64"); return t.contiguous(); };
  a = prep(a); k = prep(k); rest = prep(rest);
  bool damped = c_.has_value();
  torch::Tensor c, prev;
  if (damped) { c = prep(*c_); prev = prep(*prev_); }
  hinges = idx(hinges); hinge_pos = idx(hinge_pos); faces = idx(faces);
  face_edge_hinges = idx(face_edge_hinges); face_edge_signs = idx(face_edge_signs); face_pos = idx(face_pos);
  TORCH_CHECK(hinge_pos.numel() == 144 * H && face_pos.numel() == 81 * F, "pattern does not match the mesh");
  auto values = torch::zeros({nnz}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "assemble", [&] {
    Param<scalar_t> none{nullptr, 0, H};
    assemble_impl<scalar_t>(x.data_ptr<scalar_t>(), hinges.data_ptr<int64_t>(), H, param<scalar_t>(a, H),
                            param<scalar_t>(k, H), param<scalar_t>(rest, H), damped ? param<scalar_t>(c, H) : none,
                            damped ? param<scalar_t>(prev, H) : none, damped, int(model),
                            hinge_pos.data_ptr<int64_t>(), faces.data_ptr<int64_t>(),
                            face_edge_hinges.data_ptr<int64_t>(), face_edge_signs.data_ptr<int64_t>(),
                            face_pos.data_ptr<int64_t>(), F, per_triangle, values.data_ptr<scalar_t>());
  });
  return values;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("hinge_hessians", &hinge_hessians, "per-hinge blocks from stencils and psi', psi''");
  m.def("bending_hessians", &bending_hessians, "fused gather, angle, psi and per-hinge blocks");
  m.def("assemble", &assemble, "CSR values of the bending Hessian of one mesh, per hinge or per triangle");
}
