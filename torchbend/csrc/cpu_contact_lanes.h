// The contact pairs' PSD projections over lanes of pairs (cpu_contact.cpp's barrier operators): the full
// eigenproblem in reduced coordinates (project_group) and the one in the pair's normal frame (frame_group,
// contact_frame.h), both by the tridiagonal QL of cpu_symeig.h.
#pragma once
#include <algorithm>
#include <cstdint>
#include <vector>

#include "contact_frame.h"
#include "contact_math.h"
#include "cpu_symeig.h"

namespace torchbend {
namespace cpu {
namespace {

namespace cm = torchbend::contact;

// the lanes of a projection tile (two vectors of lanes measured no faster: the QL iterations go by the slowest lane)
constexpr int kLanes = W;

// project the pairs `idx` (all with N = 3 r reduced coordinates) of a chunk, kLanes at a time: P = R^-T proj(R^T H R)
// R^-1 back into terms[i].H, or (H12 given) expanded to the pairs' 12x12 blocks there

template <typename T, int N>
void project_group(std::vector<cm::PairTerms<T>>& terms, const std::vector<int>& idx, int64_t base, bool abs_mode,
                   T* H12) {
  constexpr int r = N / 3;
  for (size_t t0 = 0; t0 < idx.size(); t0 += kLanes) {
    const int nl = int(std::min<size_t>(kLanes, idx.size() - t0));
    alignas(64) T A[N][N][kLanes];
    T Ri[kLanes][3][3];
    for (int l = 0; l < kLanes; ++l) {
      if (l >= nl) {
        for (int i = 0; i < N; ++i) for (int j = 0; j < N; ++j) A[i][j][l] = 0;
        continue;
      }
      const auto& p = terms[idx[t0 + l]];
      T R[3][3], M[81];
      cm::gram_cholesky(p.C, r, R, Ri[l]);
      cm::congruence(R, r, p.H, M);
      for (int i = 0; i < N; ++i)
        for (int j = 0; j < N; ++j) A[i][j][l] = T(0.5) * (M[N * i + j] + M[N * j + i]);
    }
    ql_project<T, N, kLanes>(A, abs_mode);
    for (int l = 0; l < nl; ++l) {
      auto& p = terms[idx[t0 + l]];
      T M[81];
      for (int i = 0; i < N; ++i) for (int j = 0; j < N; ++j) M[N * i + j] = A[i][j][l];
      cm::congruence(Ri[l], r, M, p.H);
      if (H12) cm::expand_hessian(p.C, r, p.H, H12 + 144 * (base + idx[t0 + l]));
    }
  }
}

// project the unmollified pairs `idx` with r = 2 or 3 rows in their normal frame (contact_frame.h): S = Lb^T H Lb
// (m x m), proj(S) by lanes, U proj(S) U^T back into terms[i].H (and expanded to 12x12 blocks where H12 is given)
template <typename T, int r>
void frame_group(std::vector<cm::PairTerms<T>>& terms, const std::vector<int>& idx, int64_t base, bool abs_mode,
                 T* H12) {
  constexpr int k = 3 * r, m = r + 2, L = kLanes;
  for (size_t t0 = 0; t0 < idx.size(); t0 += L) {
    const int nl = int(std::min<size_t>(L, idx.size() - t0));
    // the lanes' H, Lb and U (lanes innermost: the products below vectorize across them)
    alignas(64) T H[k][k][L], Lb[k][m][L], U[k][m][L], W[k][m][L], A[m][m][L];
    for (int l = 0; l < L; ++l) {
      T lb[k * m], u[k * m];
      const bool on = l < nl;
      const auto* p = on ? &terms[idx[t0 + l]] : nullptr;
      if (on) cm::pair_frame(p->C, r, p->g, lb, u);
      for (int i = 0; i < k; ++i) {
        for (int c = 0; c < k; ++c) H[i][c][l] = on ? p->H[k * i + c] : T(0);
        for (int j = 0; j < m; ++j) { Lb[i][j][l] = on ? lb[m * i + j] : T(0); U[i][j][l] = on ? u[m * i + j] : T(0); }
      }
    }
    for (int i = 0; i < k; ++i)  // W = H Lb
      for (int j = 0; j < m; ++j) {
        T acc[L] = {};
        for (int c = 0; c < k; ++c)
#pragma omp simd
          for (int l = 0; l < L; ++l) acc[l] += H[i][c][l] * Lb[c][j][l];
        for (int l = 0; l < L; ++l) W[i][j][l] = acc[l];
      }
    for (int i = 0; i < m; ++i)  // A = Lb^T W, symmetrized
      for (int j = i; j < m; ++j) {
        T acc[L] = {};
        for (int c = 0; c < k; ++c)
#pragma omp simd
          for (int l = 0; l < L; ++l) acc[l] += Lb[c][i][l] * W[c][j][l] + Lb[c][j][l] * W[c][i][l];
        for (int l = 0; l < L; ++l) A[i][j][l] = A[j][i][l] = T(0.5) * acc[l];
      }
    ql_project<T, m, L>(A, abs_mode);
    for (int i = 0; i < k; ++i)  // W = U proj(A)
      for (int j = 0; j < m; ++j) {
        T acc[L] = {};
        for (int c = 0; c < m; ++c)
#pragma omp simd
          for (int l = 0; l < L; ++l) acc[l] += U[i][c][l] * A[c][j][l];
        for (int l = 0; l < L; ++l) W[i][j][l] = acc[l];
      }
    for (int i = 0; i < k; ++i)  // H = W U^T
      for (int j = i; j < k; ++j) {
        T acc[L] = {};
        for (int c = 0; c < m; ++c)
#pragma omp simd
          for (int l = 0; l < L; ++l) acc[l] += W[i][c][l] * U[j][c][l];
        for (int l = 0; l < L; ++l) H[i][j][l] = H[j][i][l] = acc[l];
      }
    for (int l = 0; l < nl; ++l) {
      auto& p = terms[idx[t0 + l]];
      for (int i = 0; i < k; ++i)
        for (int j = 0; j < k; ++j) p.H[k * i + j] = H[i][j][l];
      if (H12) cm::expand_hessian(p.C, r, p.H, H12 + 144 * (base + idx[t0 + l]));
    }
  }
}

}  // namespace
}  // namespace cpu
}  // namespace torchbend
