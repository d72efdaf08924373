"""The examples under examples/ run and meet their own acceptance checks."""
import os
import runpy

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_demo_runs_and_is_accurate(capsys):
    demo = runpy.run_path(os.path.join(ROOT, "examples", "demo.py"))  # defines run(); main() only as a script
    out = demo["run"](n=12, repeat=1)
    printed = capsys.readouterr().out
    assert "hinges" in printed and "speed-up" in printed
    assert out["hinges"] > 0
    for name, err in out["errors"].items():
        assert err < 1e-12, (name, err)
    assert all(a > 0 and b > 0 for a, b in out["timings"].values())
