from torchbend import demo


def test_demo_runs_and_is_accurate(capsys):
    out = demo.run(n=12, repeat=1)
    printed = capsys.readouterr().out
    assert "hinges" in printed and "speed-up" in printed
    assert out["hinges"] > 0
    for name, err in out["errors"].items():
        assert err < 1e-12, (name, err)
    assert all(a > 0 and b > 0 for a, b in out["timings"].values())
