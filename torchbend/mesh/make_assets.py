"""Regenerate the shipped meshes: ``python -m torchbend.mesh.make_assets [DIR]`` (default: ``torchbend/mesh/assets``).

``tests/test_mesh_io.py`` checks that the shipped files equal a regeneration."""
from __future__ import annotations

import os
import sys

from .garments import write_skirt_asset
from .io import ASSETS


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    folder = argv[0] if argv else ASSETS
    print(write_skirt_asset(os.path.join(folder, "skirt.obj")))


if __name__ == "__main__":
    main()
