// The membrane's compiled operators: the per-triangle (projected) Hessian blocks (membrane_blocks), the energy with
// its gradient (membrane_energy_gradient) and the Hessian-vector product (membrane_hvp) of every model, the
// per-triangle formulas of membrane_math.h in parallel chunks (at::parallel_for: torch's thread pool and its thread
// count), the sums over triangles in face order.
#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <initializer_list>
#include <vector>

#include "cpu_membrane.h"
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

// ---- the thin SVD and stress of ARAP, symmetric Dirichlet and neo-Hookean over the lanes of a tile --------------
// The scalar membrane_math.h functions call the C library's hypot (and log) and branch.  These lane versions compute
// both the fast and the scaled hypot and select, select instead of branching, and take neo-Hookean's log J from
// vector_math.h's tb_logv (no library call); the formulas and their order are mem_thin_svd's and mem_density's
// (order 1).  GCC does not vectorize the lane loop ("control flow in loop"), but the branch-free, call-free code
// runs ARAP's and symmetric Dirichlet's gradient 2.6x faster than the scalar functions (bm_membrane.py --operators).
// StVK has its own closed form.
constexpr int kLanes = 8;

template <typename T>
static inline T lane_hypot(T a, T b) {
  const T aa = std::abs(a), bb = std::abs(b);
  const T big = aa > bb ? aa : bb, small = aa > bb ? bb : aa;
  const T q = small / (big > T(0) ? big : T(1));
  const T slow = big * std::sqrt(T(1) + q * q);
  return mem_squares_safe(big) ? std::sqrt(a * a + b * b) : slow;
}

template <typename T>
static inline T lane_hypot3(T a, T b, T c) {
  const T big = std::max(std::max(std::abs(a), std::abs(b)), std::abs(c));
  const T inv = T(1) / (big > T(0) ? big : T(1));
  const T sa = a * inv, sb = b * inv, sc = c * inv;
  const T slow = big * std::sqrt(sa * sa + sb * sb + sc * sc);
  return mem_squares_safe(big) ? std::sqrt(a * a + b * b + c * c) : slow;
}

// psi and P = dPsi/dF (row-major, P[j] for j = 2 a + b) of one triangle of ARAP, symmetric Dirichlet or neo-Hookean
// (log J by tb_logv, no library call) from F and N
template <typename T, int Model>
static inline T lane_stress(const T (&F)[6], const T (&N)[3], T mu, T lam, T* P) {
  const T a = F[0] * F[0] + F[2] * F[2] + F[4] * F[4];
  const T b = F[0] * F[1] + F[2] * F[3] + F[4] * F[5];
  const T c = F[1] * F[1] + F[3] * F[3] + F[5] * F[5];
  const T d = T(0.5) * a - T(0.5) * c;
  const T r = lane_hypot(d, b);
  const T s1 = std::sqrt((T(0.5) * a + T(0.5) * c) + r);
  const T J = lane_hypot3(N[0], N[1], N[2]);
  const T s2 = s1 > T(0) ? J / (s1 > T(0) ? s1 : T(1)) : T(0);
  // v1 = (cp, sp) (mem_unit_eigvec)
  const bool pos = d >= T(0);
  const T ex = pos ? d + r : b, ey = pos ? b : r - d;
  const T nrm = lane_hypot(ex, ey);
  const T inv = T(1) / (nrm > T(0) ? nrm : T(1));
  const T cp = nrm > T(0) ? ex * inv : T(1), sp = nrm > T(0) ? ey * inv : T(0);
  // u1 = F v1 / |F v1|
  const T w0 = F[0] * cp + F[1] * sp, w1 = F[2] * cp + F[3] * sp, w2 = F[4] * cp + F[5] * sp;
  const T nw = lane_hypot3(w0, w1, w2);
  const T iw = T(1) / (nw > T(0) ? nw : T(1));
  const T u10 = nw > T(0) ? w0 * iw : T(1), u11 = nw > T(0) ? w1 * iw : T(0), u12 = nw > T(0) ? w2 * iw : T(0);
  // n: N made orthogonal to u1, else a unit vector perpendicular to u1
  const T cu = N[0] * u10 + N[1] * u11 + N[2] * u12;
  const T m0 = N[0] - cu * u10, m1 = N[1] - cu * u11, m2 = N[2] - cu * u12;
  const T nm = lane_hypot3(m0, m1, m2);
  const bool okn = nm > tb_tiny(T(0)) / tb_eps(T(0));
  const T im = T(1) / (okn ? nm : T(1));
  const bool use_y = std::abs(u10) > T(0.9);
  const T al0 = use_y ? T(0) : T(1), al1 = use_y ? T(1) : T(0);
  const T q0 = -u12 * al1, q1 = u12 * al0, q2 = u10 * al1 - u11 * al0;  // u1 x (al0, al1, 0)
  const T iq = T(1) / std::sqrt(q0 * q0 + q1 * q1 + q2 * q2);
  const T n0 = okn ? m0 * im : q0 * iq, n1 = okn ? m1 * im : q1 * iq, n2 = okn ? m2 * im : q2 * iq;
  const T u20 = n1 * u12 - n2 * u11, u21 = n2 * u10 - n0 * u12, u22 = n0 * u11 - n1 * u10;
  // the density in the singular values (mem_density, order 1)
  T psi, p1, p2;
  if (Model == kArap) {
    const T d1 = s1 - T(1), d2 = s2 - T(1);
    psi = mu * (d1 * d1 + d2 * d2);
    const T two = T(2) * mu;
    p1 = two * d1;
    p2 = two * d2;
  } else if (Model == kNeohookean) {
    const T lj = tb_logv(s1) + tb_logv(s2);  // log J (J = s1 s2 may underflow where s1, s2 do not)
    const T q1 = (s1 - T(1)) * (s1 + T(1)), q2 = (s2 - T(1)) * (s2 + T(1));
    psi = T(0.5) * mu * (q1 + q2) - mu * lj + T(0.5) * lam * lj * lj;
    const T i1 = T(1) / s1, i2 = T(1) / s2;
    p1 = (mu * q1 + lam * lj) * i1;
    p2 = (mu * q2 + lam * lj) * i2;
  } else {  // symmetric Dirichlet
    const T i1 = T(1) / s1, i2 = T(1) / s2;
    const T d1 = (s1 - T(1)) * (s1 + T(1)) * i1, d2 = (s2 - T(1)) * (s2 + T(1)) * i2;
    psi = (mu * d1) * d1 + (mu * d2) * d2;
    const T two = T(2) * mu;
    p1 = (two * d1) * (T(1) + i1 * i1);
    p2 = (two * d2) * (T(1) + i2 * i2);
  }
  P[0] = p1 * u10 * cp - p2 * u20 * sp;
  P[1] = p1 * u10 * sp + p2 * u20 * cp;
  P[2] = p1 * u11 * cp - p2 * u21 * sp;
  P[3] = p1 * u11 * sp + p2 * u21 * cp;
  P[4] = p1 * u12 * cp - p2 * u22 * sp;
  P[5] = p1 * u12 * sp + p2 * u22 * cp;
  return psi;
}

// energies (coef psi) and forces of the triangles [e0, e0 + nl) of one sample, nl <= kLanes: gathered per lane,
// the SVD and stress over the lanes, the forces written per triangle
template <typename T, int Model>
static void stress_tile(const T* xb, const int64_t* fc, const T* d, const T* c, T mu, T lam, int64_t e0, int nl,
                        T* psi, T* forces) {
  alignas(64) T Fs[6][kLanes], Ns[3][kLanes], Ps[6][kLanes], ps[kLanes];
  for (int l = 0; l < kLanes; ++l) {
    T F[6] = {T(1), T(0), T(0), T(1), T(0), T(0)}, N[3] = {T(0), T(0), T(1)};  // idle lanes: at rest
    if (l < nl) {
      const int64_t e = e0 + l;
      const int64_t* t = fc + 3 * e;
      face_deformation(xb + 3 * t[0], xb + 3 * t[1], xb + 3 * t[2], d + 6 * e, F);
      face_normal(xb + 3 * t[0], xb + 3 * t[1], xb + 3 * t[2], d + 6 * e, N);
    }
    for (int j = 0; j < 6; ++j) Fs[j][l] = F[j];
    for (int j = 0; j < 3; ++j) Ns[j][l] = N[j];
  }
  TB_LANES_AGG(kLanes) {
    const T F[6] = {Fs[0][l], Fs[1][l], Fs[2][l], Fs[3][l], Fs[4][l], Fs[5][l]};
    const T N[3] = {Ns[0][l], Ns[1][l], Ns[2][l]};
    T P[6];
    ps[l] = lane_stress<T, Model>(F, N, mu, lam, P);
    Ps[0][l] = P[0]; Ps[1][l] = P[1]; Ps[2][l] = P[2]; Ps[3][l] = P[3]; Ps[4][l] = P[4]; Ps[5][l] = P[5];
  }
  for (int l = 0; l < nl; ++l) {
    const int64_t e = e0 + l;
    const T ce = c[e];
    psi[e] = ce * ps[l];
    if (forces == nullptr) continue;
    const T* De = d + 6 * e;
    for (int i = 0; i < 3; ++i) {
      const T P0 = ce * Ps[2 * i][l], P1 = ce * Ps[2 * i + 1][l];
      for (int k = 0; k < 3; ++k) forces[9 * e + 3 * k + i] = P0 * De[2 * k] + P1 * De[2 * k + 1];
    }
  }
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
    std::vector<scalar_t> psi(T), forces(gradient ? 9 * T : 0);
    for (int64_t b = 0; b < B; ++b) {
      const scalar_t* xb = x.data_ptr<scalar_t>() + b * V * 3;
      if (gradient && model != kStvk) {  // the thin SVD over the lanes of tiles (branch-free, no library calls)
        const int64_t tiles = (T + kLanes - 1) / kLanes;
        at::parallel_for(0, tiles, 256, [&](int64_t begin, int64_t end) {
          for (int64_t g = begin; g < end; ++g) {
            const int64_t e0 = g * kLanes;
            const int nl = int(std::min<int64_t>(kLanes, T - e0));
            if (model == kArap)
              stress_tile<scalar_t, kArap>(xb, fc, d, c, m, la, e0, nl, psi.data(), forces.data());
            else if (model == kNeohookean)
              stress_tile<scalar_t, kNeohookean>(xb, fc, d, c, m, la, e0, nl, psi.data(), forces.data());
            else
              stress_tile<scalar_t, kSymmetricDirichlet>(xb, fc, d, c, m, la, e0, nl, psi.data(), forces.data());
          }
        });
      } else {
        at::parallel_for(0, T, 2048, [&](int64_t begin, int64_t end) {
          for (int64_t e = begin; e < end; ++e) {
            const int64_t* t = fc + 3 * e;
            psi[e] = membrane_face<scalar_t>(int(model), xb + 3 * t[0], xb + 3 * t[1], xb + 3 * t[2], d + 6 * e, m,
                                             la, c[e], gradient ? forces.data() + 9 * e : nullptr);
          }
        });
      }
      scalar_t total = 0;  // in face order: deterministic
      for (int64_t e = 0; e < T; ++e) total += psi[e];
      energy.data_ptr<scalar_t>()[b] = total;
      if (gradient) {  // the scatter in face order: deterministic, whatever the threads
        const scalar_t w = weight.data_ptr<scalar_t>()[b];
        scalar_t* gb = grad.data_ptr<scalar_t>() + b * V * 3;
        for (int64_t e = 0; e < T; ++e)
          for (int k = 0; k < 3; ++k)
            for (int i = 0; i < 3; ++i) gb[3 * fc[3 * e + k] + i] += w * forces[9 * e + 3 * k + i];
      }
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
    std::vector<scalar_t> h(9 * T), dots(T);
    for (int64_t b = 0; b < B; ++b) {
      const scalar_t* xb = x.data_ptr<scalar_t>() + b * V * 3;
      const scalar_t* vb = v.data_ptr<scalar_t>() + b * V * 3;
      at::parallel_for(0, T, 2048, [&](int64_t begin, int64_t end) {
        for (int64_t e = begin; e < end; ++e) {
          const int64_t* t = fc + 3 * e;
          dots[e] = membrane_face_hvp<scalar_t>(int(model), int(projection), xb + 3 * t[0], xb + 3 * t[1],
                                                xb + 3 * t[2], vb + 3 * t[0], vb + 3 * t[1], vb + 3 * t[2], d + 6 * e,
                                                m, la, c[e], h.data() + 9 * e);
        }
      });
      const scalar_t w = weight.data_ptr<scalar_t>()[b];
      scalar_t* hb = hv.data_ptr<scalar_t>() + b * V * 3;
      scalar_t total = 0;
      for (int64_t e = 0; e < T; ++e) {  // in face order: deterministic
        total += dots[e];
        for (int k = 0; k < 3; ++k)
          for (int i = 0; i < 3; ++i) hb[3 * fc[3 * e + k] + i] += w * h[9 * e + 3 * k + i];
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
