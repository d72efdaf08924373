// The membrane's compiled operators: the per-triangle (projected) Hessian blocks (membrane_blocks), the energy with
// its gradient (membrane_energy_gradient) and the Hessian-vector product (membrane_hvp) of every model, the
// per-triangle formulas of membrane_math.h in parallel chunks (at::parallel_for: torch's thread pool and its thread
// count), the sums over triangles in face order.
#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <initializer_list>
#include <type_traits>
#include <vector>

#include "cpu_membrane.h"
#include "cpu_membrane_lanes.h"
#include "cpu_ops.h"
#include "cpu_tiles.h"
#include "membrane_math.h"

namespace torchbend {
namespace cpu {

// What the membrane operators over positions x (..., V, 3) share (op names the operator in the messages): the
// argument checks (`same`: the tensors that must be CPU tensors of x's dtype), then x, faces, D, coef and the
// operator's `extra` tensors made contiguous, and every vertex index of the faces in [0, V).  Returns the number
// of samples.
static int64_t prepare_membrane(const char* op, Tensor& x, Tensor& faces, Tensor& D, Tensor& coef, const Tensor& mu,
                                const Tensor& lam, std::initializer_list<const Tensor*> same,
                                std::initializer_list<Tensor*> extra = {}) {
  TORCH_CHECK(x.dim() >= 2 && x.size(-1) == 3, op, ": x must be (..., V, 3)");
  TORCH_CHECK(faces.dim() == 2 && faces.size(1) == 3 && faces.scalar_type() == torch::kInt64,
              op, ": faces must be (T, 3) int64");
  const int64_t T = faces.size(0), V = x.size(-2);
  TORCH_CHECK(D.dim() == 3 && D.size(0) == T && D.size(1) == 3 && D.size(2) == 2, op, ": D must be (T, 3, 2)");
  TORCH_CHECK(coef.numel() == T && mu.numel() == 1 && lam.numel() == 1, op, ": coef (T,), one mu and one lam");
  for (const Tensor* p : same)
    TORCH_CHECK(p->scalar_type() == x.scalar_type() && p->device().is_cpu(), op, ": CPU tensors of x's dtype");
  TORCH_CHECK(x.device().is_cpu() && faces.device().is_cpu(), op, ": CPU tensors only");
  for (Tensor* t : {&x, &faces, &D, &coef}) *t = t->contiguous();
  for (Tensor* t : extra) *t = t->contiguous();
  const int64_t* fc = faces.data_ptr<int64_t>();
  for (int64_t e = 0; e < faces.numel(); ++e)
    TORCH_CHECK(fc[e] >= 0 && fc[e] < V, op, ": faces index out of range [0, ", V, ")");
  return x.numel() / std::max<int64_t>(V * 3, 1);
}

// energies (coef psi) and forces of the triangles [e0, e0 + nl) of one sample, nl <= kLanes: gathered per lane,
// the deformation, SVD, stress and forces over the lanes, written per triangle (at e - base); without forces
// (nullptr) the singular values alone (mem_energy_density: the Gram matrix's eigenvalues, no singular vectors)
template <typename T, int Model>
static void stress_tile(const T* xb, const int64_t* fc, const T* d, const T* c, T mu, T lam, int64_t e0, int nl,
                        int64_t base, T* psi, T* forces) {
  MembraneTile<T> g;
  gather_tile<T>(g, xb, nullptr, fc, d, c, e0, nl);
  alignas(64) T fs[9][kLanes], ps[kLanes];
  if (forces == nullptr) {
    TB_LANES_AGG(kLanes) {
      T F[6], N[3], p[2], lv[6], cs, sn, s1, s2, dd, b, r;
      lane_deformation(g.E, g.D, l, F);
      lane_normal(g.E, g.D, l, N);
      lane_singular_values(F, N, s1, s2, dd, b, r);
      ps[l] = g.c[l] * lane_density<T, Model, false>(s1, s2, mu, lam, p, lv, cs, sn);
    }
    for (int l = 0; l < nl; ++l) psi[e0 - base + l] = ps[l];
    return;
  }
  TB_LANES_AGG(kLanes) {
    T F[6], N[3], P[6];
    lane_deformation(g.E, g.D, l, F);
    lane_normal(g.E, g.D, l, N);
    const T ce = g.c[l];
    ps[l] = ce * lane_stress<T, Model>(F, N, mu, lam, P);
    lane_pull_back(P, g.D, ce, l, fs);
  }
  for (int l = 0; l < nl; ++l) {
    psi[e0 - base + l] = ps[l];
    for (int j = 0; j < 9; ++j) forces[9 * (e0 - base + l) + j] = fs[j][l];
  }
}

// Hessian-vector products h (coef dP D_k per vertex) and coef P : dF of the triangles [e0, e0 + nl) of one sample
// (nl <= kLanes) through the eigensystem: gathered per lane, lane_hvp over the lanes, written per triangle (at
// e - base)
template <typename T, int Model, int Proj>
static void hvp_tile(const T* xb, const T* vb, const int64_t* fc, const T* d, const T* c, T mu, T lam, int64_t e0,
                     int nl, int64_t base, T* dots, T* h) {
  MembraneTile<T> g;
  gather_tile<T>(g, xb, vb, fc, d, c, e0, nl);
  alignas(64) T hs[9][kLanes], ds[kLanes];
  TB_LANES_AGG(kLanes) {
    T F[6], N[3], dF[6], dP[6];
    lane_deformation(g.E, g.D, l, F);
    lane_normal(g.E, g.D, l, N);
    lane_deformation(g.dE, g.D, l, dF);
    const T ce = g.c[l];
    ds[l] = ce * lane_hvp<T, Model, Proj>(F, N, dF, mu, lam, dP);
    lane_pull_back(dP, g.D, ce, l, hs);
  }
  for (int l = 0; l < nl; ++l) {
    dots[e0 - base + l] = ds[l];
    for (int j = 0; j < 9; ++j) h[9 * (e0 - base + l) + j] = hs[j][l];
  }
}

// The (projected) Hessian blocks (81 per triangle, flat (3 k + i) x (3 l + j), membrane_face_block's layout and
// formulas) of the triangles [e0, e0 + nl) of one sample (nl <= kLanes), written to out (81 nl values): the thin SVD,
// the eigenvalues and the six modes over the lanes, coef sum_k proj(l_k) z_k z_k^T for vertices 1, 2, vertex 0's
// rows and columns from the translations' null space.  Returns whether every value written is finite.
template <typename T, int Model, int Proj>
static bool block_tile(const T* xb, const int64_t* fc, const T* d, const T* c, T mu, T lam, int64_t e0, int nl,
                       T* out) {
  MembraneTile<T> g;
  gather_tile<T>(g, xb, nullptr, fc, d, c, e0, nl);
  alignas(64) T Hs[81][kLanes];
  TB_LANES_AGG(kLanes) {
    T F[6], N[3];
    lane_deformation(g.E, g.D, l, F);
    lane_normal(g.E, g.D, l, N);
    const LaneSvd<T> o = lane_svd(F, N);
    T p[2], lv[6], cs, sn;
    lane_density<T, Model, true>(o.s1, o.s2, mu, lam, p, lv, cs, sn);
    const T ce = g.c[l];
    #pragma GCC unroll 6
    for (int k = 0; k < 6; ++k)
      lv[k] = ce * (Proj == kProjectClamp ? std::max(lv[k], T(0)) : Proj == kProjectAbs ? std::abs(lv[k]) : lv[k]);
    T w1[2], w2[2];  // (W v1)[m], (W v2)[m] for the vertices m = 1, 2
    #pragma GCC unroll 6
    for (int m = 0; m < 2; ++m) {
      const T d0 = g.D[2 * (m + 1)][l], d1 = g.D[2 * (m + 1) + 1][l];
      w1[m] = d0 * o.cp + d1 * o.sp;
      w2[m] = d1 * o.cp - d0 * o.sp;
    }
    const T h = T(0.70710678118654752440);
    T z[6][6];  // the six modes over (vertex m = 1, 2; axis a): index 3 (m - 1) + a
    #pragma GCC unroll 6
    for (int m = 0; m < 2; ++m)
      #pragma GCC unroll 6
      for (int a = 0; a < 3; ++a) {
        const T o11 = o.u1[a] * w1[m], o22 = o.u2[a] * w2[m], o21 = o.u2[a] * w1[m], o12 = o.u1[a] * w2[m];
        const int j = 3 * m + a;
        z[0][j] = cs * o11 + sn * o22;
        z[1][j] = cs * o22 - sn * o11;
        z[2][j] = h * (o21 - o12);
        z[3][j] = h * (o21 + o12);
        z[4][j] = o.n[a] * w1[m];
        z[5][j] = o.n[a] * w2[m];
      }
    T R[6][6];  // vertices 1, 2
    #pragma GCC unroll 6
    for (int r = 0; r < 6; ++r) {
      T lz[6];
      #pragma GCC unroll 6
      for (int k = 0; k < 6; ++k) lz[k] = lv[k] * z[k][r];
      #pragma GCC unroll 6
      for (int q = r; q < 6; ++q) {
        T acc = T(0);
        #pragma GCC unroll 6
        for (int k = 0; k < 6; ++k) acc += lz[k] * z[k][q];
        R[r][q] = acc;
        R[q][r] = acc;
      }
    }
    T C[3][6];  // vertex 0 against vertices 1, 2: minus the column sums over vertices 1, 2
    #pragma GCC unroll 6
    for (int a = 0; a < 3; ++a)
      #pragma GCC unroll 6
      for (int q = 0; q < 6; ++q) C[a][q] = -(R[a][q] + R[3 + a][q]);
    #pragma GCC unroll 6
    for (int a = 0; a < 3; ++a)
      #pragma GCC unroll 6
      for (int b = a; b < 3; ++b) {
        const T v = -(C[a][b] + C[a][3 + b]);  // vertex 0 against itself
        Hs[9 * a + b][l] = v;
        Hs[9 * b + a][l] = v;
      }
    #pragma GCC unroll 6
    for (int a = 0; a < 3; ++a)
      #pragma GCC unroll 6
      for (int q = 0; q < 6; ++q) {
        Hs[9 * a + 3 + q][l] = C[a][q];
        Hs[9 * (3 + q) + a][l] = C[a][q];
      }
    #pragma GCC unroll 6
    for (int r = 0; r < 6; ++r)
      #pragma GCC unroll 6
      for (int q = 0; q < 6; ++q) Hs[9 * (3 + r) + 3 + q][l] = R[r][q];
  }
  for (int l = 0; l < nl; ++l)
    for (int j = 0; j < 81; ++j) out[81 * l + j] = Hs[j][l];
  return all_finite(out, 81 * int64_t(nl));
}

// f(model, projection) with both as compile-time constants (std::integral_constant): one lane loop per model and
// projection (a select on a projection chosen at run time keeps GCC from vectorizing)
template <typename F>
static void with_model_projection(int64_t model, int64_t projection, F&& f) {
  auto proj = [&](auto m) {
    if (projection == kProjectClamp)
      f(m, std::integral_constant<int, kProjectClamp>{});
    else if (projection == kProjectAbs)
      f(m, std::integral_constant<int, kProjectAbs>{});
    else
      f(m, std::integral_constant<int, kProjectNone>{});
  };
  if (model == kStvk)
    proj(std::integral_constant<int, kStvk>{});
  else if (model == kArap)
    proj(std::integral_constant<int, kArap>{});
  else if (model == kNeohookean)
    proj(std::integral_constant<int, kNeohookean>{});
  else
    proj(std::integral_constant<int, kSymmetricDirichlet>{});
}

// the HVP tiles of the triangles [f0, f0 + n) of one sample into dots (n) and h (9 n), in parallel
template <typename T>
static void hvp_tiles(int64_t model, int64_t projection, const T* xb, const T* vb, const int64_t* fc, const T* d,
                      const T* c, T mu, T lam, int64_t f0, int64_t n, T* dots, T* h) {
  with_model_projection(model, projection, [&](auto m, auto p) {
    at::parallel_for(0, (n + kLanes - 1) / kLanes, 64, [&](int64_t begin, int64_t end) {
      for (int64_t g = begin; g < end; ++g)
        hvp_tile<T, decltype(m)::value, decltype(p)::value>(xb, vb, fc, d, c, mu, lam, f0 + g * kLanes,
                                                           int(std::min<int64_t>(kLanes, n - g * kLanes)), f0, dots, h);
    });
  });
}

// the energies (and forces) of the triangles [f0, f0 + n) of one sample into psi (n) and forces (9 n, or nullptr)
// for ARAP, symmetric Dirichlet and neo-Hookean (StVK has its closed form), in parallel
template <typename T, int Model>
static void stress_tiles(const T* xb, const int64_t* fc, const T* d, const T* c, T mu, T lam, int64_t f0, int64_t n,
                         T* psi, T* forces) {
  at::parallel_for(0, (n + kLanes - 1) / kLanes, 64, [&](int64_t begin, int64_t end) {
    for (int64_t g = begin; g < end; ++g)
      stress_tile<T, Model>(xb, fc, d, c, mu, lam, f0 + g * kLanes, int(std::min<int64_t>(kLanes, n - g * kLanes)), f0,
                            psi, forces);
  });
}

template <typename T>
static void stress_tiles(int64_t model, const T* xb, const int64_t* fc, const T* d, const T* c, T mu, T lam,
                         int64_t f0, int64_t n, T* psi, T* forces) {
  if (model == kArap)
    stress_tiles<T, kArap>(xb, fc, d, c, mu, lam, f0, n, psi, forces);
  else if (model == kNeohookean)
    stress_tiles<T, kNeohookean>(xb, fc, d, c, mu, lam, f0, n, psi, forces);
  else
    stress_tiles<T, kSymmetricDirichlet>(xb, fc, d, c, mu, lam, f0, n, psi, forces);
}

// the blocks of the triangles [f0, f0 + n) of one sample into out (81 n values), in parallel over tiles; returns
// whether every value is finite
template <typename T>
static bool block_tiles(int64_t model, int64_t projection, const T* xb, const int64_t* fc, const T* d, const T* c,
                        T mu, T lam, int64_t f0, int64_t n, T* out) {
  std::atomic<bool> finite{true};
  with_model_projection(model, projection, [&](auto m, auto p) {
    at::parallel_for(0, (n + kLanes - 1) / kLanes, 32, [&](int64_t begin, int64_t end) {
      bool ok = true;
      for (int64_t g = begin; g < end; ++g) {
        const int64_t i0 = g * kLanes;
        ok = block_tile<T, decltype(m)::value, decltype(p)::value>(xb, fc, d, c, mu, lam, f0 + i0,
                                                                  int(std::min<int64_t>(kLanes, n - i0)),
                                                                  out + 81 * i0) && ok;
      }
      if (!ok) finite.store(false, std::memory_order_relaxed);
    });
  });
  return finite.load();
}

static void check_model(const char* op, int64_t model, int64_t projection) {
  TORCH_CHECK(model >= kStvk && model <= kNeohookean, op, ": unknown membrane model ", model);
  TORCH_CHECK(projection >= kProjectNone && projection <= kProjectAbs, op, ": unknown projection ", projection);
}

std::tuple<Tensor, Tensor> membrane_energy_gradient(Tensor x, Tensor faces, Tensor D, Tensor coef, Tensor mu,
                                                    Tensor lam, Tensor weight, bool gradient, int64_t model) {
  const char* op = "membrane_energy_gradient";
  check_model(op, model, kProjectNone);
  const int64_t B = prepare_membrane(op, x, faces, D, coef, mu, lam, {&D, &coef, &mu, &lam, &weight}, {&weight});
  const int64_t T = faces.size(0), V = x.size(-2);
  const auto batch = x.sizes().slice(0, x.dim() - 2);
  TORCH_CHECK(!gradient || weight.numel() == B, op, ": one weight per sample");
  const int64_t* fc = faces.data_ptr<int64_t>();
  Tensor energy = torch::empty(batch, x.options());
  Tensor grad = gradient ? torch::zeros(x.sizes(), x.options()) : torch::empty({0}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "membrane_energy_gradient", [&] {
    const scalar_t* d = D.data_ptr<scalar_t>();
    const scalar_t* c = coef.data_ptr<scalar_t>();
    const scalar_t m = mu.item<scalar_t>(), la = lam.item<scalar_t>();
    const int64_t cap = std::min(T, kFaceChunk);  // the chunk's energies and forces stay in cache for the sums
    std::vector<scalar_t> psi(cap), forces(gradient ? 9 * cap : 0);
    scalar_t* f = gradient ? forces.data() : nullptr;
    for (int64_t b = 0; b < B; ++b) {
      const scalar_t* xb = x.data_ptr<scalar_t>() + b * V * 3;
      const scalar_t w = gradient ? weight.data_ptr<scalar_t>()[b] : scalar_t(0);
      scalar_t* gb = gradient ? grad.data_ptr<scalar_t>() + b * V * 3 : nullptr;
      scalar_t total = 0;
      for (int64_t c0 = 0; c0 < T; c0 += kFaceChunk) {
        const int64_t n = std::min(kFaceChunk, T - c0);
        if (model != kStvk) {  // the thin SVD over the lanes of tiles (branch-free, no library calls)
          stress_tiles<scalar_t>(model, xb, fc, d, c, m, la, c0, n, psi.data(), f);
        } else {
          at::parallel_for(0, n, 512, [&](int64_t begin, int64_t end) {
            for (int64_t i = begin; i < end; ++i) {
              const int64_t* t = fc + 3 * (c0 + i);
              psi[i] = membrane_face<scalar_t>(int(model), xb + 3 * t[0], xb + 3 * t[1], xb + 3 * t[2],
                                               d + 6 * (c0 + i), m, la, c[c0 + i], f == nullptr ? f : f + 9 * i);
            }
          });
        }
        for (int64_t i = 0; i < n; ++i) total += psi[i];  // in face order: deterministic
        if (gradient)  // the scatter in face order: deterministic, whatever the threads
          for (int64_t i = 0; i < n; ++i)
            for (int k = 0; k < 3; ++k)
              for (int a = 0; a < 3; ++a) gb[3 * fc[3 * (c0 + i) + k] + a] += w * forces[9 * i + 3 * k + a];
      }
      energy.data_ptr<scalar_t>()[b] = total;
    }
  });
  return {energy, grad};
}

std::tuple<Tensor, Tensor> membrane_hvp(Tensor x, Tensor v, Tensor faces, Tensor D, Tensor coef, Tensor mu,
                                        Tensor lam, Tensor weight, int64_t model, int64_t projection) {
  const char* op = "membrane_hvp";
  check_model(op, model, projection);
  const int64_t B =
      prepare_membrane(op, x, faces, D, coef, mu, lam, {&v, &D, &coef, &mu, &lam, &weight}, {&v, &weight});
  const int64_t T = faces.size(0), V = x.size(-2);
  TORCH_CHECK(v.sizes() == x.sizes(), op, ": v must have x's shape (..., V, 3)");
  TORCH_CHECK(weight.numel() == B, op, ": one weight per sample");
  const int64_t* fc = faces.data_ptr<int64_t>();
  Tensor hv = torch::zeros(x.sizes(), x.options());
  Tensor dot = torch::empty(x.sizes().slice(0, x.dim() - 2), x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "membrane_hvp", [&] {
    const scalar_t* d = D.data_ptr<scalar_t>();
    const scalar_t* c = coef.data_ptr<scalar_t>();
    const scalar_t m = mu.item<scalar_t>(), la = lam.item<scalar_t>();
    const int64_t cap = std::min(T, kFaceChunk);  // the chunk's products stay in cache for the scatter
    std::vector<scalar_t> h(9 * cap), dots(cap);
    for (int64_t b = 0; b < B; ++b) {
      const scalar_t* xb = x.data_ptr<scalar_t>() + b * V * 3;
      const scalar_t* vb = v.data_ptr<scalar_t>() + b * V * 3;
      const scalar_t w = weight.data_ptr<scalar_t>()[b];
      scalar_t* hb = hv.data_ptr<scalar_t>() + b * V * 3;
      scalar_t total = 0;
      for (int64_t c0 = 0; c0 < T; c0 += kFaceChunk) {
        const int64_t n = std::min(kFaceChunk, T - c0);
        if (model != kStvk || projection != kProjectNone) {  // the eigensystem over the lanes of tiles
          hvp_tiles<scalar_t>(model, projection, xb, vb, fc, d, c, m, la, c0, n, dots.data(), h.data());
        } else {  // unprojected StVK in closed form, per triangle
          at::parallel_for(0, n, 512, [&](int64_t begin, int64_t end) {
            for (int64_t i = begin; i < end; ++i) {
              const int64_t e = c0 + i;
              const int64_t* t = fc + 3 * e;
              dots[i] = membrane_face_hvp<scalar_t>(int(model), int(projection), xb + 3 * t[0], xb + 3 * t[1],
                                                    xb + 3 * t[2], vb + 3 * t[0], vb + 3 * t[1], vb + 3 * t[2],
                                                    d + 6 * e, m, la, c[e], h.data() + 9 * i);
            }
          });
        }
        for (int64_t i = 0; i < n; ++i) {  // in face order: deterministic
          total += dots[i];
          for (int k = 0; k < 3; ++k)
            for (int a = 0; a < 3; ++a) hb[3 * fc[3 * (c0 + i) + k] + a] += w * h[9 * i + 3 * k + a];
        }
      }
      dot.data_ptr<scalar_t>()[b] = total;
    }
  });
  return {hv, dot};
}

std::tuple<Tensor, bool> membrane_blocks(Tensor x, Tensor faces, Tensor D, Tensor coef, Tensor mu, Tensor lam,
                                         int64_t model, int64_t projection) {
  const char* op = "membrane_blocks";
  check_model(op, model, projection);
  const int64_t B = prepare_membrane(op, x, faces, D, coef, mu, lam, {&D, &coef, &mu, &lam});
  const int64_t T = faces.size(0), V = x.size(-2);
  std::vector<int64_t> shape(x.sizes().begin(), x.sizes().end() - 2);
  shape.insert(shape.end(), {T, 9, 9});
  Tensor out = pooled_empty(shape, x.options());  // huge pages for a large output (cpu_tiles.cpp)
  std::atomic<bool> finite{true};
  const int64_t* fc = faces.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "membrane_blocks", [&] {
    const scalar_t* d = D.data_ptr<scalar_t>();
    const scalar_t* c = coef.data_ptr<scalar_t>();
    const scalar_t m = mu.item<scalar_t>(), la = lam.item<scalar_t>();
    for (int64_t b = 0; b < B; ++b) {
      const scalar_t* xb = x.data_ptr<scalar_t>() + b * V * 3;
      scalar_t* o = out.data_ptr<scalar_t>() + b * T * 81;
      if (model != kStvk || projection != kProjectNone) {  // the eigensystem over the lanes of tiles
        if (!block_tiles<scalar_t>(model, projection, xb, fc, d, c, m, la, 0, T, o)) finite.store(false);
        continue;
      }
      at::parallel_for(0, T, 1024, [&](int64_t begin, int64_t end) {
        bool ok = true;
        for (int64_t e = begin; e < end; ++e) {
          const int64_t* t = fc + 3 * e;
          scalar_t* H = o + 81 * e;
          membrane_face_block<scalar_t>(int(model), int(projection), xb + 3 * t[0], xb + 3 * t[1], xb + 3 * t[2],
                                        d + 6 * e, m, la, c[e], H);
          ok = all_finite(H, 81) && ok;  // on the block just written, in L1
        }
        if (!ok) finite.store(false, std::memory_order_relaxed);
      });
    }
  });
  return {out, finite.load()};
}


Tensor membrane_assemble(Tensor x, Tensor faces, Tensor D, Tensor coef, Tensor mu, Tensor lam, int64_t model,
                         int64_t projection, Tensor blocks, Tensor row_len, int64_t nnz) {
  const char* op = "membrane_assemble";
  check_model(op, model, projection);
  TORCH_CHECK(x.dim() == 2, op, ": one mesh, x (V, 3)");
  prepare_membrane(op, x, faces, D, coef, mu, lam, {&D, &coef, &mu, &lam}, {&blocks, &row_len});
  const int64_t T = faces.size(0), V = x.size(-2);
  TORCH_CHECK(blocks.scalar_type() == torch::kInt64 && blocks.numel() == 9 * T && blocks.device().is_cpu(), op,
              ": blocks must be (T, 9) int64 CSR positions of the vertex pairs' 3x3 blocks");
  TORCH_CHECK(row_len.scalar_type() == torch::kInt64 && row_len.numel() == V && row_len.device().is_cpu(), op,
              ": row_len must be (V,) int64");
  const int64_t* fc = faces.data_ptr<int64_t>();
  const int64_t* bs = blocks.data_ptr<int64_t>();
  const int64_t* rl = row_len.data_ptr<int64_t>();
  for (int64_t e = 0; e < T; ++e)  // every entry base + i row_len + j (i, j < 3) inside the values
    for (int k = 0; k < 3; ++k)
      for (int l = 0; l < 3; ++l) {
        const int64_t base = bs[9 * e + 3 * k + l], r = rl[fc[3 * e + k]];
        TORCH_CHECK(base >= 0 && r >= 0 && base + 2 * r + 2 < nnz, op, ": blocks out of range [0, ", nnz, ")");
      }
  Tensor values = torch::zeros({nnz}, x.options());
  bool finite = true;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "membrane_assemble", [&] {
    const scalar_t* d = D.data_ptr<scalar_t>();
    const scalar_t* c = coef.data_ptr<scalar_t>();
    const scalar_t m = mu.item<scalar_t>(), la = lam.item<scalar_t>();
    const scalar_t* xb = x.data_ptr<scalar_t>();
    scalar_t* out = values.data_ptr<scalar_t>();
    // chunks of triangles: their blocks computed in parallel into a buffer that stays in cache, then added to the
    // values in face order (deterministic, whatever the threads): entry (3 k + i, 3 l + j) of a triangle's block at
    // blocks[k l] + i row_len[vertex k] + j
    constexpr int64_t kChunk = 2048;
    std::vector<scalar_t> buf(size_t(std::min(T, kChunk)) * 81);
    for (int64_t c0 = 0; c0 < T; c0 += kChunk) {
      const int64_t n = std::min(kChunk, T - c0);
      std::atomic<bool> ok{true};
      if (model != kStvk || projection != kProjectNone) {  // the eigensystem over the lanes of tiles
        ok.store(block_tiles<scalar_t>(model, projection, xb, fc, d, c, m, la, c0, n, buf.data()));
      } else {  // unprojected StVK in closed form, per triangle
        at::parallel_for(0, n, 256, [&](int64_t begin, int64_t end) {
          bool good = true;
          for (int64_t i = begin; i < end; ++i) {
            const int64_t e = c0 + i;
            const int64_t* t = fc + 3 * e;
            scalar_t* H = buf.data() + 81 * i;
            membrane_face_block<scalar_t>(int(model), int(projection), xb + 3 * t[0], xb + 3 * t[1], xb + 3 * t[2],
                                          d + 6 * e, m, la, c[e], H);
            good = all_finite(H, 81) && good;
          }
          if (!good) ok.store(false, std::memory_order_relaxed);
        });
      }
      finite = finite && ok.load();
      for (int64_t i = 0; i < n; ++i) {
        const int64_t e = c0 + i;
        const scalar_t* H = buf.data() + 81 * i;
        for (int k = 0; k < 3; ++k) {
          const int64_t r = rl[fc[3 * e + k]];
          for (int l = 0; l < 3; ++l) {
            scalar_t* o = out + bs[9 * e + 3 * k + l];
            for (int p = 0; p < 3; ++p)
              for (int q = 0; q < 3; ++q) o[p * r + q] += H[9 * (3 * k + p) + 3 * l + q];
          }
        }
      }
    }
  });
  return finite ? values : torch::empty({0}, x.options());
}

}  // namespace cpu
}  // namespace torchbend
