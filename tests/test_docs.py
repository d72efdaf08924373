"""The documentation site builds with no warning (``mkdocs build --strict``: broken links, docstrings griffe cannot
read), and its API reference documents every public name of torchbend, tb.mesh, tb.losses, tb.losses.hood and
tb.scenes (the guides' code blocks run in tests/test_readme.py)."""
import importlib
import os
import re
import subprocess
import sys

import pytest

from .helpers import ROOT

pytest.importorskip("mkdocs", reason="the docs extra (pip install -e '.[docs]') is not installed")
pytest.importorskip("mkdocstrings_handlers.python", reason="the docs extra is not installed")

PAGES = {"torchbend": "api/torchbend", "torchbend.mesh": "api/mesh", "torchbend.losses": "api/losses",
         "torchbend.losses.hood": "api/hood", "torchbend.scenes": "api/scenes"}
SUBMODULES = {"losses", "mesh", "scenes", "hood", "__version__"}  # documented on their own pages (or a string)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(out)], cwd=ROOT,
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, f"mkdocs build --strict failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return out


@pytest.mark.parametrize("module", sorted(PAGES))
def test_api_reference_documents_every_public_name(site, module):
    html = open(os.path.join(site, PAGES[module], "index.html"), encoding="utf-8").read()
    anchors = set(re.findall(r'id="([\w.]+)"', html))
    names = [n for n in importlib.import_module(module).__all__ if n not in SUBMODULES]
    missing = [n for n in names if f"{module}.{n}" not in anchors]
    assert not missing, f"{module}: no entry in the API reference for {missing}"


def test_guides_are_in_the_site(site):
    guides = sorted(f[:-3] for f in os.listdir(os.path.join(ROOT, "docs", "guides")) if f.endswith(".md"))
    assert len(guides) >= 8
    for g in guides:
        assert os.path.isfile(os.path.join(site, "guides", g, "index.html")), g
