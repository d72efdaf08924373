// The membrane's per-triangle blocks (membrane_stvk_blocks): the closed-form StVK Hessian of membrane_math.h over
// the triangles, in parallel chunks (at::parallel_for: torch's thread pool and its thread count).
#include <ATen/Parallel.h>

#include "cpu_ops.h"
#include "membrane_math.h"

namespace torchbend {
namespace cpu {

Tensor membrane_stvk_blocks(Tensor F, Tensor D, Tensor mu, Tensor lam, Tensor coef) {
  TORCH_CHECK(F.dim() == 3 && F.size(1) == 3 && F.size(2) == 2, "membrane_stvk_blocks: F must be (T, 3, 2)");
  TORCH_CHECK(D.sizes() == F.sizes(), "membrane_stvk_blocks: D must have F's shape (T, 3, 2)");
  TORCH_CHECK(F.device().is_cpu() && D.device().is_cpu() && mu.device().is_cpu() && lam.device().is_cpu() &&
                  coef.device().is_cpu(),
              "membrane_stvk_blocks: CPU tensors only");
  const int64_t T = F.size(0);
  for (const Tensor* p : {&D, &mu, &lam, &coef})
    TORCH_CHECK(p->scalar_type() == F.scalar_type(), "membrane_stvk_blocks: all arguments must have F's dtype");
  for (const Tensor* p : {&mu, &lam, &coef})
    TORCH_CHECK(p->numel() == 1 || p->numel() == T, "membrane_stvk_blocks: mu, lam, coef: one value or one per triangle");
  F = F.contiguous();
  D = D.contiguous();
  mu = mu.contiguous();
  lam = lam.contiguous();
  coef = coef.contiguous();
  Tensor out = torch::empty({T, 9, 9}, F.options());
  AT_DISPATCH_FLOATING_TYPES(F.scalar_type(), "membrane_stvk_blocks", [&] {
    const scalar_t* f = F.data_ptr<scalar_t>();
    const scalar_t* d = D.data_ptr<scalar_t>();
    const scalar_t* m = mu.data_ptr<scalar_t>();
    const scalar_t* la = lam.data_ptr<scalar_t>();
    const scalar_t* c = coef.data_ptr<scalar_t>();
    const int64_t sm = mu.numel() == 1 ? 0 : 1, sl = lam.numel() == 1 ? 0 : 1, sc = coef.numel() == 1 ? 0 : 1;
    scalar_t* o = out.data_ptr<scalar_t>();
    at::parallel_for(0, T, 2048, [&](int64_t begin, int64_t end) {
      for (int64_t e = begin; e < end; ++e)
        stvk_block<scalar_t>(f + 6 * e, d + 6 * e, m[sm * e], la[sl * e], c[sc * e], o + 81 * e);
    });
  });
  return out;
}

}  // namespace cpu
}  // namespace torchbend
