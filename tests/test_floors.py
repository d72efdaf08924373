"""benchmarks/floors.py: the compute floor's model (the FMA units' work against the divider's), the measured op
costs and the op counts by name that it reads."""
import math

import pytest
import torch

import torchbend as tb
from tests.helpers import benchmark_script

floors = benchmark_script("floors")


def test_compute_floor_is_the_busier_unit():
    counts = {"mul": 80.0, "add": 20.0, "div": 10.0, "sqrt": 2.0, "sin": 4.0}
    costs = {"div": 1.0, "sqrt": 0.5, "sin": 0.25}
    rate = 1e11  # flop/s: 100 plain flops take 1 ns
    fma = 100 / rate * 1e9 + 4 * 0.25  # the plain arithmetic and the sines share the FMA units
    divider = 10 * 1.0 + 2 * 0.5
    assert floors.compute_floor_ns(counts, rate, costs) == pytest.approx(max(fma, divider))  # the divider: 11 ns
    cheap = dict(costs, div=0.01, sqrt=0.01)
    assert floors.compute_floor_ns(counts, rate, cheap) == pytest.approx(fma)
    # without costs (a GPU record, or one written before they were measured): every op one flop
    assert floors.compute_floor_ns(counts, rate, None) == pytest.approx(116 / rate * 1e9)
    assert floors.compute_floor_ns(counts, rate, {}) == pytest.approx(116 / rate * 1e9)


def test_op_costs_measured_on_the_cpu_only():
    costs = floors.op_costs(torch.float64, n=4096, repeat=5)
    assert set(costs) == {"div", "atan2"} | set(floors.DIVIDER) | set(floors.TRANSCENDENTAL)
    assert all(math.isfinite(c) and c >= 0.0 for c in costs.values()), costs
    assert floors.op_costs(torch.float64, device="cuda") == {}


def test_op_counts_by_name_sum_to_the_flops():
    rest, faces = tb.scenes.random_curved_sheet(6, 6, amplitude=0.2, seed=0, dtype=torch.float64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3)
    x = rest + 0.01 * torch.randn(rest.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    v = torch.ones_like(x)
    counts = floors.ops_per_hinge(bend, x, v)
    flops = floors.flops_per_hinge(bend, x, v)
    assert set(counts) == set(floors.OPS) == set(flops)
    for op in floors.OPS:
        assert sum(counts[op].values()) == pytest.approx(flops[op])
    assert counts["energy"]["atan2"] == pytest.approx(1.0)  # one bend angle a hinge
    assert counts["gradient"]["index_add"] == pytest.approx(12.0)  # 12 coordinates scattered a hinge
    assert floors.compute_floor_ns(counts["energy"], 1e11, floors.op_costs(torch.float64, n=4096, repeat=5)) > 0
