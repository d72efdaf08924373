r"""Optional fused CPU kernel for the per-hinge 12x12 bending Hessians (C++, built on first use).

The eager-PyTorch path (:func:`torchbend.geometry.hinge_energy_hessian_soa`) is a chain of some
hundred elementwise passes over per-hinge arrays; it is memory bound.  This module compiles the same
closed form (the half-hinge factors of the tech report, sec. 6, and ``H = Y + Y^T`` with the B
terms, see :mod:`torchbend.geometry`) into one loop over hinges that keeps every intermediate in
registers and writes each 12x12 block once, parallel over hinges (``at::parallel_for``).

It is opt-in because the first call compiles C++ (``torch.utils.cpp_extension.load_inline``; about
a minute, cached afterwards in ``TORCH_EXTENSIONS_DIR``):

    import torchbend.native
    torchbend.native.enable()          # or TORCHBEND_NATIVE=1 in the environment

Once enabled, :meth:`BendingEnergy.hinge_hessians` (and everything built on the blocks: hinge
assembly, projections, the solver's preconditioner) uses it for CPU float32/float64 inputs when no
autograd graph is needed; otherwise, or if the build fails (a warning says why), the eager path
runs.  Both give the same blocks to round-off (tests compare them).

Large outputs are allocated as transparent huge pages (``madvise``): on the project's 2-core machine
the kernel then takes ~160-180 ns per hinge (float64) instead of ~550 with 4 KiB page faults, but a
call occasionally stalls (up to ~900 ns per hinge) while the OS compacts memory for huge pages.
"""
from __future__ import annotations

import os
import warnings

import torch
from torch import Tensor

__all__ = ["enable", "disable", "enabled", "available", "hinge_hessian_blocks"]

_SOURCE = r"""
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <cmath>
#include <limits>
#include <algorithm>
#include <cstdlib>
#include <sys/mman.h>
// Output blocks are large (1152 bytes per hinge in float64) and written once: a fresh glibc
// allocation above its mmap threshold page-faults on every 4 KiB page.  Large outputs are
// therefore allocated 2 MiB-aligned and advised as transparent huge pages (where the kernel
// allows it, 'madvise' mode), which removes most of that cost.
static torch::Tensor big_empty(std::vector<int64_t> sizes, const torch::TensorOptions& opt) {
  int64_t n = 1;
  for (auto s : sizes) n *= s;
  size_t bytes = size_t(n) * opt.dtype().itemsize();
  const size_t huge = size_t(2) << 20;
  if (bytes < 4 * huge) return torch::empty(sizes, opt);
  size_t rounded = (bytes + huge - 1) / huge * huge;
  void* p = nullptr;
  if (posix_memalign(&p, huge, rounded) != 0) return torch::empty(sizes, opt);
#ifdef MADV_HUGEPAGE
  madvise(p, rounded, MADV_HUGEPAGE);
#endif
  return torch::from_blob(p, sizes, [](void* q) { std::free(q); }, opt);
}

template <typename T> static inline void cross(const T* u, const T* v, T* o) {
  o[0] = u[1] * v[2] - u[2] * v[1]; o[1] = u[2] * v[0] - u[0] * v[2]; o[2] = u[0] * v[1] - u[1] * v[0];
}
template <typename T> static inline T dot(const T* u, const T* v) { return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]; }

// one half-hinge (a, b, c) = (x0, x1, wing): rho (3), unit normal n, mh[k] = m_k / h_k, mcs = m_c / |e|^2
template <typename T>
static inline void half(const T* a, const T* b, const T* c, const T* e, T* rho, T* n, T mh[3][3], T* mcs) {
  T u[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
  T w[3] = {c[0] - b[0], c[1] - b[1], c[2] - b[2]};
  T N[3]; cross(e, u, N);
  T ee = dot(e, e), uu = dot(u, u), ww = dot(w, w);
  T area2 = std::sqrt(dot(N, N)), elen = std::sqrt(ee);
  bool valid = area2 > std::numeric_limits<T>::epsilon() * std::max(std::max(ee, uu), ww);
  T ia = valid ? T(1) / area2 : T(0), ie = valid ? T(1) / elen : T(0);
  T s = ie * ia;
  rho[0] = -dot(e, w) * s; rho[1] = dot(e, u) * s; rho[2] = -elen * ia;
  for (int p = 0; p < 3; ++p) n[p] = N[p] * ia;
  T t[3];
  cross(w, n, t); for (int p = 0; p < 3; ++p) mh[0][p] = t[p] * ia;
  cross(n, u, t); for (int p = 0; p < 3; ++p) mh[1][p] = t[p] * ia;
  cross(e, n, t); for (int p = 0; p < 3; ++p) { mh[2][p] = t[p] * ia; mcs[p] = t[p] * ie * ie * ie; }
}

template <typename T>
static void kernel(const T* x, const T* d1, const T* d2, T* out, T* gout, int64_t H) {
  at::parallel_for(0, H, 256, [&](int64_t begin, int64_t end) {
    for (int64_t h = begin; h < end; ++h) {
      const T* s = x + 12 * h;
      const T *x0 = s, *x1 = s + 3, *x2 = s + 6, *x3 = s + 9;
      T e[3] = {x1[0] - x0[0], x1[1] - x0[1], x1[2] - x0[2]};
      T rA[3], nA[3], mA[3][3], cA[3], rB[3], nB[3], mB[3][3], cB[3];
      half(x0, x1, x2, e, rA, nA, mA, cA);
      half(x0, x1, x3, e, rB, nB, mB, cB);
      T a = d1[h], b = d2[h];
      // per stencil vertex i: coefficient of n_A and n_B in the gradient, and m_s/h_s rows
      T rhoA[4] = {rA[0], rA[1], rA[2], T(0)}, rhoB[4] = {rB[0], rB[1], T(0), rB[2]};
      T g[12];
      for (int i = 0; i < 4; ++i)
        for (int p = 0; p < 3; ++p) g[3 * i + p] = rhoA[i] * nA[p] - rhoB[i] * nB[p];
      const T zero3[3] = {T(0), T(0), T(0)};
      const T* mhA[4] = {mA[0], mA[1], mA[2], zero3};
      const T* mhB[4] = {mB[0], mB[1], zero3, mB[2]};
      T* o = out + 144 * h;
      // Y[(i,p),(j,q)] = d1 (rhoA_i mhA_j[p] nA_q - rhoB_i mhB_j[p] nB_q) + d2/2 g_(i,p) g_(j,q);  H = Y + Y^T
      T Y[144];
      for (int i = 0; i < 4; ++i) {
        T ai = a * rhoA[i], bi = a * rhoB[i];
        for (int p = 0; p < 3; ++p) {
          T hg = T(0.5) * b * g[3 * i + p];
          for (int j = 0; j < 4; ++j) {
            T ca = ai * mhA[j][p], cb = bi * mhB[j][p];
            T* row = Y + 12 * (3 * i + p) + 3 * j;
            for (int q = 0; q < 3; ++q) row[q] = ca * nA[q] - cb * nB[q] + hg * g[3 * j + q];
          }
        }
      }
      for (int r = 0; r < 12; ++r)
        for (int c = 0; c < 12; ++c) o[12 * r + c] = Y[12 * r + c] + Y[12 * c + r];
      // B terms on the (x0, x1) blocks: Bs = d1 (nA mcA^T - nB mcB^T);  [[-Bs, Bs], [Bs^T, -Bs]]
      for (int p = 0; p < 3; ++p)
        for (int q = 0; q < 3; ++q) {
          T B = a * (nA[p] * cA[q] - nB[p] * cB[q]);
          T Bt = a * (nA[q] * cA[p] - nB[q] * cB[p]);
          o[12 * p + q] -= B;
          o[12 * p + 3 + q] += B;
          o[12 * (3 + p) + q] += Bt;
          o[12 * (3 + p) + 3 + q] -= B;
        }
      for (int k = 0; k < 12; ++k) gout[12 * h + k] = g[k];
    }
  });

}

std::vector<torch::Tensor> hinge_hessians(torch::Tensor x4, torch::Tensor d1, torch::Tensor d2) {
  TORCH_CHECK(x4.device().is_cpu() && x4.is_contiguous() && x4.dim() == 3 && x4.size(1) == 4 && x4.size(2) == 3,
              "x4 must be a contiguous CPU (H, 4, 3) tensor");
  int64_t H = x4.size(0);
  TORCH_CHECK(d1.is_contiguous() && d2.is_contiguous() && d1.numel() == H && d2.numel() == H, "d1, d2 must be (H,)");
  auto out = big_empty({H, 12, 12}, x4.options());
  auto g = torch::empty({H, 12}, x4.options());
  AT_DISPATCH_FLOATING_TYPES(x4.scalar_type(), "hinge_hessians", [&] {
    kernel<scalar_t>(x4.data_ptr<scalar_t>(), d1.data_ptr<scalar_t>(), d2.data_ptr<scalar_t>(),
                     out.data_ptr<scalar_t>(), g.data_ptr<scalar_t>(), H);
  });
  return {out, g};
}
"""

_state = {"enabled": os.environ.get("TORCHBEND_NATIVE", "0") == "1", "module": None, "failed": None}


def _module():
    if _state["module"] is None and _state["failed"] is None:
        try:
            from torch.utils.cpp_extension import load_inline

            _state["module"] = load_inline(
                name="torchbend_native_v2", cpp_sources=[_SOURCE], functions=["hinge_hessians"],
                extra_cflags=["-O3", "-march=native", "-fopenmp"], extra_ldflags=["-fopenmp"], verbose=False)
        except Exception as e:  # no compiler, no ninja, ...
            _state["failed"] = f"{type(e).__name__}: {e}"
            warnings.warn(f"torchbend.native: could not build the C++ kernel ({_state['failed'][:300]}); "
                          "using the eager path", RuntimeWarning, stacklevel=3)
    return _state["module"]


def enable(build: bool = True) -> bool:
    """Use the fused kernel from now on; with ``build`` compile it now.  Returns whether it is usable."""
    _state["enabled"] = True
    return _module() is not None if build else True


def disable() -> None:
    """Back to the eager path."""
    _state["enabled"] = False


def enabled() -> bool:
    return bool(_state["enabled"])


def available() -> bool:
    """Whether the kernel is built (or can be built now)."""
    return _module() is not None


def hinge_hessian_blocks(x4: Tensor, d1: Tensor, d2: Tensor):
    """Fused ``(Hb (..., H, 12, 12), g (..., H, 12))``, or ``None`` where it does not apply
    (disabled, not built, non-CPU, other dtypes, or an autograd graph is being recorded)."""
    if not _state["enabled"] or x4.device.type != "cpu" or x4.dtype not in (torch.float32, torch.float64):
        return None
    if torch.is_grad_enabled() and any(t.requires_grad for t in (x4, d1, d2)):
        return None
    mod = _module()
    if mod is None:
        return None
    batch = x4.shape[:-2]
    d1 = d1.to(x4.dtype).expand(batch).contiguous().reshape(-1)
    d2 = d2.to(x4.dtype).expand(batch).contiguous().reshape(-1)
    Hb, g = mod.hinge_hessians(x4.detach().contiguous().reshape(-1, 4, 3), d1, d2)
    return Hb.reshape(batch + (12, 12)), g.reshape(batch + (12,))
