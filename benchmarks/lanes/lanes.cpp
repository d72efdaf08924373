// The lane functions of the CPU kernels timed alone (benchmarks/bm_lanes.py): the bend angles of tiles of
// stencils (theta_tile), psi and its derivatives of the tan model (psi_lane), and tb_atan2v, each over 1e5
// lanes of random data held in L2, fastest of `repeat` passes, in ns per lane.  Compiled against the csrc
// directory given to bm_lanes.py, so that two trees (before and after a change) and two -march targets can be
// compared on one machine without building the extension.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <vector>

#include "hinge_ops.h"

using namespace torchbend;
constexpr int W = 16;  // the tiles of the energy, gradient and product operators (WL in cpu_tiles.h)

__attribute__((noinline)) static void run_theta(const double (*X)[12][W], int nt, double* out) {
  for (int t = 0; t < nt; ++t) theta_tile<double, W>(X[t], out + W * t);
}

__attribute__((noinline)) static void run_psi(const double* th, const double* rest, int n, double* out) {
  for (int t = 0; t < n; t += W) {
    TB_LANES_AGG(W) {
      double d1, d2, ps;
      psi_lane<1, false>(th[t + l], 1.0, 1.0, rest[t + l], 0.0, 0.0, ps, d1, d2, static_cast<double*>(nullptr));
      out[t + l] = ps + d1 + d2;
    }
  }
}

__attribute__((noinline)) static void run_atan2(const double* y, const double* x, int n, double* out) {
  for (int t = 0; t < n; t += W) {
    TB_LANES_AGG(W) out[t + l] = tb_atan2v(y[t + l], x[t + l]);
  }
}

int main(int argc, char** argv) {
  const int repeat = argc > 1 ? std::atoi(argv[1]) : 200;
  const int nt = 100000 / W, n = nt * W;
  std::vector<double> X(size_t(nt) * 12 * W), th(n), rest(n), out(n), y(n), x(n);
  std::mt19937_64 g(1);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (auto& v : X) v = u(g);
  for (int i = 0; i < n; ++i) { rest[i] = 2.0 * u(g); y[i] = u(g); x[i] = u(g); }
  auto Xt = reinterpret_cast<const double (*)[12][W]>(X.data());
  double sink = 0.0;
  auto timeit = [&](const char* name, auto f) {
    double best = 1e30;
    for (int r = 0; r < repeat; ++r) {
      auto t0 = std::chrono::steady_clock::now();
      f();
      best = std::min(best, std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    }
    std::printf("%s %.3f\n", name, best / n * 1e9);
  };
  run_theta(Xt, nt, th.data());
  for (auto& t : th) t = std::min(std::max(t, -3.0), 3.0);  // inside the tan model's (-pi, pi)
  timeit("theta_tile", [&] { run_theta(Xt, nt, out.data()); });
  timeit("psi_lane", [&] { run_psi(th.data(), rest.data(), n, out.data()); });
  timeit("tb_atan2v", [&] { run_atan2(y.data(), x.data(), n, out.data()); });
  // the outputs' sum (fixed order): equal across trees and -march targets where the lane functions agree bit for bit
  run_theta(Xt, nt, out.data());
  for (double v : out) sink += v;
  run_psi(th.data(), rest.data(), n, out.data());
  for (double v : out) sink += v;
  run_atan2(y.data(), x.data(), n, out.data());
  for (double v : out) sink += v;
  std::printf("# checksum %a\n", sink);
  return 0;
}
