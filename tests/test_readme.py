"""Every ```python block of README.md runs as written, in order, in one namespace; so does every page of docs/
(each page in a namespace of its own).  The shell commands of both name existing scripts and options."""
import glob
import os
import re
import traceback

import pytest
import torch

README = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "README.md")
PAGES = sorted(glob.glob(os.path.join(os.path.dirname(README), "docs", "**", "*.md"), recursive=True))
"""The pages of docs/ (guides, API reference stubs)."""


def python_blocks(text: str) -> list[str]:
    """The bodies of the fenced ```python blocks of a Markdown text, in order."""
    return re.findall(r"^```python[ \t]*\n(.*?)^```[ \t]*$", text, flags=re.M | re.S)


def test_readme_has_python_blocks():
    blocks = [b for path in [README, *PAGES] for b in python_blocks(open(path, encoding="utf-8").read())]
    assert len(blocks) >= 10 and python_blocks(open(README, encoding="utf-8").read())


def _run_blocks(path: str) -> None:
    blocks = python_blocks(open(path, encoding="utf-8").read())
    torch.manual_seed(0)
    namespace: dict = {"__name__": "__readme__"}
    name = os.path.relpath(path, os.path.dirname(README))
    for i, block in enumerate(blocks):
        try:
            exec(compile(block, f"{name} python block {i}", "exec"), namespace)
        except Exception:
            pytest.fail(f"{name} python block {i} failed:\n{block}\n{traceback.format_exc()}", pytrace=False)


def test_readme_python_blocks_run_in_order():
    _run_blocks(README)


def test_docs_have_pages():
    assert len(PAGES) >= 10 and any(p.endswith(os.path.join("guides", "solver.md")) for p in PAGES)


@pytest.mark.parametrize("page", [os.path.relpath(p, os.path.dirname(README)) for p in PAGES])
def test_docs_python_blocks_run_in_order(page):
    _run_blocks(os.path.join(os.path.dirname(README), page))


# ------------------------------------------------------------------------------ shell commands
ROOT = os.path.dirname(README)


def bash_commands(text: str) -> list[list[str]]:
    """The commands of the fenced ```bash blocks, split into words (comments dropped, ``&&`` chains split)."""
    import shlex

    out = []
    for block in re.findall(r"^```bash[ \t]*\n(.*?)^```[ \t]*$", text, flags=re.M | re.S):
        for line in block.splitlines():
            words = shlex.split(line, comments=True)
            while words:
                cut = words.index("&&") if "&&" in words else len(words)
                out.append(words[:cut])
                words = words[cut + 1:]
    return out


def _script_parser(path: str):
    """The check of a command line of a script of train/ or of ``python -m torchbend.scenes``:
    ``argv -> None``, parsing the options (``SystemExit`` on a bad one) and loading the config with
    the ``--set`` overrides (``ValueError`` naming an unknown key)."""
    from torchbend.scenes import cli, run
    from torchbend.scenes.config import SceneConfig, load_config

    if path == "-m torchbend.scenes":
        def check_scene(argv):
            a = cli.parse_args(run.parser(), argv)
            load_config(a.config, SceneConfig, a.overrides)
        return check_scene
    from tests.helpers import train_script

    name = os.path.splitext(os.path.basename(path))[0]
    if os.path.dirname(path) != "train":
        raise AssertionError(f"README runs {path}: add a check of its options to tests/test_readme.py")
    script = train_script(name)

    def check_script(argv):
        a = script.parse_args(argv)
        load_config(a.config, script.Config, a.overrides)
    return check_script


def _check_files(words: list[str]) -> None:
    for w in words:
        if w.endswith((".py", ".yaml", ".yml", ".urdf", ".obj")) and not w.startswith("runs/"):
            assert os.path.isfile(os.path.join(ROOT, w)), f"README names {w}, which does not exist"


def _check_pip(words: list[str]) -> None:
    import tomllib

    extras = set(tomllib.load(open(os.path.join(ROOT, "pyproject.toml"), "rb"))["project"]["optional-dependencies"])
    for w in words:
        m = re.fullmatch(r"\.\[([\w,-]+)\]", w)
        if m:
            missing = set(m.group(1).split(",")) - extras
            assert not missing, f"README installs extras {sorted(missing)} that pyproject.toml does not define"
    if "--no-build-isolation" in words:
        assert "-e" in words or "." in words


def _all_text() -> str:
    return "\n".join(open(p, encoding="utf-8").read() for p in [README, *PAGES])


def test_readme_code_blocks_are_python_or_bash():
    # the two kinds the tests run or check; a new kind needs a check here
    for path in [README, *PAGES]:
        fences = re.findall(r"^```(\w*)[ \t]*$", open(path, encoding="utf-8").read(), flags=re.M)
        assert set(fences[0::2]) <= {"python", "bash"} and not any(fences[1::2]), (path, fences)


def test_readme_shell_commands_name_existing_scripts_and_options():
    commands = bash_commands(_all_text())
    assert len(commands) >= 8
    for words in commands:
        _check_files(words)
        if words[0] == "pip":
            _check_pip(words)
        elif words[0] == "torchrun":
            script = next(i for i, w in enumerate(words) if w.endswith(".py"))
            _script_parser(words[script])(words[script + 1:])
        elif words[:3] == ["python", "-m", "torchbend.scenes"]:
            _script_parser("-m torchbend.scenes")(words[3:])
        elif words[:3] == ["python", "-m", "pytest"]:
            marks = [words[i + 1] for i, w in enumerate(words) if w == "-m" and i > 1]
            assert all(m in ("slow", "gpu", "not slow") for m in marks), marks
        elif words[0] == "python" and words[1].endswith(".py"):
            _script_parser(words[1])(words[2:])
        else:
            raise AssertionError(f"README runs {' '.join(words)}: add a check of it to tests/test_readme.py")


def test_readme_inline_commands_name_existing_files_and_modules():
    import importlib.util

    text = _all_text()
    for cmd in re.findall(r"`(python [^`]+)`", text):
        words = cmd.split()
        if words[1] == "-m":
            assert importlib.util.find_spec(words[2]) is not None, f"README runs {cmd}: no module {words[2]}"
        else:
            _check_files(words[1:2])
