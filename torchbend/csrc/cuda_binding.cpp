// Torch binding of the CUDA driver (bending_cuda.cu, through its C interface bending_cuda.h).  It is
// compiled by g++ against whatever torch is installed (a CPU-only torch too: then it builds, links and
// imports, and no CUDA tensor ever reaches it) and linked with the nvcc-built driver and cudart.  The
// Python functions (torchbend.backends.cuda) pass the current CUDA stream of x's device as an integer; the CUDA
// kernels of the operators torch.ops.torchbend.* (TORCH_LIBRARY_IMPL(torchbend, CUDA), below) take it from the
// device guard and check as those functions do (non-finite inputs before, folded tan hinges after the kernel).
#include <torch/extension.h>
#include <torch/library.h>
#include <c10/core/DeviceGuard.h>
#include <c10/core/impl/DeviceGuardImplInterface.h>

#include "bending_cuda.h"
#include "checks.h"
#include "contact_math.h"
#include "op_registration.h"

namespace {

tb_param tparam(const torch::Tensor& t) { return tb_param{t.data_ptr(), t.numel()}; }

void check(int code, const char* what) {
  TORCH_CHECK(code == 0, "torchbend CUDA ", what, ": ", tb_cuda_error_string(code));
}

struct Args {
  torch::Tensor x, hinges, a, k, rest, c, prev;
  int64_t B = 1, V = 0, H = 0;
  tb_hinge_args args{};
  std::vector<int64_t> batch;
};

// x a CUDA float32/float64 (..., V, 3) tensor, else the ValueError naming the operator
void check_x(const char* op, const torch::Tensor& x) {
  namespace ck = torchbend::checks;
  ck::require(x.is_cuda() && x.dim() >= 2 && x.size(-1) == 3, op, "x must be a CUDA (..., V, 3) tensor, got ",
              ck::shape_str(x), " on ", x.device());
  ck::require(x.scalar_type() == torch::kFloat || x.scalar_type() == torch::kDouble, op,
              "x must be float32 or float64, got ", x.scalar_type());
}

// the element indices `elems` (n, cols) int64 on x's device with vertex indices in [0, V), checked; r gets x
// (contiguous), its batch shape, B and V
template <class R>
torch::Tensor mesh_indices(const char* op, const torch::Tensor& x, const torch::Tensor& elems, const char* name,
                           int64_t cols, R& r) {
  namespace ck = torchbend::checks;
  torch::Tensor idx = ck::index_tensor(op, name, elems, x.device(), cols);
  r.batch.assign(x.sizes().begin(), x.sizes().end() - 2);
  for (auto s : r.batch) r.B *= s;
  r.V = x.size(-2);
  ck::check_range(op, name, idx, 0, r.V, "x has V = " + std::to_string(r.V) + " vertices");
  r.x = x.contiguous();
  return idx;
}

// the shared arguments, checked before any work (checks.h: a ValueError naming the operator, the argument and
// its first offending entry): x a CUDA float32/float64 (..., V, 3) tensor, hinges int64 (H, 4) on x's device with
// vertex indices in [0, V), per-hinge parameters on x's device with 1, H or B*H values, c and prev both or neither
Args prepare(const char* op, const torch::Tensor& x, const torch::Tensor& hinges, const torch::Tensor& a,
             const torch::Tensor& k, const torch::Tensor& rest, const c10::optional<torch::Tensor>& c,
             const c10::optional<torch::Tensor>& prev, int64_t model) {
  namespace ck = torchbend::checks;
  check_x(op, x);
  ck::require(model >= 0 && model <= 2, op, "model code must be 0 (quadratic), 1 (tan) or 2 (sin), got ", model);
  ck::require(c.has_value() == prev.has_value(), op, "the viscous term needs both c and prev (got ",
              c.has_value() ? "c without prev" : "prev without c", ")");
  Args r;
  r.hinges = mesh_indices(op, x, hinges, "hinges", 4, r);
  r.H = hinges.size(0);
  auto prep = [&](const torch::Tensor& t, const char* name) {
    ck::require(t.device() == x.device(), op, name, " must be on x's device (", x.device(), "), got ", t.device());
    ck::require(t.is_floating_point() || t.scalar_type() == torch::kLong || t.scalar_type() == torch::kInt, op, name,
                " must be a real tensor, got ", t.scalar_type());
    ck::require(t.numel() == 1 || t.numel() == r.H || t.numel() == r.B * r.H, op, name, " has ", t.numel(),
                " values; expected 1, H = ", r.H, " or B*H = ", r.B * r.H);
    return t.to(x.scalar_type()).contiguous();
  };
  r.a = prep(a, "a"); r.k = prep(k, "k"); r.rest = prep(rest, "rest");
  bool damped = c.has_value();
  if (damped) { r.c = prep(*c, "c"); r.prev = prep(*prev, "prev"); }
  tb_param none{nullptr, 0};
  r.args = tb_hinge_args{tparam(r.a), tparam(r.k), tparam(r.rest), damped ? tparam(r.c) : none,
                         damped ? tparam(r.prev) : none, damped ? 1 : 0, int(model)};
  return r;
}

std::vector<int64_t> with(std::vector<int64_t> s, std::initializer_list<int64_t> tail) {
  s.insert(s.end(), tail);
  return s;
}

void* as_stream(int64_t s) { return reinterpret_cast<void*>(static_cast<intptr_t>(s)); }
int dtype_code(const torch::Tensor& x) { return x.scalar_type() == torch::kDouble ? 1 : 0; }

std::tuple<torch::Tensor, torch::Tensor> energy(torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k,
                                                torch::Tensor rest, c10::optional<torch::Tensor> c,
                                                c10::optional<torch::Tensor> prev, int64_t model, int64_t stream) {
  c10::DeviceGuard guard(x.device());
  Args r = prepare("bending_energy", x, hinges, a, k, rest, c, prev, model);
  auto psi = torch::empty(with(r.batch, {r.H}), r.x.options()), theta = torch::empty_like(psi);
  check(tb_cuda_energy(dtype_code(r.x), r.x.data_ptr(), r.hinges.data_ptr<int64_t>(), r.B, r.V, r.H, r.args,
                       psi.data_ptr(), theta.data_ptr(), as_stream(stream)), "energy");
  return {psi, theta};
}

torch::Tensor weight_of(const char* op, const torch::Tensor& w, const Args& r) {
  torchbend::checks::require(w.device() == r.x.device() && w.is_floating_point() &&
                                 (w.numel() == 1 || w.numel() == r.H || w.numel() == r.B * r.H),
                             op, "weight must be a floating-point tensor on x's device with 1, H = ", r.H,
                             " or B*H = ", r.B * r.H, " values, got ", w.numel(), " on ", w.device());
  return w.to(r.x.scalar_type()).contiguous();
}

// the direction v of an HVP, checked against x (shape, dtype, device), contiguous
torch::Tensor direction(const char* op, const torch::Tensor& v, const torch::Tensor& x) {
  torchbend::checks::require(v.sizes() == x.sizes() && v.scalar_type() == x.scalar_type() && v.device() == x.device(),
                             op, "v must have x's shape ", torchbend::checks::shape_str(x), ", dtype and device, got ",
                             torchbend::checks::shape_str(v), " ", v.scalar_type(), " on ", v.device());
  return v.contiguous();
}

// ---- the membrane (one material): x (..., V, 3) CUDA float32/float64, faces (T, 3) int64, D (T, 3, 2) and coef (T,)
// on x's device; the sums over triangles are torch's (deterministic), the scatter atomic
struct MembraneArgs {
  torch::Tensor x, faces, D, coef;
  int64_t B = 1, V = 0, T = 0;
  std::vector<int64_t> batch;
  tb_membrane_args args{};
};

MembraneArgs prepare_membrane(const char* op, const torch::Tensor& x, const torch::Tensor& faces,
                              const torch::Tensor& D, const torch::Tensor& coef, double mu, double lam, int64_t model,
                              int64_t projection) {
  namespace ck = torchbend::checks;
  check_x(op, x);
  ck::require(model >= 0 && model <= 3 && projection >= 0 && projection <= 2, op,
              "membrane model code must be 0-3 and projection 0-2, got ", model, " and ", projection);
  MembraneArgs r;
  r.faces = mesh_indices(op, x, faces, "faces", 3, r);
  r.T = faces.size(0);
  ck::require(D.device() == x.device() && D.numel() == 6 * r.T && coef.device() == x.device() && coef.numel() == r.T,
              op, "D (T, 3, 2) and coef (T,) must be on x's device");
  r.D = D.to(x.scalar_type()).contiguous();
  r.coef = coef.to(x.scalar_type()).contiguous();
  r.args = tb_membrane_args{r.D.data_ptr(), r.coef.data_ptr(), mu, lam, int(model), int(projection)};
  return r;
}

torch::Tensor sample_weight(const char* op, const torch::Tensor& w, const MembraneArgs& r) {
  torchbend::checks::require(w.device() == r.x.device() && w.is_floating_point() && w.numel() == r.B, op,
                             "weight must be one value per sample on x's device, got ", w.numel());
  return w.to(r.x.scalar_type()).contiguous();
}

// (psi (..., T), weight dE/dx (..., V, 3) or empty)
std::tuple<torch::Tensor, torch::Tensor> membrane_energy_gradient(torch::Tensor x, torch::Tensor faces,
                                                                  torch::Tensor D, torch::Tensor coef, double mu,
                                                                  double lam, torch::Tensor weight, bool gradient,
                                                                  int64_t model, int64_t stream) {
  c10::DeviceGuard guard(x.device());
  MembraneArgs r = prepare_membrane("membrane_energy_gradient", x, faces, D, coef, mu, lam, model, 0);
  auto psi = torch::empty(with(r.batch, {r.T}), r.x.options());
  auto gx = gradient ? torch::zeros(r.x.sizes(), r.x.options()) : torch::empty({0}, r.x.options());
  auto w = gradient ? sample_weight("membrane_energy_gradient", weight, r) : torch::empty({0}, r.x.options());
  check(tb_cuda_membrane_energy_gradient(dtype_code(r.x), r.x.data_ptr(), r.faces.data_ptr<int64_t>(), r.B, r.V, r.T,
                                         r.args, gradient ? w.data_ptr() : nullptr, psi.data_ptr(),
                                         gradient ? gx.data_ptr() : nullptr, as_stream(stream)),
        "membrane_energy_gradient");
  return {psi, gx};
}

// (weight H v (..., V, 3), coef P : dF per triangle (..., T))
std::tuple<torch::Tensor, torch::Tensor> membrane_hvp(torch::Tensor x, torch::Tensor v, torch::Tensor faces,
                                                      torch::Tensor D, torch::Tensor coef, double mu, double lam,
                                                      torch::Tensor weight, int64_t model, int64_t projection,
                                                      int64_t stream) {
  c10::DeviceGuard guard(x.device());
  MembraneArgs r = prepare_membrane("membrane_hvp", x, faces, D, coef, mu, lam, model, projection);
  auto vc = direction("membrane_hvp", v, x);
  auto w = sample_weight("membrane_hvp", weight, r);
  auto hv = torch::zeros(r.x.sizes(), r.x.options());
  auto dots = torch::empty(with(r.batch, {r.T}), r.x.options());
  check(tb_cuda_membrane_hvp(dtype_code(r.x), r.x.data_ptr(), vc.data_ptr(), r.faces.data_ptr<int64_t>(), r.B, r.V,
                             r.T, r.args, w.data_ptr(), hv.data_ptr(), dots.data_ptr(), as_stream(stream)),
        "membrane_hvp");
  return {hv, dots};
}

// (..., T, 9, 9): the (projected) Hessian of each triangle
torch::Tensor membrane_blocks(torch::Tensor x, torch::Tensor faces, torch::Tensor D, torch::Tensor coef, double mu,
                              double lam, int64_t model, int64_t projection, int64_t stream) {
  c10::DeviceGuard guard(x.device());
  MembraneArgs r = prepare_membrane("membrane_blocks", x, faces, D, coef, mu, lam, model, projection);
  auto blocks = torch::empty(with(r.batch, {r.T, 9, 9}), r.x.options());
  check(tb_cuda_membrane_blocks(dtype_code(r.x), r.x.data_ptr(), r.faces.data_ptr<int64_t>(), r.B, r.V, r.T, r.args,
                                blocks.data_ptr(), as_stream(stream)),
        "membrane_blocks");
  return blocks;
}

// (E (N,), G (N, 12) or empty, H (N, 12, 12) or empty): the barrier of contact stencils (N, 4) of the given types
// over the points x (n, 3), unprojected (contact_math.h); eps: the edge-edge pairs' mollifier thresholds or empty
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> contact_barrier(torch::Tensor x, torch::Tensor stencils,
                                                                        torch::Tensor types, torch::Tensor eps,
                                                                        double dhat_sq, double kappa, int64_t want,
                                                                        int64_t stream) {
  namespace ck = torchbend::checks;
  const char* op = "contact_barrier";
  c10::DeviceGuard guard(x.device());
  ck::require(x.is_cuda() && x.dim() == 2 && x.size(1) == 3 &&
              (x.scalar_type() == torch::kFloat || x.scalar_type() == torch::kDouble), op,
              "x must be a CUDA (n, 3) float32 or float64 tensor, got ", ck::shape_str(x), " ", x.scalar_type());
  auto st = ck::index_tensor(op, "stencils", stencils, x.device(), 4);
  ck::check_range(op, "stencils", st, 0, x.size(0), "x has n = " + std::to_string(x.size(0)) + " points");
  const int64_t N = st.size(0);
  auto ty = ck::index_tensor(op, "types", types, x.device());
  ck::require(ty.dim() == 1 && ty.size(0) == N, op, "types must have one entry per stencil, got ", ck::shape_str(ty));
  ck::check_range(op, "types", ty, 0, torchbend::contact::NUM_TYPES, "the distance types");
  const bool mollified = eps.numel() > 0;
  if (mollified) {
    ck::require(eps.dim() == 1 && eps.size(0) == N && eps.device() == x.device(), op,
                "eps must be empty or hold one threshold per stencil on x's device, got ", ck::shape_str(eps));
    eps = eps.to(x.scalar_type()).contiguous();
  }
  ck::require(dhat_sq > 0 && std::isfinite(dhat_sq) && kappa >= 0 && std::isfinite(kappa) && want >= 0 && want <= 2,
              op, "dhat_sq must be finite and > 0, kappa finite and >= 0 and want 0, 1 or 2");
  auto xc = x.contiguous();
  auto E = torch::empty({N}, x.options());
  auto G = torch::empty({want >= 1 ? N : 0, 12}, x.options());
  auto H = torch::empty({want >= 2 ? N : 0, 12, 12}, x.options());
  check(tb_cuda_contact_barrier(dtype_code(xc), xc.data_ptr(), st.data_ptr<int64_t>(), ty.data_ptr<int64_t>(),
                                mollified ? eps.data_ptr() : nullptr, N, dhat_sq, kappa, int(want), E.data_ptr(),
                                want >= 1 ? G.data_ptr() : nullptr, want >= 2 ? H.data_ptr() : nullptr,
                                as_stream(stream)),
        op);
  return {E, G, H};
}

// (w dE/dx, w dpsi/dparams or empty, psi or empty, theta); with `energy` the per-hinge energies psi come from the
// same kernel
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, torch::Tensor> gradient(
    torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest,
    c10::optional<torch::Tensor> c, c10::optional<torch::Tensor> prev, int64_t model, torch::Tensor weight,
    bool params, bool energy, int64_t stream) {
  c10::DeviceGuard guard(x.device());
  Args r = prepare("bending_gradient", x, hinges, a, k, rest, c, prev, model);
  auto w = weight_of("bending_gradient", weight, r);
  auto gx = torch::zeros(with(r.batch, {r.V, 3}), r.x.options());
  auto gp = params ? torch::empty(with(r.batch, {r.H, 4}), r.x.options()) : torch::empty({0}, r.x.options());
  auto theta = torch::empty(with(r.batch, {r.H}), r.x.options());
  auto psi = energy ? torch::empty_like(theta) : torch::empty({0}, r.x.options());
  check(tb_cuda_gradient(dtype_code(r.x), r.x.data_ptr(), r.hinges.data_ptr<int64_t>(), r.B, r.V, r.H, r.args,
                         tparam(w), gx.data_ptr(), params ? gp.data_ptr() : nullptr,
                         energy ? psi.data_ptr() : nullptr, theta.data_ptr(), as_stream(stream)), "gradient");
  return {gx, gp, psi, theta};
}

std::tuple<torch::Tensor, torch::Tensor> hvp(torch::Tensor x, torch::Tensor v, torch::Tensor hinges, torch::Tensor a,
                                             torch::Tensor k, torch::Tensor rest, c10::optional<torch::Tensor> c,
                                             c10::optional<torch::Tensor> prev, int64_t model, torch::Tensor weight,
                                             int64_t stream) {
  c10::DeviceGuard guard(x.device());
  Args r = prepare("bending_hvp", x, hinges, a, k, rest, c, prev, model);
  auto vc = direction("bending_hvp", v, x);
  auto w = weight_of("bending_hvp", weight, r);
  auto hv = torch::zeros(with(r.batch, {r.V, 3}), r.x.options());
  auto theta = torch::empty(with(r.batch, {r.H}), r.x.options());
  check(tb_cuda_hvp(dtype_code(r.x), r.x.data_ptr(), vc.data_ptr(), r.hinges.data_ptr<int64_t>(), r.B, r.V, r.H,
                    r.args, tparam(w), hv.data_ptr(), theta.data_ptr(), as_stream(stream)), "hvp");
  return {hv, theta};
}

std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, torch::Tensor> second_order(
    torch::Tensor x, c10::optional<torch::Tensor> v, c10::optional<torch::Tensor> t, torch::Tensor hinges,
    torch::Tensor a, torch::Tensor k, torch::Tensor rest, c10::optional<torch::Tensor> c,
    c10::optional<torch::Tensor> prev, int64_t model, torch::Tensor weight, int64_t stream) {
  c10::DeviceGuard guard(x.device());
  Args r = prepare("bending_second_order", x, hinges, a, k, rest, c, prev, model);
  torch::Tensor vc, tc;
  if (v.has_value()) vc = direction("bending_second_order", *v, x);
  if (t.has_value()) {
    torchbend::checks::require(t->device() == x.device() && t->is_floating_point() && t->dim() >= 2 &&
                                   t->size(-1) == 4 && t->size(-2) == r.H &&
                                   (t->numel() == 4 * r.H || t->numel() == 4 * r.B * r.H),
                               "bending_second_order", "t must be a floating-point (H, 4) or (..., H, 4) tensor of x's "
                               "batch on x's device, H = ", r.H, ", got ", torchbend::checks::shape_str(*t));
    tc = t->to(r.x.scalar_type()).contiguous();
  }
  auto w = weight_of("bending_second_order", weight, r);
  auto dx = torch::zeros(with(r.batch, {r.V, 3}), r.x.options());
  auto dp = torch::empty(with(r.batch, {r.H, 4}), r.x.options());
  auto dg = torch::empty(with(r.batch, {r.H}), r.x.options()), theta = torch::empty_like(dg);
  check(tb_cuda_second_order(dtype_code(r.x), r.x.data_ptr(), vc.defined() ? vc.data_ptr() : nullptr,
                             tc.defined() ? tc.data_ptr() : nullptr, tc.defined() ? tc.numel() / 4 : 0,
                             r.hinges.data_ptr<int64_t>(), r.B, r.V, r.H, r.args, tparam(w), dx.data_ptr(),
                             dp.data_ptr(), dg.data_ptr(), theta.data_ptr(), as_stream(stream)), "second_order");
  return {dx, dp, dg, theta};
}

std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, torch::Tensor> hinge_hessians(
    torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest,
    c10::optional<torch::Tensor> c, c10::optional<torch::Tensor> prev, int64_t model, int64_t stream) {
  c10::DeviceGuard guard(x.device());
  Args r = prepare("hinge_hessians", x, hinges, a, k, rest, c, prev, model);
  auto blocks = torch::empty(with(r.batch, {r.H, 12, 12}), r.x.options());
  auto grads = torch::empty(with(r.batch, {r.H, 12}), r.x.options());
  auto d2 = torch::empty(with(r.batch, {r.H}), r.x.options()), theta = torch::empty_like(d2);
  check(tb_cuda_hinge_hessians(dtype_code(r.x), r.x.data_ptr(), r.hinges.data_ptr<int64_t>(), r.B, r.V, r.H, r.args,
                               blocks.data_ptr(), grads.data_ptr(), d2.data_ptr(), theta.data_ptr(), as_stream(stream)),
        "hinge_hessians");
  return {blocks, grads, d2, theta};
}

std::vector<std::string> kernels() {
  std::vector<std::string> out;
  for (int i = 0; i < tb_cuda_kernel_count(); ++i) out.emplace_back(tb_cuda_kernel_name(i));
  return out;
}


// ---- the operators' CUDA kernels (the schemas: the CPU extension's TORCH_LIBRARY, op_registration.h) ----------
namespace reg = torchbend::reg;
using OptTensor = c10::optional<torch::Tensor>;
using Str = c10::string_view;

int64_t current_stream(const torch::Tensor& x) {
  void* s = c10::impl::getDeviceGuardImpl(c10::DeviceType::CUDA)->getStream(x.device()).native_handle();
  return static_cast<int64_t>(reinterpret_cast<intptr_t>(s));
}

// with `check`: the ValueError of non-finite x (and v), before any work (torchbend.backends._status.input_status)
void check_inputs(bool check, const std::string& model, const torch::Tensor& x, const OptTensor& v = {}) {
  if (!check) return;
  int64_t status = torch::isfinite(x).all().item<bool>() ? 0 : 1;
  if (v.has_value() && !torch::isfinite(*v).all().item<bool>()) status |= 2;
  if (status) reg::raise_status(status, model, x, torch::Tensor(), v);
}

// the ValueError of a folded tan hinge, from the kernel's angles (torchbend.backends._status.fold_status)
void check_fold(int64_t code, const std::string& model, const torch::Tensor& x, const torch::Tensor& theta) {
  if (code == 1 && theta.numel() > 0 && (theta.abs() >= M_PI).any().item<bool>()) reg::raise_status(4, model, x, theta);
}

torch::Tensor op_energy(torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest,
                        OptTensor c, OptTensor prev, Str model_, bool check) {
  std::string model(model_);
  int64_t code = reg::model_code("bending_energy", model);
  check_inputs(check, model, x);
  auto [psi, theta] = energy(x, hinges, a, k, rest, c, prev, code, current_stream(x));
  check_fold(code, model, x, theta);
  return psi;
}

std::tuple<torch::Tensor, torch::Tensor> op_gradient(torch::Tensor x, torch::Tensor hinges, torch::Tensor a,
                                                     torch::Tensor k, torch::Tensor rest, OptTensor c, OptTensor prev,
                                                     Str model_, torch::Tensor weight, torch::Tensor, torch::Tensor,
                                                     bool params, bool check) {
  std::string model(model_);
  int64_t code = reg::model_code("bending_gradient", model);
  check_inputs(check, model, x);
  auto [gx, gp, psi, theta] = gradient(x, hinges, a, k, rest, c, prev, code, weight, params, false, current_stream(x));
  check_fold(code, model, x, theta);
  return {gx, gp};
}

std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> op_energy_gradient(
    torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest, OptTensor c,
    OptTensor prev, Str model_, torch::Tensor, torch::Tensor, bool params, bool check) {
  std::string model(model_);
  int64_t code = reg::model_code("bending_energy_gradient", model);
  check_inputs(check, model, x);
  auto [gx, gp, psi, theta] = gradient(x, hinges, a, k, rest, c, prev, code, torch::ones({1}, x.options()), params,
                                       true, current_stream(x));
  check_fold(code, model, x, theta);
  return {psi, gx, gp};
}

torch::Tensor op_hvp(torch::Tensor x, torch::Tensor v, torch::Tensor hinges, torch::Tensor a, torch::Tensor k,
                     torch::Tensor rest, OptTensor c, OptTensor prev, Str model_, torch::Tensor weight, torch::Tensor,
                     torch::Tensor, bool check) {
  std::string model(model_);
  int64_t code = reg::model_code("bending_hvp", model);
  check_inputs(check, model, x, v);
  auto [hv, theta] = hvp(x, v, hinges, a, k, rest, c, prev, code, weight, current_stream(x));
  check_fold(code, model, x, theta);
  return hv;
}

std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> op_second_order(
    torch::Tensor x, OptTensor v, OptTensor t, torch::Tensor hinges, torch::Tensor a, torch::Tensor k,
    torch::Tensor rest, OptTensor c, OptTensor prev, Str model_, torch::Tensor weight, torch::Tensor, torch::Tensor) {
  std::string model(model_);
  int64_t code = reg::model_code("bending_second_order", model);
  auto [dx, dp, dg, theta] = second_order(x, v, t, hinges, a, k, rest, c, prev, code, weight, current_stream(x));
  check_fold(code, model, x, theta);
  return {dx, dp, dg};
}

std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> op_hinge_hessians(torch::Tensor x, torch::Tensor hinges,
                                                                          torch::Tensor a, torch::Tensor k,
                                                                          torch::Tensor rest, OptTensor c,
                                                                          OptTensor prev, Str model_, bool check) {
  std::string model(model_);
  int64_t code = reg::model_code("hinge_hessians", model);
  check_inputs(check, model, x);
  auto [blocks, grads, d2, theta] = hinge_hessians(x, hinges, a, k, rest, c, prev, code, current_stream(x));
  check_fold(code, model, x, theta);
  return {blocks, grads, d2};
}

}  // namespace

TORCH_LIBRARY_IMPL(torchbend, CUDA, m) {
  m.impl("bending_energy", TORCH_FN(op_energy));
  m.impl("bending_gradient", TORCH_FN(op_gradient));
  m.impl("bending_energy_gradient", TORCH_FN(op_energy_gradient));
  m.impl("bending_hvp", TORCH_FN(op_hvp));
  m.impl("bending_second_order", TORCH_FN(op_second_order));
  m.impl("hinge_hessians", TORCH_FN(op_hinge_hessians));
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("bending_energy", &energy, "per-hinge energies and angles (CUDA)");
  m.def("bending_gradient", &gradient,
        "weighted gradient, per-hinge parameter gradients and (optionally) energies in one pass (CUDA)");
  m.def("bending_hvp", &hvp, "weighted Hessian-vector product (CUDA)");
  m.def("bending_hessians", &hinge_hessians, "per-hinge 12x12 blocks, angle gradients, psi'', theta (CUDA)");
  m.def("bending_second_order", &second_order,
        "the general double backward: position and parameter directions, per-hinge weight (CUDA)");
  m.def("membrane_energy_gradient", &membrane_energy_gradient,
        "per-triangle membrane energies and, optionally, the weighted gradient (CUDA)");
  m.def("membrane_hvp", &membrane_hvp, "the (projected) membrane Hessian-vector product, weighted (CUDA)");
  m.def("membrane_blocks", &membrane_blocks, "the (projected) membrane Hessian of each triangle (CUDA)");
  m.def("contact_barrier", &contact_barrier,
        "barrier energies, gradients and Hessians of contact stencils, closed form, unprojected (CUDA)");
  m.def("kernels", &kernels, "the names of the CUDA kernels in this build");
  m.def("set_status_handler", &torchbend::reg::set_status_handler,
        "the Python function raising the ValueError of a status word in the registered operators");
}
