"""benchmarks/scene_campaign.py (the contact robustness campaign): two tiny scenes pass, one in this process and one
through the runner's child process, with the summary's fields; both intersection tests see a cloth cut by a body;
every line of benchmarks/scene_campaign.txt parses, and an unknown key or value does not."""
import json
import math

import pytest

from tests.helpers import ROOT, benchmark_script

campaign = benchmark_script("scene_campaign")

SUMMARY_FIELDS = {"args", "tag", "V", "F", "steps_total", "passed", "max_iters", "total_s", "min_dist", "fail", "check"}
PILE = ["kind=drop", "body=meshfloor", "layers=2", "n=5", "L=0.1", "v0=1", "mu=0.3", "steps=3"]
INCLINE = ["kind=incline", "body=plane", "n=5", "L=0.1", "ang=30", "mu=0.3", "h=5e-4", "steps=3"]


def test_a_small_pile_passes_every_step_with_the_summary_fields():
    rec = campaign.run_scene(campaign.parse_scene(PILE + ["tag=pile"]), " ".join(PILE), log=None)
    rec = json.loads(json.dumps(rec))  # what the SUMMARY line carries
    assert set(rec) == SUMMARY_FIELDS, rec
    assert rec["fail"] is None and rec["passed"] == rec["steps_total"] == 3, rec
    assert rec["V"] == 2 * 25 and rec["F"] == 2 * 32 and rec["tag"] == "pile"
    assert rec["max_iters"] >= 1 and rec["total_s"] > 0 and 0 < rec["min_dist"] < math.inf
    assert rec["check"] in ("ipctk", "exact")


def test_the_runner_runs_a_small_incline_in_a_child_process(tmp_path, capsys):
    scenes = tmp_path / "scenes.txt"
    scenes.write_text("# a comment\n\nI01 " + " ".join(INCLINE) + "  # and another\n")
    out = tmp_path / "results.jsonl"
    assert campaign.main(["--all", "--list", str(scenes), "--timeout", "120", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "torch " in text and "commit" in text, text
    row = next(line for line in text.splitlines() if line.startswith("I01"))
    assert row.split()[1] == "3/3" and row.endswith("ok"), row
    assert text.rstrip().endswith("1 of 1 scenes passed")
    (rec,) = [json.loads(line) for line in out.read_text().splitlines()]
    assert set(rec) == SUMMARY_FIELDS | {"id", "wall_s"} and rec["id"] == rec["tag"] == "I01", rec
    assert rec["fail"] is None and rec["passed"] == 3 and rec["min_dist"] > 0


@pytest.mark.parametrize("check", ["exact", "ipctk"])
def test_a_cloth_cut_by_a_box_fails_before_its_first_step(check):
    if check == "ipctk":
        pytest.importorskip("ipctk")
    a = campaign.parse_scene(["kind=drop", "body=box", "fsize=0.05", "n=5", "L=0.1", "h=-0.01", "steps=2",
                              f"check={check}"])
    rec = campaign.run_scene(a, log=None)
    assert rec["passed"] == 0 and rec["fail"]["step"] == -1 and "mesh intersection" in rec["fail"]["why"], rec


def test_every_scene_of_the_list_parses():
    scenes = campaign.read_scene_list(f"{ROOT}/benchmarks/scene_campaign.txt")
    ids = [sid for sid, _ in scenes]
    assert len(scenes) == 59 and len(set(ids)) == len(ids)
    assert {"S01", "S41", "S52", "V41"} <= set(ids)
    for sid, args in scenes:
        a = campaign.parse_scene(args)
        assert a["steps"] > 0, sid


@pytest.mark.parametrize("bad", ["colour=red", "kind=wobble", "n=1.5", "dtype=f16", "steps"])
def test_an_unknown_key_or_value_is_rejected(bad):
    with pytest.raises(ValueError):
        campaign.parse_scene(["kind=drop", bad])
