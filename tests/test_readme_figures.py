"""The time and accuracy figures of README.md and docs/ are the ones benchmarks/readme_figures.py measured.

Each figure sits between ``<!-- fig:NAME -->`` and ``<!-- /fig -->`` and must equal ``figures[NAME]``
of ``benchmarks/results/readme_figures.json`` (a hand edit of either is caught); a number with a unit of
time or length, or a percentage, outside those markers and outside code is refused unless it is listed
in ``ALLOWED`` below (settings and definitions, not measurements).
"""
import json
import os
import re

import pytest

from .helpers import ROOT, load_script

README = os.path.join(ROOT, "README.md")


figures_script = load_script("benchmarks", "readme_figures")
MEASURING = os.environ.get("TORCHBEND_README_FIGURES") == "measuring"
"""Set while benchmarks/readme_figures.py times the test suite: it rewrites the JSON and README.md
meanwhile, and runs the two comparisons below itself once it has."""

ALLOWED = {
    "has run 5 s",  # the solver's INFO logging threshold (a setting)
}
"""Unmarked phrases with a unit that are settings or definitions, not measured figures."""

MEASURE = re.compile(r"(?:about |~)?\b\d+(?:\.\d+)?(?:[eE][+-]?\d+)?\s?(?:s|ms|us|µs|ns|min|minutes?|seconds?|h|hours?|mm|cm|"
                     r"mJ|µm|um|%|x faster|x slower|tests?)\b(?!-)|\d+(?:\.\d+)?\s?%")


def _readme() -> str:
    """README.md and the pages of docs/ (figures may sit in either), one text."""
    texts = []
    for path in figures_script.documents():
        with open(path, encoding="utf-8") as f:
            texts.append(f.read())
    return "\n".join(texts)


def _recorded() -> dict:
    with open(figures_script.RESULTS) as f:
        return json.load(f)


def test_readme_figures_equal_the_recorded_measurements():
    if MEASURING:
        pytest.skip("readme_figures.py is measuring the suite; it checks README.md against the JSON afterwards")
    recorded = _recorded()
    marked = figures_script.readme_markers(_readme())
    assert len(marked) >= 15, sorted(marked)
    unknown = sorted(set(marked) - set(recorded["figures"]))
    assert not unknown, f"README.md marks figures no measurement produced: {unknown}"
    wrong = {name: (values, recorded["figures"][name]) for name, values in marked.items()
             if any(v != recorded["figures"][name] for v in values)}
    assert not wrong, f"README.md figures differ from benchmarks/results/readme_figures.json (README, JSON): {wrong}"
    # the recorded figures come from full runs on a described machine
    assert not any(m.get("quick") for m in recorded["measurements"].values())
    assert set(recorded["measurements"]) == set(figures_script.MEASUREMENTS)
    assert recorded["machine"]["cores"] and recorded["machine"]["cpu"] and recorded["machine"]["note"]
    # each measurement names the CPU it ran on (model and vector extensions), which README.md quotes
    assert all(m.get("machine", {}).get("cpu") and "vector_extensions" in m["machine"]
               for m in recorded["measurements"].values())


def test_rewriting_the_readme_from_the_json_changes_nothing():
    if MEASURING:
        pytest.skip("readme_figures.py is measuring the suite; it checks README.md against the JSON afterwards")
    text = _readme()
    assert figures_script.rewrite(text, _recorded()["figures"]) == text
    assert figures_script.combined_figures(_recorded()) == _recorded()["figures"]


def _prose(text: str) -> str:
    """README prose and the comments of its code blocks: code, marked figures and HTML comments removed."""
    comments = " ".join(re.findall(r"#[^\n]*", " ".join(re.findall(r"^```\w*\n(.*?)^```", text, flags=re.M | re.S))))
    text = re.sub(r"^```.*?^```[ \t]*$", " ", text, flags=re.M | re.S) + " " + comments
    text = figures_script.MARKER.sub(" FIGURE ", text)
    text = re.sub(r"<!--.*?-->", " ", text, flags=re.S)
    return re.sub(r"`[^`\n]*`", " CODE ", text)


def test_no_unmarked_measurement_in_readme_prose():
    prose = _prose(_readme())
    found = []
    for m in MEASURE.finditer(prose):
        context = prose[max(0, m.start() - 40):m.end() + 10]
        if not any(a in context for a in ALLOWED):
            found.append(" ".join(context.split()))
    assert not found, "unmarked figures in README.md (mark them and measure them in benchmarks/readme_figures.py):\n" + "\n".join(found)


def test_the_unmarked_figure_check_catches_hand_typed_figures():
    for typed in ("takes about 40 s on", "```bash\nrun x   # folds a towel (84 s on 2 cores)\n```", "lay 3.1, 1.9 and 21 mm RMS", "2.5 min on the",
                  "(602 tests, 42 skipped", "0.13 to 0.48 mJ above", "ends 1.4% above"):
        assert MEASURE.search(_prose(typed)), typed
    assert not MEASURE.search(_prose("<!-- fig:tests_s -->150 s<!-- /fig --> and `sleep 5 s` and 30k-hinge"))


def test_figure_formatting():
    assert [figures_script.seconds(v) for v in (47.4, 9.96, 6.24, 0.81)] == ["47 s", "10 s", "6.2 s", "0.8 s"]
    assert [figures_script.milliseconds(v) for v in (0.0123, 0.00225)] == ["12 ms", "2.2 ms"]
    assert [figures_script.sig(v) for v in (0.0078123, 20.6, 3.1049, 1234.0)] == ["0.0078", "21", "3.1", "1200"]
    assert figures_script.listing(["3.1", "1.9", "21"]) == "3.1, 1.9 and 21"
    counts = figures_script._pytest_counts(
        "SKIPPED [40] tests/test_cuda.py:12: CUDA is not available\nSKIPPED [2] tests/x.py:3: needs jax\n"
        "600 passed, 42 skipped, 7 deselected in 150.2s\n")
    assert counts == {"passed": 600, "skipped": 42, "deselected": 7, "skipped_gpu": 40, "skipped_while_measuring": 0}
    counts = figures_script._pytest_counts(
        "SKIPPED [2] tests/test_readme_figures.py:40: readme_figures.py is measuring the suite; ...\n"
        "598 passed, 44 skipped in 150.2s\n")
    assert counts["passed"] == 600 and counts["skipped"] == 42 and counts["skipped_while_measuring"] == 2
