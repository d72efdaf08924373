"""Meshes of different topologies packed into one (PyTorch3D's "packed" representation)."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["PackedMeshes", "pack_meshes"]


@dataclass(frozen=True)
class PackedMeshes:
    """Meshes of different topologies packed into one (PyTorch3D-style "packed" representation).

    Attributes:
        verts: ``(sum V_m, 3)`` concatenated vertex positions [m].
        faces: ``(sum F_m, 3)`` int64 faces with vertex indices offset into ``verts``.
        vert_offsets: ``(M + 1,)`` int64; mesh ``m`` owns vertices ``vert_offsets[m]:vert_offsets[m+1]``.
        face_mesh: ``(sum F_m,)`` int64 mesh index of each face.
    """

    verts: Tensor
    faces: Tensor
    vert_offsets: Tensor
    face_mesh: Tensor

    @property
    def mesh_count(self) -> int:
        return int(self.vert_offsets.shape[0] - 1)

    def pack(self, verts_list) -> Tensor:
        """Concatenate per-mesh positions ``[(V_m, 3)]`` (e.g. deformed states) into ``(sum V_m, 3)``."""
        sizes = (self.vert_offsets[1:] - self.vert_offsets[:-1]).tolist()
        if len(verts_list) != len(sizes):
            raise ValueError(f"expected {len(sizes)} meshes, got {len(verts_list)}")
        for m, (v, n) in enumerate(zip(verts_list, sizes)):
            if tuple(v.shape) != (n, 3):
                raise ValueError(f"mesh {m}: positions must have shape ({n}, 3), got {tuple(v.shape)}")
        return torch.cat(list(verts_list), 0)

    def unpack(self, x: Tensor) -> list[Tensor]:
        """Split packed ``(..., sum V_m, 3)`` back into per-mesh ``(..., V_m, 3)`` views."""
        sizes = (self.vert_offsets[1:] - self.vert_offsets[:-1]).tolist()
        return list(torch.split(x, sizes, dim=-2))


def pack_meshes(meshes) -> PackedMeshes:
    """Pack ``[(verts (V_m, 3), faces (F_m, 3)), ...]`` into one :class:`PackedMeshes`."""
    meshes = list(meshes)
    if not meshes:
        raise ValueError("pack_meshes needs at least one (verts, faces) pair")
    verts, faces, face_mesh, offsets = [], [], [], [0]
    for m, (v, f) in enumerate(meshes):
        v = torch.as_tensor(v)
        f = torch.as_tensor(f)
        if v.ndim != 2 or v.shape[-1] != 3:
            raise ValueError(f"mesh {m}: verts must have shape (V, 3), got {tuple(v.shape)}")
        if f.ndim != 2 or f.shape[-1] != 3:
            raise ValueError(f"mesh {m}: faces must have shape (F, 3), got {tuple(f.shape)}")
        if f.numel() and (int(f.min()) < 0 or int(f.max()) >= v.shape[0]):
            raise ValueError(f"mesh {m}: face indices must lie in [0, {v.shape[0]})")
        verts.append(v)
        faces.append(f.to(torch.int64) + offsets[-1])
        face_mesh.append(torch.full((f.shape[0],), m, dtype=torch.int64))
        offsets.append(offsets[-1] + v.shape[0])
    return PackedMeshes(
        verts=torch.cat(verts, 0),
        faces=torch.cat(faces, 0),
        vert_offsets=torch.tensor(offsets, dtype=torch.int64),
        face_mesh=torch.cat(face_mesh, 0),
    )

