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
