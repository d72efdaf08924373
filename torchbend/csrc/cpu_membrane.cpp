// The membrane's compiled operators: the per-triangle (projected) Hessian blocks (membrane_blocks), the energy with
// its gradient (membrane_energy_gradient) and the Hessian-vector product (membrane_hvp) of every model, the
// per-triangle formulas of membrane_math.h in parallel chunks (at::parallel_for: torch's thread pool and its thread
// count), the sums over triangles in face order.
#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <initializer_list>
#include <vector>

#include "cpu_membrane.h"
#include "cpu_ops.h"
#include "cpu_tiles.h"
#include "membrane_math.h"

namespace torchbend {
namespace cpu {

// The checks the StVK operators over positions x (..., V, 3) share (op names the operator in the messages); `same`:
// the tensors that must be CPU tensors of x's dtype.  Returns the number of samples.
static int64_t check_membrane(const char* op, const Tensor& x, const Tensor& faces, const Tensor& D, const Tensor& coef,
                          const Tensor& mu, const Tensor& lam, std::initializer_list<const Tensor*> same) {
  TORCH_CHECK(x.dim() >= 2 && x.size(-1) == 3, op, ": x must be (..., V, 3)");
  TORCH_CHECK(faces.dim() == 2 && faces.size(1) == 3 && faces.scalar_type() == torch::kInt64,
              op, ": faces must be (T, 3) int64");
  const int64_t T = faces.size(0), V = x.size(-2);
  TORCH_CHECK(D.dim() == 3 && D.size(0) == T && D.size(1) == 3 && D.size(2) == 2, op, ": D must be (T, 3, 2)");
  TORCH_CHECK(coef.numel() == T && mu.numel() == 1 && lam.numel() == 1, op, ": coef (T,), one mu and one lam");
  for (const Tensor* p : same)
    TORCH_CHECK(p->scalar_type() == x.scalar_type() && p->device().is_cpu(), op, ": CPU tensors of x's dtype");
  TORCH_CHECK(x.device().is_cpu() && faces.device().is_cpu(), op, ": CPU tensors only");
  return x.numel() / std::max<int64_t>(V * 3, 1);
}

// Every vertex index of the contiguous faces (T, 3) in [0, V).
static void check_face_indices(const char* op, const Tensor& faces, int64_t V) {
  const int64_t* fc = faces.data_ptr<int64_t>();
  for (int64_t e = 0; e < faces.numel(); ++e)
    TORCH_CHECK(fc[e] >= 0 && fc[e] < V, op, ": faces index out of range [0, ", V, ")");
}

static void check_model(const char* op, int64_t model, int64_t projection) {
  TORCH_CHECK(model >= kStvk && model <= kNeohookean, op, ": unknown membrane model ", model);
  TORCH_CHECK(projection >= kProjectNone && projection <= kProjectAbs, op, ": unknown projection ", projection);
}

std::tuple<Tensor, Tensor> membrane_energy_gradient(Tensor x, Tensor faces, Tensor D, Tensor coef, Tensor mu,
                                                    Tensor lam, Tensor weight, bool gradient, int64_t model) {
  const char* op = "membrane_energy_gradient";
  check_model(op, model, kProjectNone);
  const int64_t B = check_membrane(op, x, faces, D, coef, mu, lam, {&D, &coef, &mu, &lam, &weight});
  const int64_t T = faces.size(0), V = x.size(-2);
  const auto batch = x.sizes().slice(0, x.dim() - 2);
  TORCH_CHECK(!gradient || weight.numel() == B, op, ": one weight per sample");
  x = x.contiguous();
  faces = faces.contiguous();
  D = D.contiguous();
  coef = coef.contiguous();
  weight = weight.contiguous();
  check_face_indices(op, faces, V);
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
      at::parallel_for(0, T, 2048, [&](int64_t begin, int64_t end) {
        for (int64_t e = begin; e < end; ++e) {
          const int64_t* t = fc + 3 * e;
          psi[e] = membrane_face<scalar_t>(int(model), xb + 3 * t[0], xb + 3 * t[1], xb + 3 * t[2], d + 6 * e, m, la,
                                           c[e], gradient ? forces.data() + 9 * e : nullptr);
        }
      });
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
  const int64_t B = check_membrane(op, x, faces, D, coef, mu, lam, {&v, &D, &coef, &mu, &lam, &weight});
  const int64_t T = faces.size(0), V = x.size(-2);
  TORCH_CHECK(v.sizes() == x.sizes(), op, ": v must have x's shape (..., V, 3)");
  TORCH_CHECK(weight.numel() == B, op, ": one weight per sample");
  x = x.contiguous();
  v = v.contiguous();
  faces = faces.contiguous();
  D = D.contiguous();
  coef = coef.contiguous();
  weight = weight.contiguous();
  check_face_indices(op, faces, V);
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
  const int64_t B = check_membrane(op, x, faces, D, coef, mu, lam, {&D, &coef, &mu, &lam});
  const int64_t T = faces.size(0), V = x.size(-2);
  x = x.contiguous();
  faces = faces.contiguous();
  D = D.contiguous();
  coef = coef.contiguous();
  check_face_indices(op, faces, V);
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
  check_membrane(op, x, faces, D, coef, mu, lam, {&D, &coef, &mu, &lam});
  const int64_t T = faces.size(0), V = x.size(-2);
  TORCH_CHECK(x.dim() == 2, op, ": one mesh, x (V, 3)");
  TORCH_CHECK(blocks.scalar_type() == torch::kInt64 && blocks.numel() == 9 * T && blocks.device().is_cpu(), op,
              ": blocks must be (T, 9) int64 CSR positions of the vertex pairs' 3x3 blocks");
  TORCH_CHECK(row_len.scalar_type() == torch::kInt64 && row_len.numel() == V && row_len.device().is_cpu(), op,
              ": row_len must be (V,) int64");
  x = x.contiguous();
  faces = faces.contiguous();
  D = D.contiguous();
  coef = coef.contiguous();
  blocks = blocks.contiguous();
  row_len = row_len.contiguous();
  check_face_indices(op, faces, V);
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
