"""Layer 1, meshes: connectivity (the hinge convention), packing of several meshes, procedural meshes."""
from .packing import PackedMeshes, pack_meshes
from .topology import HingeTopology, mesh_and_rest

__all__ = ["HingeTopology", "PackedMeshes", "mesh_and_rest", "pack_meshes"]
