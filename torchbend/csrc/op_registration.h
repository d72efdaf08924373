// What the operator registrations of the CPU extension (cpu_registration.cpp: register_operators, the schemas and
// the CPU kernels) and of the CUDA binding (cuda_binding.cpp: TORCH_LIBRARY_IMPL(torchbend,
// CUDA)) share: the schemas of torch.ops.torchbend.* (the same strings as the Python fallback's,
// torchbend.backends._table.SCHEMAS, which a test compares), the check of the bending model's name, and the one
// place that turns a kernel's status word into the ValueError of the eager path: the Python function the loader
// registers (torchbend.backends._status.raise_for_status, called under the GIL), so that the wording stays in
// one helper.  Without a registered handler (the library used without torchbend's Python side) a status is a
// plain ValueError naming it.
#pragma once
#include <torch/extension.h>

#include <cstdint>
#include <string>

namespace torchbend {
namespace reg {

// the schemas, in the order of torchbend.backends._table.OPERATORS
// (internal linkage: two builds of the module loaded in one process each read their own)
static constexpr const char* kSchemas[] = {
    "bending_energy(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, str model, "
    "bool check) -> Tensor",
    "bending_gradient(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, str model, "
    "Tensor weight, Tensor ptr, Tensor idx, bool params, bool check) -> (Tensor, Tensor)",
    "bending_energy_gradient(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, "
    "str model, Tensor ptr, Tensor idx, bool params, bool check) -> (Tensor, Tensor, Tensor)",
    "bending_hvp(Tensor x, Tensor v, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, "
    "str model, Tensor weight, Tensor ptr, Tensor idx, bool check=False) -> Tensor",
    "bending_second_order(Tensor x, Tensor? v, Tensor? t, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, "
    "Tensor? prev, str model, Tensor weight, Tensor ptr, Tensor idx) -> (Tensor, Tensor, Tensor)",
    "hinge_hessians(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, str model, "
    "bool check=False) -> (Tensor, Tensor, Tensor)",
    "assemble(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, str model, "
    "Tensor hinge_blocks, Tensor faces, Tensor face_edge_hinges, Tensor face_edge_signs, Tensor face_blocks, "
    "Tensor row_len, SymInt nnz, bool per_triangle) -> Tensor",
    "project_blocks(Tensor M, str mode, bool hinge=False) -> Tensor",
    "membrane_energy_gradient(Tensor x, Tensor faces, Tensor D, Tensor coef, Tensor mu, Tensor lam, Tensor weight, "
    "bool gradient, str model) -> (Tensor, Tensor)",
    "membrane_hvp(Tensor x, Tensor v, Tensor faces, Tensor D, Tensor coef, Tensor mu, Tensor lam, Tensor weight, "
    "str model, str projection) -> (Tensor, Tensor)",
    "sum_last(Tensor values) -> Tensor",
};

// the schemas and the CPU kernels of torch.ops.torchbend.* (cpu_registration.cpp), registered on the first call
void register_operators();

// the Python callable (status, model, x, theta, v) -> raises; held for the life of the process (never destroyed:
// kernels may run at interpreter exit)
inline PyObject*& status_handler() {
  static PyObject* handler = nullptr;
  return handler;
}

inline void set_status_handler(pybind11::object fn) {
  pybind11::gil_scoped_acquire gil;
  PyObject*& h = status_handler();
  Py_XDECREF(h);
  h = fn.release().ptr();
}

// the ValueError of a non-zero status: the handler's (it raises the eager path's error; a Python exception
// travels through the dispatcher back to the caller as itself)
[[noreturn]] inline void raise_status(int64_t status, const std::string& model, const torch::Tensor& x,
                                      const torch::Tensor& theta, const c10::optional<torch::Tensor>& v = {}) {
  if (status_handler() != nullptr && Py_IsInitialized()) {
    pybind11::gil_scoped_acquire gil;
    pybind11::handle fn(status_handler());
    fn(status, model, x, theta, v.has_value() ? pybind11::cast(*v) : pybind11::none());
  }
  throw c10::ValueError({__func__, __FILE__, static_cast<uint32_t>(__LINE__)},
                        "torchbend: the compiled kernel reported invalid input (status " + std::to_string(status) +
                            ")");
}

// the kernels' code of a bending model's name; else the ValueError naming the operator and the choices
inline int64_t model_code(const char* op, const std::string& model) {
  if (model == "quadratic") return 0;
  if (model == "tan") return 1;
  if (model == "sin") return 2;
  std::string shown = "'" + model + "'";
  if (Py_IsInitialized()) {  // Python's repr of the name, as the eager path words it
    pybind11::gil_scoped_acquire gil;
    shown = pybind11::repr(pybind11::str(model)).cast<std::string>();
  }
  throw c10::ValueError({__func__, __FILE__, static_cast<uint32_t>(__LINE__)},
                        std::string("torchbend.") + op + ": model must be one of 'quadratic', 'tan', 'sin', got " +
                            shown);
}

}  // namespace reg
}  // namespace torchbend
