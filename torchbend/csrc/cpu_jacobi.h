// The PSD projection of W symmetric blocks at a time by cyclic Jacobi (cpu_projection.cpp: the hinge and
// membrane blocks; cpu_contact.cpp: the contact pairs' reduced Hessians).
#pragma once
#include "cpu_tiles.h"

namespace torchbend {
namespace cpu {
// ----------------------------------------------------------------------------------------------
// PSD projection of symmetric blocks (torchbend.ops.projection: clamp Q max(L, 0) Q^T, abs Q |L| Q^T) by cyclic
// Jacobi, W blocks at a time with every rotation vectorized across the lanes.  Each block is symmetrized and
// scaled by its largest entry (no overflow or underflow in the rotations, whatever the units), swept until
// the off-diagonal part is below eps / 100 of the whole in every lane (quadratic convergence: 6-8 sweeps for
// the 12x12 hinge blocks), and rebuilt as sum_k f(l_k) v_k v_k^T.  Jacobi's eigenvalues are accurate to the
// block's norm times eps, as eigh's.

// Each lane's block scaled by its largest entry (scale[l]; 1 for a zero or non-finite block), V = I: the start of
// both eigensolvers (this one and cpu_symeig.h's)
template <typename T, int N, int WL>
static inline void lanes_scale(T (&A)[N][N][WL], T (&V)[N][N][WL], T (&scale)[WL]) {
  for (int l = 0; l < WL; ++l) {
    T mx = T(0);
    for (int i = 0; i < N; ++i)
      for (int j = 0; j < N; ++j) mx = std::max(mx, std::abs(A[i][j][l]));
    scale[l] = mx > T(0) && std::isfinite(mx) ? mx : T(1);
  }
  for (int i = 0; i < N; ++i)
    for (int j = 0; j < N; ++j)
#pragma omp simd
      for (int l = 0; l < WL; ++l) {
        A[i][j][l] /= scale[l];
        V[i][j][l] = i == j ? T(1) : T(0);
      }
}

// A <- V f(L) V^T with the eigenvalues L[k] and eigenvectors V[:, k] of the scaled block: f = max(., 0) (clamp)
// or |.| (abs), times the scale back
template <typename T, int N, int WL>
static inline void lanes_rebuild(T (&A)[N][N][WL], const T (&V)[N][N][WL], const T (&L)[N][WL], const T (&scale)[WL],
                                 bool abs_mode) {
  T f[N][WL];
  for (int k = 0; k < N; ++k)
#pragma omp simd
    for (int l = 0; l < WL; ++l) {
      T lk = L[k][l];
      f[k][l] = (abs_mode ? std::abs(lk) : std::max(lk, T(0))) * scale[l];
    }
  for (int i = 0; i < N; ++i)
    for (int j = i; j < N; ++j) {
      T acc[WL];
#pragma omp simd
      for (int l = 0; l < WL; ++l) acc[l] = T(0);
      for (int k = 0; k < N; ++k)
#pragma omp simd
        for (int l = 0; l < WL; ++l) acc[l] += V[i][k][l] * f[k][l] * V[j][k][l];
#pragma omp simd
      for (int l = 0; l < WL; ++l) A[i][j][l] = A[j][i][l] = acc[l];
    }
}

// A (N x N per lane, symmetric) <- its projection, in place
template <typename T, int N>
static void jacobi_project(T (&A)[N][N][W], bool abs_mode) {
  alignas(64) T V[N][N][W];
  T scale[W];
  lanes_scale(A, V, scale);
  // rotations of |a_pq| <= skip (the blocks are scaled to entries of at most 1, so |A| >= 1) are left out: they
  // change the result by less than eps / 1000 of |A|; the sweeps stop when the off-diagonal part is below
  // eps / 100 of |A| in every lane (the skipped entries together stay below that: N^2 skip^2 < 1e-4 eps^2)
  constexpr T eps = std::numeric_limits<T>::epsilon(), skip = eps * T(1e-3);
  for (int sweep = 0; sweep < 30; ++sweep) {
    bool done = true;
    for (int l = 0; l < W; ++l) {
      T off = T(0), all = T(0);
      for (int i = 0; i < N; ++i) {
        all += A[i][i][l] * A[i][i][l];
        for (int j = i + 1; j < N; ++j) off += A[i][j][l] * A[i][j][l];
      }
      done = done && off <= eps * eps * T(1e-4) * (all + T(2) * off);
    }
    if (done) break;
    for (int p = 0; p < N - 1; ++p)
      for (int q = p + 1; q < N; ++q) {
        T c[W], sn[W], t[W], big = T(0);
        for (int l = 0; l < W; ++l) big = std::max(big, std::abs(A[p][q][l]));
        if (big <= skip) continue;  // below what the result can resolve in every lane
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T apq = A[p][q][l], tau = A[q][q][l] - A[p][p][l];
          T den = std::abs(tau) + std::sqrt(tau * tau + T(4) * apq * apq);
          t[l] = den > T(0) ? T(2) * apq * (tau >= T(0) ? T(1) : T(-1)) / den : T(0);
          c[l] = T(1) / std::sqrt(T(1) + t[l] * t[l]);
          sn[l] = t[l] * c[l];
        }
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T apq = A[p][q][l];
          A[p][p][l] -= t[l] * apq;
          A[q][q][l] += t[l] * apq;
          A[p][q][l] = T(0);
        }
        // only the upper triangle is kept up to date (the sweeps read no other entry): half the stores
        for (int k = 0; k < N; ++k) {
          if (k == p || k == q) continue;
          T* kp = k < p ? A[k][p] : A[p][k];
          T* kq = k < q ? A[k][q] : A[q][k];
#pragma omp simd
          for (int l = 0; l < W; ++l) {
            T akp = kp[l], akq = kq[l];
            kp[l] = c[l] * akp - sn[l] * akq;
            kq[l] = sn[l] * akp + c[l] * akq;
          }
        }
        for (int k = 0; k < N; ++k) {
#pragma omp simd
          for (int l = 0; l < W; ++l) {
            T vkp = V[k][p][l], vkq = V[k][q][l];
            V[k][p][l] = c[l] * vkp - sn[l] * vkq;
            V[k][q][l] = sn[l] * vkp + c[l] * vkq;
          }
        }
      }
  }
  T L[N][W];
  for (int k = 0; k < N; ++k)
#pragma omp simd
    for (int l = 0; l < W; ++l) L[k][l] = A[k][k][l];
  lanes_rebuild(A, V, L, scale, abs_mode);
}
}  // namespace cpu
}  // namespace torchbend
