// The PSD projection of symmetric blocks (project_blocks).
#include "cpu_ops.h"
#include "cpu_jacobi.h"
#include "cpu_tiles.h"

namespace torchbend {
namespace cpu {

// (M + M^T) / 2 of the first nl blocks at `in` (N x N each) into A (zeros in the other lanes)
template <typename T, int N>
static void load_symmetric(const T* in, int nl, T (&A)[N][N][W]) {
  for (int l = 0; l < W; ++l)
    for (int i = 0; i < N; ++i)
      for (int j = 0; j < N; ++j)
        A[i][j][l] = l < nl ? T(0.5) * (in[l * N * N + i * N + j] + in[l * N * N + j * N + i]) : T(0);
}

template <typename T, int N>
static void store_blocks(const T (&A)[N][N][W], int nl, T* out) {
  for (int l = 0; l < nl; ++l)
    for (int i = 0; i < N; ++i)
      for (int j = 0; j < N; ++j) out[l * N * N + i * N + j] = A[i][j][l];
}

// Hinge blocks (4 vertices x 3) are invariant under translations (rows and columns of each 3x3 block row sum to
// zero): with U (12 x 9) an orthonormal basis of the translations' complement, H = U (U^T H U) U^T and its
// projection is U proj(U^T H U) U^T, a 9x9 eigenproblem instead of 12x12 (0.42 of the work).  U = h^T (x) I3,
// h the orthonormal (Helmert) rows (1, -1, 0, 0) / sqrt 2, (1, 1, -2, 0) / sqrt 6, (1, 1, 1, -3) / sqrt 12.
template <typename T>
static void project_hinge_tile(const T* in, T* out, int nl, bool abs_mode) {
  const T r2 = T(1) / std::sqrt(T(2)), r6 = T(1) / std::sqrt(T(6)), r12 = T(1) / std::sqrt(T(12));
  const T h[3][4] = {{r2, -r2, T(0), T(0)}, {r6, r6, T(-2) * r6, T(0)}, {r12, r12, r12, T(-3) * r12}};
  alignas(64) T S[12][12][W], T1[12][9][W], A[9][9][W];
  load_symmetric<T, 12>(in, nl, S);
  for (int r = 0; r < 12; ++r)  // T1 = S U
    for (int c = 0; c < 3; ++c)
      for (int j = 0; j < 3; ++j)
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T acc = T(0);
          for (int a = 0; a < 4; ++a) acc += S[r][3 * a + j][l] * h[c][a];
          T1[r][3 * c + j][l] = acc;
        }
  for (int b = 0; b < 3; ++b)  // A = U^T T1
    for (int i = 0; i < 3; ++i)
      for (int cc = 0; cc < 9; ++cc)
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T acc = T(0);
          for (int a = 0; a < 4; ++a) acc += h[b][a] * T1[3 * a + i][cc][l];
          A[3 * b + i][cc][l] = acc;
        }
  for (int i = 0; i < 9; ++i)  // exactly symmetric before the sweeps
    for (int j = i + 1; j < 9; ++j)
#pragma omp simd
      for (int l = 0; l < W; ++l) A[i][j][l] = A[j][i][l] = T(0.5) * (A[i][j][l] + A[j][i][l]);
  jacobi_project<T, 9>(A, abs_mode);
  for (int r = 0; r < 9; ++r)  // T1^T = P U^T: T1[c'][r] = sum_c P[r][c] U[c'][c]
    for (int a = 0; a < 4; ++a)
      for (int j = 0; j < 3; ++j)
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T acc = T(0);
          for (int c = 0; c < 3; ++c) acc += A[r][3 * c + j][l] * h[c][a];
          T1[3 * a + j][r][l] = acc;
        }
  for (int a = 0; a < 4; ++a)  // out = U (P U^T): out[3a+i][col] = sum_b h[b][a] T1[col][3b+i]
    for (int i = 0; i < 3; ++i)
      for (int col = 0; col < 12; ++col)
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T acc = T(0);
          for (int b = 0; b < 3; ++b) acc += h[b][a] * T1[col][3 * b + i][l];
          S[3 * a + i][col][l] = acc;
        }
  for (int i = 0; i < 12; ++i)
    for (int j = i + 1; j < 12; ++j)
#pragma omp simd
      for (int l = 0; l < W; ++l) S[i][j][l] = S[j][i][l] = T(0.5) * (S[i][j][l] + S[j][i][l]);
  store_blocks<T, 12>(S, nl, out);
}

// The `reduced` projection of hinge blocks (torchbend.ops.projection): the lower-right 9x9 block (the Hessian in
// y_k = x_k - x_0) clamped, then D^T P D back to 12x12 (block row and column 0: minus the sums of the others)
template <typename T>
static void project_reduced_tile(const T* in, T* out, int nl) {
  alignas(64) T A[9][9][W];
  for (int l = 0; l < W; ++l)
    for (int i = 0; i < 9; ++i)
      for (int j = 0; j < 9; ++j)
        A[i][j][l] = l < nl ? T(0.5) * (in[l * 144 + (i + 3) * 12 + j + 3] + in[l * 144 + (j + 3) * 12 + i + 3]) : T(0);
  jacobi_project<T, 9>(A, false);
  for (int l = 0; l < nl; ++l) {
    T* o = out + l * 144;
    for (int i = 0; i < 9; ++i)
      for (int j = 0; j < 9; ++j) o[(i + 3) * 12 + j + 3] = A[i][j][l];
    for (int p = 0; p < 3; ++p)
      for (int c = 3; c < 12; ++c) {  // row p of block row 0 and, by symmetry, column p
        T s = T(0);
        for (int k = 0; k < 3; ++k) s += o[(3 * (k + 1) + p) * 12 + c];
        o[p * 12 + c] = o[c * 12 + p] = -s;
      }
    for (int p = 0; p < 3; ++p)
      for (int q = 0; q < 3; ++q) {
        T s = T(0);
        for (int k = 0; k < 3; ++k) s += o[p * 12 + 3 * (k + 1) + q];
        o[p * 12 + q] = -s;
      }
  }
}

template <typename T, int N>
static void project_tile(const T* in, T* out, int nl, bool abs_mode) {
  alignas(64) T A[N][N][W];
  load_symmetric<T, N>(in, nl, A);
  jacobi_project<T, N>(A, abs_mode);
  store_blocks<T, N>(A, nl, out);
}

// the PSD projection (mode 0: clamp, 1: abs) of symmetric blocks M (..., n, n), n = 9 or 12; with `hinge`, 12x12
// blocks invariant under translations of their 4 vertices, projected in the translations' complement, or by
// mode 2 (reduced, hinge blocks only): a new tensor
torch::Tensor project_blocks(torch::Tensor M, int64_t mode, bool hinge) {
  const char* op = "project_blocks";
  namespace ck = torchbend::checks;
  ck::require(M.device().is_cpu() && M.dim() >= 2 && M.size(-1) == M.size(-2) && (M.size(-1) == 9 || M.size(-1) == 12),
              op, "M must be a CPU (..., n, n) tensor with n 9 or 12, got ", ck::shape_str(M), " on ", M.device());
  ck::require(M.scalar_type() == torch::kFloat || M.scalar_type() == torch::kDouble, op,
              "M must be float32 or float64, got ", M.scalar_type());
  ck::require(mode >= 0 && mode <= 2 && (mode < 2 || (hinge && M.size(-1) == 12)), op,
              "mode must be 0 (clamp), 1 (abs) or, for 12x12 hinge blocks, 2 (reduced), got ", mode);
  if (finite_status(M.contiguous(), 1)) {
    auto bad = M.isfinite().logical_not().reshape({-1, M.size(-1) * M.size(-1)}).any(1).nonzero();
    ck::fail(op, "M holds non-finite values (first in block ", bad[0][0].item<int64_t>(), " of the flattened batch)");
  }
  const bool abs_mode = mode == 1;
  M = M.contiguous();
  const int64_t n = M.size(-1), count = n ? M.numel() / (n * n) : 0;
  auto out = pooled_empty(M.sizes().vec(), M.options());
  AT_DISPATCH_FLOATING_TYPES(M.scalar_type(), "project_blocks", [&] {
    const scalar_t* in = M.data_ptr<scalar_t>();
    scalar_t* o = out.data_ptr<scalar_t>();
    const int64_t tiles = (count + W - 1) / W;
    at::parallel_for(0, tiles, 16, [&](int64_t begin, int64_t end) {
      for (int64_t t = begin; t < end; ++t) {
        int nl = int(std::min<int64_t>(W, count - t * W));
        if (mode == 2) project_reduced_tile<scalar_t>(in + t * W * 144, o + t * W * 144, nl);
        else if (n == 12 && hinge) project_hinge_tile<scalar_t>(in + t * W * 144, o + t * W * 144, nl, abs_mode);
        else if (n == 12) project_tile<scalar_t, 12>(in + t * W * 144, o + t * W * 144, nl, abs_mode);
        else project_tile<scalar_t, 9>(in + t * W * 81, o + t * W * 81, nl, abs_mode);
      }
    });
  });
  return out;
}


}  // namespace cpu
}  // namespace torchbend
