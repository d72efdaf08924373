"""The package's structural rules (the energy-term protocol keeps the solver free of concrete energies; classes
and functions stay small enough to read): checked on the source, so that a later edit cannot silently undo them.
Function complexity is ruff's (``C901``, ``max-complexity`` in ``pyproject.toml``, run by CI)."""
from __future__ import annotations

import ast
import pathlib
import re

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "torchbend"
MAX_CLASS_LINES = 150
SOLVER_MODULES = ("newton.py", "directions.py", "linear.py", "line_search.py", "damping.py", "curvature.py",
                  "adjoint.py", "linearized.py")
CONCRETE = ("BendingEnergy", "MembraneEnergy", "SelfContact", "MeshCollider", "Sphere", "Plane", "Capsule",
            "Gravity")


def _sources():
    return sorted(PACKAGE.rglob("*.py"))


def test_no_class_above_the_line_limit():
    long = []
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef) and node.end_lineno is not None:
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_CLASS_LINES:
                    long.append(f"{path.relative_to(PACKAGE)}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, f"classes above {MAX_CLASS_LINES} lines: {long}"


def test_no_step_data_threaded_by_hand():
    found = [str(p.relative_to(PACKAGE)) for p in _sources() if "bend_kw" in p.read_text(encoding="utf-8")]
    assert not found, f"bend_kw in {found}: a term's time-step data travels in its StepContext"


@pytest.mark.parametrize("module", SOLVER_MODULES)
def test_the_solver_names_no_concrete_energy(module):
    """The solver iterates the model's terms; it names no energy (docstrings and comments aside)."""
    tree = ast.parse((PACKAGE / "sim" / module).read_text(encoding="utf-8"))
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    names |= {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
    names |= {a.name.split(".")[-1] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
    assert not names & set(CONCRETE), f"sim/{module} names {sorted(names & set(CONCRETE))}"


def test_ruff_limits_function_complexity_to_12():
    text = (PACKAGE.parent / "pyproject.toml").read_text(encoding="utf-8")
    match = re.search(r"max-complexity\s*=\s*(\d+)", text)
    assert match and int(match.group(1)) <= 12 and '"C90"' in text
