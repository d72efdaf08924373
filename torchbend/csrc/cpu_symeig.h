// The PSD projection of WL symmetric blocks at a time by Householder tridiagonalization and implicit QL with
// Wilkinson-type shifts (the contact pairs' reduced Hessians, cpu_contact.cpp): about a quarter of cyclic Jacobi's
// arithmetic for 6x6 and 9x9 blocks.  Every step runs across the lanes of a tile: the Householder reflections and
// the eigenvector updates vectorized, the QL chase lane by lane with selects (a lane whose eigenvalue has
// converged, or whose chase ends earlier, takes identity rotations).  Each block is scaled by its largest entry
// first (lanes_scale, cpu_jacobi.h), so that entries below eps / 1000 count as zero.
#pragma once
#include "cpu_jacobi.h"

namespace torchbend {
namespace cpu {

// A (N x N per lane, symmetric) <- Q f(L) Q^T, f = max(., 0) (clamp) or |.| (abs), in place
template <typename T, int N, int WL = W>
static void ql_project(T (&A)[N][N][WL], bool abs_mode) {
  static_assert(N >= 2, "blocks of at least 2 x 2");
  alignas(64) T Z[N][N][WL];
  T scale[WL], d[N][WL], e[N][WL];
  lanes_scale(A, Z, scale);
  // ---- tridiagonalization: H_k = I - beta v v^T maps column k below the diagonal to (alpha, 0, ...)
  // (every lane loop innermost, with the sums in per-lane accumulators: each loop vectorizes)
  for (int k = 0; k < N - 2; ++k) {
    T v[N][WL], p[N][WL], beta[WL], K[WL], sigma[WL];
#pragma omp simd
    for (int l = 0; l < WL; ++l) sigma[l] = T(0);
    for (int i = k + 2; i < N; ++i)
#pragma omp simd
      for (int l = 0; l < WL; ++l) {
        sigma[l] += A[i][k][l] * A[i][k][l];
        v[i][l] = A[i][k][l];
      }
#pragma omp simd
    for (int l = 0; l < WL; ++l) {
      T x0 = A[k + 1][k][l], norm = std::sqrt(x0 * x0 + sigma[l]);
      T alpha = x0 >= T(0) ? -norm : norm, v0 = x0 - alpha, vn2 = sigma[l] + v0 * v0;
      beta[l] = vn2 > T(0) ? T(2) / vn2 : T(0);
      e[k][l] = vn2 > T(0) ? alpha : x0;
      d[k][l] = A[k][k][l];
      v[k + 1][l] = v0;
      K[l] = T(0);
    }
    for (int i = k + 1; i < N; ++i) {  // p = beta B v (B = A[k+1:, k+1:]); K = beta v^T p / 2
      T acc[WL];
#pragma omp simd
      for (int l = 0; l < WL; ++l) acc[l] = T(0);
      for (int j = k + 1; j < N; ++j)
#pragma omp simd
        for (int l = 0; l < WL; ++l) acc[l] += A[i][j][l] * v[j][l];
#pragma omp simd
      for (int l = 0; l < WL; ++l) {
        p[i][l] = beta[l] * acc[l];
        K[l] += v[i][l] * p[i][l];
      }
    }
    for (int i = k + 1; i < N; ++i)  // w = p - K v, kept in p
#pragma omp simd
      for (int l = 0; l < WL; ++l) p[i][l] -= T(0.5) * beta[l] * K[l] * v[i][l];
    for (int i = k + 1; i < N; ++i)  // B <- H B H = B - v w^T - w v^T
      for (int j = k + 1; j < N; ++j)
#pragma omp simd
        for (int l = 0; l < WL; ++l) A[i][j][l] -= v[i][l] * p[j][l] + p[i][l] * v[j][l];
    for (int r = 0; r < N; ++r) {  // Z <- Z H
      T t[WL];
#pragma omp simd
      for (int l = 0; l < WL; ++l) t[l] = T(0);
      for (int j = k + 1; j < N; ++j)
#pragma omp simd
        for (int l = 0; l < WL; ++l) t[l] += Z[r][j][l] * v[j][l];
      for (int j = k + 1; j < N; ++j)
#pragma omp simd
        for (int l = 0; l < WL; ++l) Z[r][j][l] -= beta[l] * t[l] * v[j][l];
    }
  }
#pragma omp simd
  for (int l = 0; l < WL; ++l) {
    d[N - 2][l] = A[N - 2][N - 2][l];
    e[N - 2][l] = A[N - 1][N - 2][l];
    d[N - 1][l] = A[N - 1][N - 1][l];
    e[N - 1][l] = T(0);
  }
  // ---- implicit QL (tqli): e[i] couples d[i] and d[i + 1]; eigenvalue L converges when e[L] is negligible
  constexpr T eps = std::numeric_limits<T>::epsilon(), floor_ = eps * T(1e-3);
  for (int L = 0; L < N; ++L) {
    for (int iter = 0; iter < 40; ++iter) {
      T m[WL];  // per lane: the first negligible coupling at or after L (as a value: the lane loops stay in T)
#pragma omp simd
      for (int l = 0; l < WL; ++l) m[l] = T(N - 1);
      for (int i = N - 2; i >= L; --i)
#pragma omp simd
        for (int l = 0; l < WL; ++l) {
          T ae = std::abs(e[i][l]);
          const bool small = (ae <= eps * (std::abs(d[i][l]) + std::abs(d[i + 1][l]))) | (ae <= floor_);
          m[l] = small ? T(i) : m[l];
        }
      T mx = T(L);
      for (int l = 0; l < WL; ++l) mx = std::max(mx, m[l]);
      const int mmax = int(mx);
      if (mmax == L) break;  // every lane's eigenvalue L has converged
      T g[WL], s[WL], c[WL], p[WL], run[WL], broke[WL], dm[WL];
#pragma omp simd
      for (int l = 0; l < WL; ++l) dm[l] = T(0);
      for (int i = L; i < N; ++i)
#pragma omp simd
        for (int l = 0; l < WL; ++l) dm[l] = T(i) == m[l] ? d[i][l] : dm[l];
#pragma omp simd
      for (int l = 0; l < WL; ++l) {
        const bool act = m[l] != T(L);
        T el = act ? e[L][l] : T(1);
        T gg = (d[L + 1][l] - d[L][l]) / (T(2) * el);
        T r = std::sqrt(gg * gg + T(1));
        g[l] = act ? dm[l] - d[L][l] + el / (gg + (gg >= T(0) ? r : -r)) : T(0);
        s[l] = T(1); c[l] = T(1); p[l] = T(0);
        run[l] = act ? T(1) : T(0);
        broke[l] = T(0);
      }
      for (int i = mmax - 1; i >= L; --i) {
        T cc[WL], ss[WL];
#pragma omp simd
        for (int l = 0; l < WL; ++l) {
          const bool act = (run[l] > T(0)) & (T(i) < m[l]);
          T f = s[l] * e[i][l], b = c[l] * e[i][l];
          T r = std::sqrt(f * f + g[l] * g[l]);
          const bool brk = act & (r <= T(0));
          const bool ok = act & (r > T(0));
          T rs = r > T(0) ? r : T(1);
          T sn = f / rs, cn = g[l] / rs;
          T gq = d[i + 1][l] - p[l];
          T rr = (d[i][l] - gq) * sn + T(2) * cn * b;
          T pn = sn * rr;
          e[i + 1][l] = act ? r : e[i + 1][l];
          d[i + 1][l] = ok ? gq + pn : (brk ? d[i + 1][l] - p[l] : d[i + 1][l]);
          s[l] = ok ? sn : s[l];
          c[l] = ok ? cn : c[l];
          p[l] = ok ? pn : p[l];
          g[l] = ok ? cn * rr - b : g[l];
          run[l] = brk ? T(0) : run[l];
          broke[l] = brk ? T(1) : broke[l];
          cc[l] = ok ? cn : T(1);
          ss[l] = ok ? sn : T(0);
        }
        for (int k = 0; k < N; ++k)
#pragma omp simd
          for (int l = 0; l < WL; ++l) {
            T f = Z[k][i + 1][l], zi = Z[k][i][l];
            Z[k][i + 1][l] = ss[l] * zi + cc[l] * f;
            Z[k][i][l] = cc[l] * zi - ss[l] * f;
          }
      }
      for (int l = 0; l < WL; ++l) {
        if (run[l] > T(0)) { d[L][l] -= p[l]; e[L][l] = g[l]; }
        if (run[l] > T(0) || broke[l] > T(0)) e[int(m[l])][l] = T(0);
      }
    }
  }
  lanes_rebuild(A, Z, d, scale, abs_mode);
}

}  // namespace cpu
}  // namespace torchbend
