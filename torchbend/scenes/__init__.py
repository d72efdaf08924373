"""Layer 7, scenes: procedural meshes (``torchbend.scenes.grid`` and friends, defined in
:mod:`torchbend.mesh.procedural`), YAML scene configs (:mod:`torchbend.scenes.config`) and the runner
CLI (``python -m torchbend.scenes CONFIG``, :mod:`torchbend.scenes.run`)."""
from ..mesh.procedural import cylinder, grid, icosphere, mannequin, random_curved_sheet, single_hinge

__all__ = ["cylinder", "grid", "icosphere", "mannequin", "random_curved_sheet", "single_hinge"]
