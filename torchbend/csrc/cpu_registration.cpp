// The operators torch.ops.torchbend.* registered in C++: the schemas (op_registration.h) and the CPU kernels over
// the operators of cpu_ops.h, by register_operators (which the loader calls once it has chosen this module; not
// static initializers, so that a stale installed module imported directly, e.g. by a documentation tool, and the
// current JIT build can be loaded in one process: two TORCH_LIBRARY blocks for one namespace abort it).  Each kernel checks the
// model's name, runs the operator and turns a non-zero status word into the eager path's ValueError
// (reg::raise_status).  The fake kernels (shapes for tracing) are registered from Python
// (torchbend.backends.ops); so is project_blocks' kernel, whose eager fallback (CUDA tensors, other block
// sizes) is Python's.  The CUDA kernels are registered by the CUDA binding (cuda_binding.cpp).
#include <torch/library.h>

#include <mutex>
#include <optional>

#include "cpu_ops.h"
#include "op_registration.h"

namespace {

using torchbend::cpu::OptTensor;
using torchbend::cpu::Tensor;
namespace cpu = torchbend::cpu;
namespace reg = torchbend::reg;
using Str = c10::string_view;

Tensor none_or(bool keep, const Tensor& t, const Tensor& x) { return keep ? t : torch::empty({0}, x.options()); }

Tensor energy(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, OptTensor c, OptTensor prev, Str model_,
              bool check) {
  std::string model(model_);
  auto [psi, theta, status] =
      cpu::bending_energy(x, hinges, a, k, rest, c, prev, reg::model_code("bending_energy", model), check);
  if (status) reg::raise_status(status, model, x, theta);
  return psi;
}

std::tuple<Tensor, Tensor> gradient(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, OptTensor c,
                                    OptTensor prev, Str model_, Tensor weight, Tensor ptr, Tensor idx, bool params,
                                    bool check) {
  std::string model(model_);
  auto [gx, gp, theta, status] = cpu::bending_gradient(
      x, hinges, a, k, rest, c, prev, reg::model_code("bending_gradient", model), weight, ptr, idx, params, check);
  if (status) reg::raise_status(status, model, x, theta);
  return {gx, none_or(params, gp, x)};
}

std::tuple<Tensor, Tensor, Tensor> energy_gradient(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest,
                                                   OptTensor c, OptTensor prev, Str model_, Tensor ptr, Tensor idx,
                                                   bool params, bool check) {
  std::string model(model_);
  auto [psi, gx, gp, theta, status] = cpu::bending_energy_gradient(
      x, hinges, a, k, rest, c, prev, reg::model_code("bending_energy_gradient", model), ptr, idx, params, check);
  if (status) reg::raise_status(status, model, x, theta);
  return {psi, gx, none_or(params, gp, x)};
}

Tensor hvp(Tensor x, Tensor v, Tensor hinges, Tensor a, Tensor k, Tensor rest, OptTensor c, OptTensor prev,
           Str model_, Tensor weight, Tensor ptr, Tensor idx, bool check) {
  std::string model(model_);
  auto [hv, theta, status] = cpu::bending_hvp(x, v, hinges, a, k, rest, c, prev,
                                              reg::model_code("bending_hvp", model), weight, ptr, idx, check);
  if (status) reg::raise_status(status, model, x, theta, v);
  return hv;
}

std::tuple<Tensor, Tensor, Tensor> second_order(Tensor x, OptTensor v, OptTensor t, Tensor hinges, Tensor a, Tensor k,
                                                Tensor rest, OptTensor c, OptTensor prev, Str model_, Tensor weight,
                                                Tensor ptr, Tensor idx) {
  std::string model(model_);
  auto [dx, dp, dg, theta, status] = cpu::bending_second_order(
      x, v, t, hinges, a, k, rest, c, prev, reg::model_code("bending_second_order", model), weight, ptr, idx);
  if (status) reg::raise_status(status, model, x, theta);
  return {dx, dp, dg};
}

std::tuple<Tensor, Tensor, Tensor> hinge_hessians(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest,
                                                  OptTensor c, OptTensor prev, Str model_, bool check) {
  std::string model(model_);
  auto [blocks, g, d2, theta, status] = cpu::bending_hessians(
      x, hinges, a, k, rest, c, prev, reg::model_code("hinge_hessians", model), c10::nullopt, c10::nullopt, check);
  if (status) reg::raise_status(status, model, x, theta);
  return {blocks, g, d2};
}

Tensor assemble(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, OptTensor c, OptTensor prev, Str model_,
                Tensor hinge_blocks, Tensor faces, Tensor face_edge_hinges, Tensor face_edge_signs, Tensor face_blocks,
                Tensor row_len, int64_t nnz, bool per_triangle) {
  std::string model(model_);
  auto [values, theta, status] =
      cpu::assemble(x, hinges, a, k, rest, c, prev, reg::model_code("assemble", model), hinge_blocks, faces,
                    face_edge_hinges, face_edge_signs, face_blocks, row_len, nnz, per_triangle, c10::nullopt);
  if (status) reg::raise_status(status, model, x, theta);
  return values;
}

}  // namespace

void torchbend::reg::register_operators() {
  static std::once_flag once;
  std::call_once(once, [] {
    // never destroyed: the operators stay registered for the life of the process, as the module stays loaded
    auto* def = new torch::Library(torch::Library::DEF, "torchbend", std::nullopt, __FILE__, __LINE__);
    def->set_python_module("torchbend.backends.ops");  // the fake kernels are registered there
    for (const char* schema : torchbend::reg::kSchemas) def->def(schema);
    auto* m = new torch::Library(torch::Library::IMPL, "torchbend", c10::DispatchKey::CPU, __FILE__, __LINE__);
    m->impl("bending_energy", TORCH_FN(energy));
    m->impl("bending_gradient", TORCH_FN(gradient));
    m->impl("bending_energy_gradient", TORCH_FN(energy_gradient));
    m->impl("bending_hvp", TORCH_FN(hvp));
    m->impl("bending_second_order", TORCH_FN(second_order));
    m->impl("hinge_hessians", TORCH_FN(hinge_hessians));
    m->impl("assemble", TORCH_FN(assemble));
  });
}
