"""Layer 1, meshes: connectivity (the hinge convention), packing of several meshes, procedural meshes, mesh files
(``load``, ``clean``, ``save``, ``save_obj``) and the shipped garment (``skirt``, ``asset_path("skirt.obj")``)."""
from .garments import skirt
from .io import MeshReport, asset_path, clean, load, save, save_obj
from .packing import PackedMeshes, pack_meshes
from .topology import HingeTopology, lumped_areas, mesh_and_rest

__all__ = [
    "HingeTopology",
    "MeshReport",
    "PackedMeshes",
    "asset_path",
    "clean",
    "load",
    "lumped_areas",
    "mesh_and_rest",
    "pack_meshes",
    "save",
    "save_obj",
    "skirt",
]
