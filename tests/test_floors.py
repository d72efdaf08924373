"""benchmarks/floors.py and the floor columns of benchmarks/tables.py: the compute floor's model (the FMA units'
work against the divider's), the measured op costs and the op counts by name that it reads."""
import math

import pytest
import torch

import torchbend as tb
from tests.helpers import benchmark_script, load_script

floors = benchmark_script("floors")


def test_compute_floor_is_the_busier_unit():
    counts = {"mul": 80.0, "add": 20.0, "div": 10.0, "sqrt": 2.0, "tan": 4.0}
    costs = {"div": 1.0, "sqrt": 0.5, "tan": 0.25, "sin": 0.3, "cos": 0.2}
    rate = 1e11  # flop/s: 100 plain flops take 1 ns
    fma = 100 / rate * 1e9 + 4 * 0.25  # the plain arithmetic and the tangents share the FMA units
    divider = 10 * 1.0 + 2 * 0.5
    assert floors.compute_floor_ns(counts, rate, costs) == pytest.approx(max(fma, divider))  # the divider: 11 ns
    cheap = dict(costs, div=0.01, sqrt=0.01)
    assert floors.compute_floor_ns(counts, rate, cheap) == pytest.approx(fma)
    # costs are one thread's: at 4 threads the costly ops take a quarter (the flop rate is the run's own)
    assert floors.compute_floor_ns(counts, rate, costs, threads=4) == pytest.approx(max(1.0 + 1.0 / 4, 11.0 / 4))
    # without costs (a GPU record, or one written before they were measured): every op one flop
    assert floors.compute_floor_ns(counts, rate, None) == pytest.approx(116 / rate * 1e9)
    assert floors.compute_floor_ns(counts, rate, {}) == pytest.approx(116 / rate * 1e9)


def test_sine_and_cosine_pair_into_one_sincos():
    costs = {"sin": 0.5, "cos": 0.4}
    rate = 1e30  # arithmetic free
    # three pairs at the dearer cost (0.5), one sine alone
    assert floors.compute_floor_ns({"sin": 4.0, "cos": 3.0}, rate, costs) == pytest.approx(3 * 0.5 + 0.5)
    assert floors.compute_floor_ns({"cos": 2.0}, rate, costs) == pytest.approx(0.8)


def test_op_costs_measured_on_one_thread():
    threads = torch.get_num_threads()
    costs = floors.op_costs(torch.float64, repeat=20)
    assert torch.get_num_threads() == threads  # restored
    assert set(costs) == set(floors.DIVIDER) | set(floors.TRANSCENDENTAL)
    assert all(math.isfinite(c) and c >= 0.0 for c in costs.values()), costs
    assert costs["atan2"] > 0.0, costs  # atan2 costs more than a multiplication on every machine
    assert floors.op_costs(torch.float64, device="cuda") == {}


def test_op_counts_by_name():
    rest, faces = tb.scenes.random_curved_sheet(6, 6, amplitude=0.2, seed=0, dtype=torch.float64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3)
    x = rest + 0.01 * torch.randn(rest.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    counter = floors.FlopCounter()
    with torch.no_grad(), counter:
        bend.gradient(x, backend="eager")
    assert sum(counter.by_op.values()) == counter.total > 0
    counts = floors.ops_per_hinge(bend, x, torch.ones_like(x))
    assert set(counts) == set(floors.OPS)
    assert counts["gradient"] == pytest.approx({k: n / bend.hinge_count for k, n in counter.by_op.items()})
    assert counts["energy"]["atan2"] == pytest.approx(1.0)  # one bend angle a hinge
    assert counts["gradient"]["index_add"] == pytest.approx(12.0)  # 12 coordinates scattered a hinge


def _record(op_costs, ops_per_hinge):
    config = {"hinges": 1000, "vertices": 400, "nnz": 9000, "param_elems": 2001, "dtype": "float64",
              "flops_per_hinge": {op: 100.0 for op in floors.OPS},
              "rows": [{"method": "torchbend", "op": op, "ns": 50.0} for op in floors.OPS]}
    if ops_per_hinge:
        config["ops_per_hinge"] = {op: {"mul": 90.0, "div": 10.0} for op in floors.OPS}
    used = {"bandwidth": 1e10, "flops": {"float64": 1e11}, "threads": 1}
    if op_costs is not None:
        used["op_costs"] = op_costs
    return {"dtypes": ["float64"], "configs": [config],
            "floors": {"used": used, "before": used, "after": used}}


@pytest.mark.parametrize("kind", ["old", "cpu", "gpu"])
def test_floor_table_renders_every_record(kind):
    """Records without op costs (written before they were measured, or on a GPU: empty costs) render with one flop
    an op; a CPU record with costs prices the divisions on the divider."""
    tables = load_script("benchmarks", "tables")
    costs = {"old": None, "cpu": {"float64": {"div": 1.0}}, "gpu": {"float64": {}}}[kind]
    result = _record(costs, kind != "old")
    lines = tables.floor_table(result)
    row = next(line for line in lines if line.startswith("| float64 | energy |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    compute_floor = float(cells[5])
    assert compute_floor == pytest.approx(10.0 if kind == "cpu" else 1.0)  # 10 divisions at 1 ns, or 100 flops
    assert ("op costs" in lines[-1]) == (kind == "cpu")
