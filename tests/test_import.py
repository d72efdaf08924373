"""``import torchbend`` stays light: nothing heavy is imported with it (torch.compile's machinery, the training
and scene extras), and the import-time stand-in for :func:`torch.compiler.assume_constant_result` marks a function
as PyTorch's own does."""
import subprocess
import sys

import torch

from torchbend._torch_compat import assume_constant_result

HEAVY = ("torch._dynamo", "tensorboard", "torch.utils.tensorboard", "matplotlib", "pytorch_kinematics", "pydantic",
         "yaml", "meshio")


def test_import_loads_nothing_heavy():
    code = ("import sys, torch; before = set(sys.modules); import torchbend; "
            f"print(','.join(sorted(m for m in {HEAVY!r} if m in set(sys.modules) - before)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"import torchbend imported {out} (load them where they are used)"


def test_constant_result_marker_is_torchs():
    def ours():
        return 1

    def theirs():
        return 1

    assert assume_constant_result(ours) is ours
    torch.compiler.assume_constant_result(theirs)
    assert vars(ours) == vars(theirs) == {"_dynamo_marked_constant": True}


BLOCK = """
import sys

class Block:
    def find_spec(self, name, path=None, target=None):
        if name.partition('.')[0] in {blocked!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)

sys.meta_path.insert(0, Block())
"""


def _without(blocked: set, code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", BLOCK.format(blocked=blocked) + code], capture_output=True, text=True)


def test_core_without_extras_and_one_line_errors_naming_them(tmp_path):
    """Without the optional packages the core runs (bending and membrane energy, gradient, HVP); a feature that needs
    one raises a one-line ImportError naming the extra that installs it."""
    extras = {"pydantic", "yaml", "tqdm", "matplotlib", "meshio", "pytorch_kinematics", "tensorboard"}
    core = ("import torch, torchbend as tb\n"
            "x, f = tb.scenes.grid(6, 5, dtype=torch.float64)\n"
            "bend = tb.BendingEnergy(f, x, stiffness=1e-3); y = x + 0.01 * torch.randn_like(x)\n"
            "print(float(bend(y)), float(bend.gradient(y).norm()), float(bend.hvp(y, y).norm()))\n"
            "mem = tb.MembraneEnergy(f, x, young=1e5, poisson=0.3, thickness=1e-3)\n"
            "print(float(mem(y)), float(mem.gradient(y).norm()), float(mem.hvp(y, y).norm()))\n"
            f"import sys; print(sorted(m for m in sys.modules if m.partition('.')[0] in {extras!r}))\n")
    r = _without(extras, core)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "[]"
    ply = tmp_path / "tri.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                   "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    cases = (("import torchbend.scenes.config", "scenes"), ("from torchbend.robot import Robot; Robot()", "robot"),
             (f"import torchbend as tb; tb.mesh.load({str(ply)!r})", "io"))
    probe = "".join(f"try:\n    {code}\nexcept Exception as e:\n    print(type(e).__name__ + ': ' + str(e))\n"
                    for code, _ in cases)
    r = _without(extras, probe)
    lines = r.stdout.strip().splitlines()
    assert r.returncode == 0 and len(lines) == len(cases), r.stderr[-2000:]
    for (code, extra), line in zip(cases, lines):
        assert line.startswith("ImportError: ") and f"pip install 'torchbend[{extra}]'" in line, (code, line)
