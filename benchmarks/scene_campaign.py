"""Contact robustness campaign: cloth scenes built through the public API, each step checked for convergence and
for exact intersections.

    python benchmarks/scene_campaign.py --all                              # every scene of scene_campaign.txt
    python benchmarks/scene_campaign.py --all --only S01 S08 --timeout 180 --out results.jsonl
    python benchmarks/scene_campaign.py kind=fold body=plane n=17 dtype=f32 steps=8   # one scene, step by step

One scene (``key=value`` arguments, :data:`PARAMS`; an unknown key or value is an error) is simulated with
:func:`torchbend.implicit_euler_step`.  A step fails when the solve does not converge, when the solver's
``min_distance`` is not positive, when a position is not finite, or when the state intersects: the cloth and the
body mesh are tested together in float64 with ``ipctk.has_intersections`` (the ``test`` extra), or, where ipctk is
not installed, with the exact edge-triangle crossing test of ``tests/test_self_contact.py``; vertices must lie
strictly outside an analytic sphere or plane.  The scene stops at its first failed step and prints a ``SUMMARY``
line of JSON (``tag``, ``args``, ``V``, ``F``, ``steps_total``, ``passed``, ``max_iters``, ``total_s``, ``min_dist``,
``fail``: ``null`` or the failed step's solver report; ``chord_depth`` with an analytic sphere).

Scene kinds (``kind=``):
    drop    an ``n x n`` cloth of side ``L`` (``layers > 1``: a pile, layer k turned ``k * twist`` degrees, ``gap``
            apart) falling at ``v0`` onto ``body``, ``h`` above its top
    fold    a strip (``L x L/2``) folded tightly onto itself (its layers ``fgap * dhat`` apart) falling onto ``body``
    flop    a strip half flat on the body, the other half standing up and swung over onto it at ``w`` rad/s
    push    a sheet (``pin=corners``: its corners pinned) hit from below by a body mesh moving up at ``vb`` m/s
    incline a sheet resting on a slope of ``ang`` degrees (``body=meshfloor``: a tilted MeshCollider, ``plane``: a
            tilted analytic Plane)
Bodies (``body=``): ``none``, ``sphere`` (analytic, radius ``R``), ``spheremesh`` (icosphere MeshCollider of
``sub`` subdivisions), ``plane`` (analytic z = 0), ``meshfloor`` (a square MeshCollider at z = 0 of ``fm x fm``
cells, side ``fsize``), ``box`` (a box MeshCollider of side ``fsize``, its top at z = 0).

The runner (``--all``) runs each scene of the list (``ID key=value ...`` lines) in a child process of its own
(``OMP_NUM_THREADS=1``), one at a time, killed after ``--timeout`` seconds, and prints a table row per scene and
"N of M scenes passed"; its exit status is 1 when a scene failed.  Pin it to one core for timings
(``taskset -c 1``).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import math
import os
import subprocess
import sys
import time
from typing import Any, Callable

import numpy as np
import torch

import torchbend as tb

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENE_LIST = os.path.join(HERE, "scene_campaign.txt")


def _float_or_none(v: str) -> float | None:
    return None if v in ("None", "none") else float(v)


def _int_or_none(v: str) -> int | None:
    return None if v in ("None", "none") else int(v)


def _time_limit(v: str) -> float | str | None:
    return v if v == "auto" else _float_or_none(v)


def _choice(*names: str) -> Callable[[str], str]:
    def convert(v: str) -> str:
        if v not in names:
            raise ValueError(f"{v!r} is not one of {', '.join(names)}")
        return v

    return convert


PARAMS: dict[str, tuple[Callable[[str], Any], Any]] = {
    # the scene
    "kind": (_choice("drop", "fold", "flop", "push", "incline"), "drop"),
    "body": (_choice("none", "sphere", "spheremesh", "plane", "meshfloor", "box"), "plane"),
    "dtype": (_choice("f32", "f64"), "f64"),
    "steps": (int, 20),
    "dt": (float, 0.01),
    "tag": (str, ""),
    # the cloth: n x n vertices, side L [m], h [m] above the body's top; piles, folds, flops
    "n": (int, 15),
    "L": (float, 0.3),
    "h": (float, 1.2e-3),
    "ox": (float, 0.0),
    "oy": (float, 0.0),
    "v0": (float, 1.0),
    "layers": (int, 1),
    "twist": (float, 0.0),
    "gap": (float, 2e-3),
    "fgap": (float, 1.05),
    "w": (float, 10.0),
    # its material
    "young": (float, 1e5),
    "kb": (float, 1e-5),
    "density": (float, 0.2),
    "thick": (float, 5e-4),
    # contact: barrier distance, friction (bmu: the body's, default mu), self contact on/off, an extra floor depth
    "dhat": (float, 1e-3),
    "mu": (float, 0.0),
    "bmu": (_float_or_none, None),
    "eps_v": (float, 1e-3),
    "sc": (int, 1),
    "floor": (float, 0.0),
    # the bodies: sphere radius and subdivisions, floor cells and size, incline angle, push speed and pins
    "R": (float, 0.3),
    "sub": (int, 3),
    "fm": (int, 1),
    "fsize": (_float_or_none, None),
    "ang": (float, 30.0),
    "vb": (float, 0.5),
    "pin": (_choice("corners", "none"), "corners"),
    # the solver (None: its defaults)
    "tol": (_float_or_none, None),
    "max_iters": (_int_or_none, None),
    "time_limit": (_time_limit, "auto"),
    # the intersection test: ipctk where installed (auto), or the exact crossing test
    "check": (_choice("auto", "ipctk", "exact"), "auto"),
}
"""``key: (conversion of its text, default)`` of a scene's ``key=value`` arguments."""


def parse_scene(argv: list[str]) -> dict[str, Any]:
    """The parameters of one scene from its ``key=value`` arguments (ValueError for an unknown key or value)."""
    a = {k: default for k, (_, default) in PARAMS.items()}
    for item in argv:
        k, eq, v = item.partition("=")
        if not eq:
            raise ValueError(f"{item!r} is not key=value")
        if k not in PARAMS:
            raise ValueError(f"unknown key {k!r}; keys: {' '.join(PARAMS)}")
        try:
            a[k] = PARAMS[k][0](v)
        except ValueError as e:
            raise ValueError(f"{k}={v}: {e}") from None
    return a


def read_scene_list(path: str) -> list[tuple[str, list[str]]]:
    """``[(id, [key=value, ...])]`` of a scene list: one ``ID key=value ...`` line a scene; ``#`` starts a comment."""
    scenes = []
    with open(path) as f:
        for line in f:
            words = line.split("#", 1)[0].split()
            if words:
                scenes.append((words[0], words[1:]))
    return scenes


# ------------------------------------------------------------------------------------------------ scenes

F64 = torch.float64


def rot_z(deg: float) -> torch.Tensor:
    t = math.radians(deg)
    return torch.tensor([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]], dtype=F64)


def centered_grid(nx: int, ny: int, size: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """A flat ``nx x ny`` grid of ``size`` [m] centred on the origin (float64)."""
    v, f = tb.scenes.grid(nx, ny, size, dtype=F64)
    return v - torch.tensor([size[0] / 2, size[1] / 2, 0.0], dtype=F64), f


def box_mesh(lo, hi, dt: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = torch.tensor([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)], dtype=dt)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = torch.tensor([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=torch.int64)
    return v, f


def drop_cloth(a: dict, top: float):
    """``(x0, v0, faces, pinned)`` of a drop or push: ``layers`` sheets ``gap`` apart above ``top``."""
    n = a["n"]
    flat, f1 = centered_grid(n, n, (a["L"], a["L"]))
    parts = [flat @ rot_z(a["twist"] * k).T + torch.tensor([a["ox"], a["oy"], top + a["h"] + a["gap"] * k], dtype=F64)
             for k in range(a["layers"])]
    x0 = torch.cat(parts)
    faces = torch.cat([f1 + k * len(flat) for k in range(a["layers"])])
    v0 = torch.zeros_like(x0)
    pinned = None
    if a["kind"] == "push":
        if a["pin"] == "corners":
            pinned = torch.zeros(len(x0), dtype=torch.bool)
            for k in range(a["layers"]):
                pinned[[i + k * n * n for i in (0, n - 1, n * (n - 1), n * n - 1)]] = True
    else:
        v0[:, 2] = -a["v0"]
    return x0, v0, faces, pinned


def fold_cloth(a: dict, top: float):
    """``(x0, v0, faces, None)``: an ``L x L/2`` strip folded onto itself (half-circle of radius fgap*dhat/2)."""
    L = a["L"]
    flat, faces = tb.scenes.grid(a["n"], max(3, a["n"] // 2 + 1), (L, L / 2), dtype=F64)
    r = a["fgap"] * a["dhat"] / 2
    s0 = L / 2 - math.pi * r / 2
    s = flat[:, 0]
    x0 = flat.clone()
    th = ((s - s0) / r).clamp(0, math.pi)
    arc = (s >= s0) & (s <= s0 + math.pi * r)
    x0[:, 0] = torch.where(s < s0, s, torch.where(arc, s0 + r * torch.sin(th), s0 - (s - s0 - math.pi * r)))
    x0[:, 2] = torch.where(s < s0, torch.zeros_like(s), torch.where(arc, r - r * torch.cos(th), torch.full_like(s, 2 * r)))
    x0 = (x0 - torch.tensor([L / 4, L / 4, 0.0], dtype=F64)) @ rot_z(a["twist"]).T
    x0 = x0 + torch.tensor([a["ox"], a["oy"], top + a["h"]], dtype=F64)
    v0 = torch.zeros_like(x0)
    v0[:, 2] = -a["v0"]
    return x0, v0, faces, None


def flop_cloth(a: dict, top: float):
    """``(x0, v0, faces, None)``: an ``L x L/2`` strip, its first half flat, the second standing up and swinging
    over at ``w`` rad/s."""
    L = a["L"]
    flat, faces = tb.scenes.grid(a["n"], max(3, a["n"] // 2 + 1), (L, L / 2), dtype=F64)
    s = flat[:, 0] - L / 2
    r = 0.02 * L
    x0 = flat.clone()
    th = (s / r).clamp(0, math.pi / 2)
    bend = (s > 0) & (s <= r * math.pi / 2)
    up = s > r * math.pi / 2
    x0[:, 0] = torch.where(s <= 0, s, torch.where(bend, r * torch.sin(th), torch.full_like(s, r)))
    x0[:, 2] = torch.where(s <= 0, torch.zeros_like(s), torch.where(bend, r - r * torch.cos(th), r + (s - r * math.pi / 2)))
    x0[:, 1] -= L / 4
    x0[:, 2] += top + a["h"]
    v0 = torch.zeros_like(x0)
    v0[:, 0] = torch.where(up | bend, -a["w"] * (x0[:, 2] - top - a["h"]), torch.zeros_like(s))
    v0[:, 2] = -a["v0"]
    return x0, v0, faces, None


def incline_scene(a: dict):
    """``(x0, v0, faces, bodymesh, analytic)``: a sheet ``h`` above a slope of ``ang`` degrees (float64; the
    :class:`Scene` casts both meshes to its dtype)."""
    ang = math.radians(a["ang"])
    nrm = torch.tensor([math.sin(ang), 0.0, math.cos(ang)], dtype=F64)
    down = torch.tensor([math.cos(ang), 0.0, -math.sin(ang)], dtype=F64)
    across = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    bodymesh = analytic = None
    if a["body"] == "meshfloor":
        fs = a["fsize"] or 4 * a["L"]
        g, gf = centered_grid(a["fm"] + 1, a["fm"] + 1, (fs, fs))
        bodymesh = (g[:, :1] * down + g[:, 1:2] * across, gf)
    elif a["body"] == "plane":
        analytic = ("plane", tuple(nrm.tolist()))
    else:
        raise ValueError("incline: body must be meshfloor or plane")
    flat, faces = centered_grid(a["n"], a["n"], (a["L"], a["L"]))
    x0 = flat[:, :1] * down + flat[:, 1:2] * across + a["h"] * nrm
    return x0, torch.zeros_like(x0), faces, bodymesh, analytic


def body_geometry(a: dict, dt: torch.dtype):
    """``(bodymesh, analytic)`` of a drop, fold, flop or push (``bodymesh`` in ``dt``; a push's body starts below
    the cloth)."""
    body, bodymesh, analytic = a["body"], None, None
    if body == "sphere":
        analytic = ("sphere", a["R"])
    elif body == "spheremesh":
        bodymesh = tb.scenes.icosphere(a["sub"], a["R"], dtype=dt)
    elif body == "plane":
        analytic = ("plane", (0.0, 0.0, 1.0))
    elif body == "meshfloor":
        fs = a["fsize"] or 2 * a["L"]
        v, f = tb.scenes.grid(a["fm"] + 1, a["fm"] + 1, (fs, fs), dtype=dt)
        bodymesh = (v + torch.tensor([-fs / 2, -fs / 2, 0.0], dtype=dt), f)
    elif body == "box":
        hs = (a["fsize"] or a["L"]) / 2
        bodymesh = box_mesh((-hs, -hs, -2 * hs), (hs, hs, 0.0), dt)
    if a["kind"] == "push":
        if body not in ("spheremesh", "box") or bodymesh is None:
            raise ValueError("push: body must be spheremesh or box")
        drop = 0.05 + (a["R"] if body == "spheremesh" else 0.0)
        bodymesh = (bodymesh[0] - torch.tensor([0.0, 0.0, drop], dtype=dt), bodymesh[1])
    return bodymesh, analytic


CLOTHS = {"drop": drop_cloth, "push": drop_cloth, "fold": fold_cloth, "flop": flop_cloth}


class Scene:
    """A built scene: the model, its initial state, the body (``body``: the MeshCollider or None, ``analytic``:
    ``("sphere", R)``, ``("plane", normal)`` or None) and the meshes the checks test."""

    def __init__(self, a: dict):
        dt = torch.float32 if a["dtype"] == "f32" else F64
        pinned = None
        if a["kind"] == "incline":
            x0, v0, faces, bodymesh, analytic = incline_scene(a)
        else:
            top = a["R"] if a["body"] in ("sphere", "spheremesh") else 0.0
            x0, v0, faces, pinned = CLOTHS[a["kind"]](a, top)
            bodymesh, analytic = body_geometry(a, dt)
        x0, v0 = x0.to(dt), v0.to(dt)
        dhat, bmu = a["dhat"], a["mu"] if a["bmu"] is None else a["bmu"]
        colliders: list = []
        if analytic is not None and analytic[0] == "sphere":
            colliders.append(tb.Sphere((0.0, 0.0, 0.0), analytic[1], margin=dhat, friction=bmu, eps_v=a["eps_v"]))
        elif analytic is not None:
            colliders.append(tb.Plane((0.0, 0.0, 0.0), analytic[1], margin=dhat, friction=bmu, eps_v=a["eps_v"]))
        self.body = None
        if bodymesh is not None:
            self.body = tb.MeshCollider(bodymesh[0].to(dt), bodymesh[1], dhat=dhat, friction=bmu, eps_v=a["eps_v"])
            colliders.append(self.body)
        if a["floor"]:  # an extra analytic floor, `floor` below z = 0
            colliders.append(tb.Plane((0.0, 0.0, -a["floor"]), (0.0, 0.0, 1.0), margin=dhat, friction=bmu))
        terms = [tb.SelfContact(dhat=dhat, friction=a["mu"], eps_v=a["eps_v"])] if a["sc"] else []
        rest = x0.clone()
        self.model = tb.ClothModel(
            faces, rest, density=a["density"], terms=terms, colliders=colliders, pinned=pinned, gravity=(0.0, 0.0, -9.81),
            membrane=tb.MembraneEnergy(faces, rest, young=a["young"], poisson=0.3, thickness=a["thick"]),
            bending=tb.BendingEnergy(faces, rest, stiffness=a["kb"]))
        self.state = tb.ClothState(x0, v0)
        self.faces, self.analytic, self.floor = faces, analytic, a["floor"]
        self.body_faces = bodymesh[1].long() if bodymesh is not None else None


# ------------------------------------------------------------------------------------------------ exact checks


def have_ipctk() -> bool:
    """Whether ipctk (the ``test`` extra; x86-64 Linux wheels) can be imported."""
    try:
        import ipctk  # noqa: F401
    except ImportError:
        return False
    return True


def edges_of(faces: torch.Tensor) -> torch.Tensor:
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).sort(1).values
    return e.unique(dim=0)


def segment_crosses_triangle(p0, p1, t0, t1, t2) -> torch.Tensor:
    """Moller-Trumbore test ``(N,)``: segment p0->p1 crosses triangle (t0, t1, t2) (segments within 1e-10 rad of
    the triangle's plane are not tested: coplanar overlaps do not occur between non-adjacent primitives here).
    A copy of ``tests/test_self_contact.py``'s."""
    e1, e2, d = t1 - t0, t2 - t0, p1 - p0
    h = torch.linalg.cross(d, e2)
    a = (e1 * h).sum(-1)
    # a segment (nearly) in the triangle's plane: u, v, t are round-off there; such a pair is not a crossing
    ok = a.abs() > 1e-10 * d.norm(dim=-1) * e1.norm(dim=-1) * e2.norm(dim=-1)
    f = 1 / torch.where(ok, a, torch.ones_like(a))
    s = p0 - t0
    u = f * (s * h).sum(-1)
    q = torch.linalg.cross(s, e1)
    v = f * (d * q).sum(-1)
    t = f * (e2 * q).sum(-1)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def crossing(x: torch.Tensor, faces: torch.Tensor, cloth: int, chunk: int = 1 << 21) -> bool:
    """Whether an edge crosses a triangle that contains neither of its vertices, among the pairs that involve one
    of the first ``cloth`` vertices (the cloth's; the rest are the body's): ``tests/test_self_contact.py``'s
    brute-force ``intersects``, in chunks of about ``chunk`` pairs, ``x`` in float64."""
    edges = edges_of(faces)
    E, F = edges.shape[0], faces.shape[0]
    step = max(1, chunk // F)
    for s in range(0, E, step):
        e = edges[s:s + step]
        ei = e[:, None, :].expand(len(e), F, 2).reshape(-1, 2)
        fi = faces[None].expand(len(e), F, 3).reshape(-1, 3)
        keep = (ei[:, :, None] != fi[:, None, :]).all(-1).all(-1) & ((ei[:, 0] < cloth) | (fi[:, 0] < cloth))
        ei, fi = ei[keep], fi[keep]
        if bool(segment_crosses_triangle(x[ei[:, 0]], x[ei[:, 1]], x[fi[:, 0]], x[fi[:, 1]], x[fi[:, 2]]).any()):
            return True
    return False


class IntersectionCheck:
    """The exact tests of a state of a :class:`Scene` (float64): the cloth and the body mesh together (ipctk, or
    :func:`crossing`), vertices outside an analytic sphere or plane and above the extra floor.  ``chord_depth``: the
    deepest an edge's chord has dipped into an analytic sphere (information only: the analytic colliders hold
    vertices, not edges)."""

    def __init__(self, scene: Scene, method: str):
        self.scene, self.method, self.chord_depth = scene, method, 0.0

    def __call__(self, x: torch.Tensor) -> str:
        """A description of what intersects, or ``""``."""
        sc = self.scene
        x = x.detach().double()
        msgs = []
        allv, allf = x, sc.faces
        if sc.body is not None and sc.body_faces is not None:
            allv = torch.cat([x, sc.body.vertices.detach().double()])
            allf = torch.cat([sc.faces, sc.body_faces + x.shape[0]])
        if self.method == "ipctk":
            import ipctk

            v, f = allv.numpy(), allf.numpy().astype(np.int32)
            if ipctk.has_intersections(ipctk.CollisionMesh(v, ipctk.edges(f), f), v):
                msgs.append("mesh intersection (ipctk)")
        elif crossing(allv, allf, x.shape[0]):
            msgs.append("mesh intersection (edge crosses triangle)")
        if sc.analytic is not None and sc.analytic[0] == "sphere":
            R = sc.analytic[1]
            vd = float(x.norm(dim=1).min())
            if vd <= R:
                msgs.append(f"vertex inside analytic sphere by {R - vd:.3g}")
            e = edges_of(sc.faces)
            p, d = x[e[:, 0]], x[e[:, 1]] - x[e[:, 0]]
            t = (-(p * d).sum(1) / (d * d).sum(1).clamp_min(1e-300)).clamp(0, 1)
            self.chord_depth = max(self.chord_depth, R - float((p + t[:, None] * d).norm(dim=1).min()))
        elif sc.analytic is not None:
            s = float((x @ torch.tensor(sc.analytic[1], dtype=F64)).min())
            if s <= 0:
                msgs.append(f"vertex below analytic plane by {-s:.3g}")
        if sc.floor and float(x[:, 2].min()) <= -sc.floor:
            msgs.append("vertex below floor plane")
        return "; ".join(msgs)


# ------------------------------------------------------------------------------------------------ one scene


def step_failure(info, x: torch.Tensor, check: IntersectionCheck) -> str:
    """Why a step failed (``""``: it passed)."""
    why = [] if info.converged else ["not converged"]
    inter = check(x)
    if inter:
        why.append(inter)
    if not info.min_distance > 0:
        why.append(f"min_distance {info.min_distance}")
    if not bool(torch.isfinite(x).all()):
        why.append("non-finite x")
    return "; ".join(why)


def failure_record(step: int, why: str, info) -> dict:
    rh = [float(r) for r in info.residual_history]
    return dict(step=step, why=why, stop_reason=info.stop_reason, message=info.message, phase=info.phase,
                solves=info.solves, substeps=info.substeps, iterations=info.iterations, residual=info.residual,
                tolerance=info.tolerance, seconds=info.seconds, residual_tail=rh[-12:],
                line_search_failures=info.line_search_failures, regularized_steps=info.regularized_steps,
                adaptations=info.adaptations)


def run_scene(a: dict, args: str = "", log: Callable[[str], None] | None = print) -> dict:
    """Simulates the scene of parameters ``a`` (:func:`parse_scene`) until its first failed step; returns its
    summary (the module docstring).  ``log``: a line per step and the failure's report (None: silent)."""
    log = log or (lambda _: None)
    scene = Scene(a)
    method = a["check"] if a["check"] != "auto" else ("ipctk" if have_ipctk() else "exact")
    check = IntersectionCheck(scene, method)
    opts = {k: a[k] for k in ("tol", "max_iters") if a[k] is not None}
    if a["time_limit"] != "auto":
        opts["time_limit"] = a["time_limit"]
    state, body = scene.state, scene.body
    base = body.vertices.detach().clone() if body is not None else None
    rec: dict[str, Any] = dict(args=args, tag=a["tag"], V=int(state.x.shape[0]), F=int(scene.faces.shape[0]),
                               steps_total=a["steps"], passed=0, max_iters=0, total_s=0.0, min_dist=math.inf,
                               fail=None, check=method)
    bad = check(state.x)
    if bad:
        rec["fail"] = dict(step=-1, why="initial state intersects: " + bad)
    t_all = time.perf_counter()
    for i in range(0 if bad else a["steps"]):
        if a["kind"] == "push" and body is not None and base is not None:
            body.vertices = base + torch.tensor([0.0, 0.0, a["vb"] * a["dt"] * (i + 1)], dtype=base.dtype)
        t0 = time.perf_counter()
        state, info = tb.implicit_euler_step(scene.model, state, a["dt"], **opts)
        wall = time.perf_counter() - t0
        why = step_failure(info, state.x, check)
        log(f"step {i:3d} conv={int(info.converged)} it={info.iterations:3d} solves={info.solves} "
            f"sub={info.substeps} phase={info.phase} t={wall:6.2f}s dmin={info.min_distance:.3e} "
            f"nc={info.contact_count} adapt={info.adaptations} stop={info.stop_reason}" + (f"  <-- {why}" if why else ""))
        rec["max_iters"] = max(rec["max_iters"], info.iterations)
        rec["min_dist"] = min(rec["min_dist"], info.min_distance)
        if why:
            rec["fail"] = f = failure_record(i, why, info)
            log(f"FAIL at step {i}: {why}\n  stop_reason: {f['stop_reason']} | phase: {f['phase']} | solves: "
                f"{f['solves']} | substeps: {f['substeps']} | iterations: {f['iterations']}\n  message: {f['message']}\n"
                f"  residual {f['residual']:.3e} tolerance {f['tolerance']:.3e} line_search_failures "
                f"{f['line_search_failures']}\n  residual history (last 12): "
                + " ".join(f"{r:.2e}" for r in f["residual_tail"]))
            break
        rec["passed"] += 1
    rec["total_s"] = time.perf_counter() - t_all
    if scene.analytic is not None and scene.analytic[0] == "sphere":
        rec["chord_depth"] = check.chord_depth
    return rec


def scene_main(argv: list[str]) -> int:
    """One scene from ``key=value`` arguments: a line per step, then ``SUMMARY {json}``; 0 if every step passed."""
    try:
        a = parse_scene(argv)
    except ValueError as e:
        print(f"scene_campaign.py: {e}", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    logging.getLogger("torchbend.sim").setLevel(logging.WARNING)
    if a["check"] == "auto" and not have_ipctk():
        print("ipctk is not installed (the test extra): the exact edge-triangle crossing test checks intersections")
    rec = run_scene(a, " ".join(argv), log=lambda s: print(s, flush=True))
    print("SUMMARY " + json.dumps(rec), flush=True)
    return 0 if rec["fail"] is None else 1


# ------------------------------------------------------------------------------------------------ the runner


def _common():
    """benchmarks/common.py by its path (a plain ``import common`` may find another directory's module of that name
    when this script is loaded into a process that has one, as the tests do)."""
    spec = importlib.util.spec_from_file_location("_torchbend_bench_common", os.path.join(HERE, "common.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def git_commit() -> str:
    """The short commit of the repository, ``+ uncommitted changes`` where the tree differs from it."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                               text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + (" + uncommitted changes" if dirty else "")


def run_child(scene_id: str, args: list[str], timeout: float) -> dict:
    """Runs one scene in a child process (this file, ``OMP_NUM_THREADS=1``); its summary with ``id`` and ``wall_s``
    added (a timeout or a crash: ``fail`` says so)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    cmd = [sys.executable, os.path.abspath(__file__), *args, f"tag={scene_id}"]
    t0 = time.perf_counter()
    try:
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return dict(id=scene_id, args=" ".join(args), wall_s=time.perf_counter() - t0,
                    fail=dict(step=None, why=f"timeout after {timeout:g} s"))
    wall = time.perf_counter() - t0
    summary = [line for line in out.stdout.splitlines() if line.startswith("SUMMARY ")]
    if summary:
        rec = json.loads(summary[-1][len("SUMMARY "):])
    else:
        tail = (out.stderr.strip().splitlines() or ["no output"])[-1]
        rec = dict(args=" ".join(args), fail=dict(step=None, why=f"exit status {out.returncode}: {tail}"))
    return dict(id=scene_id, wall_s=wall, **rec)


ROW = "{:<5} {:>7} {:>6} {:>8} {:>8} {:>10}  {}"


def table_row(rec: dict) -> str:
    fail = rec.get("fail")
    result = "ok" if fail is None else (f"step {fail['step']}: " if fail.get("step") is not None else "") + fail["why"]
    steps = f"{rec['passed']}/{rec['steps_total']}" if "passed" in rec else "-"
    iters = str(rec["max_iters"]) if "max_iters" in rec else "-"
    step_s = f"{rec['total_s']:.1f}" if "total_s" in rec else "-"
    dmin = rec.get("min_dist")
    dist = f"{dmin:.2e}" if dmin is not None and math.isfinite(dmin) else "-"
    return ROW.format(rec["id"], steps, iters, step_s, f"{rec['wall_s']:.1f}", dist, result)


def runner_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n", 1)[0],
                                epilog="One scene: scene_campaign.py key=value ... (keys: " + " ".join(PARAMS) + ")")
    p.add_argument("--all", action="store_true", required=True, help="run the scenes of the list, one at a time")
    p.add_argument("--list", default=SCENE_LIST, help="the scene list (default: benchmarks/scene_campaign.txt)")
    p.add_argument("--only", nargs="+", metavar="ID", help="run only these scenes of the list")
    p.add_argument("--timeout", type=float, default=180.0, help="seconds a scene may run (default 180)")
    p.add_argument("--out", help="write the scenes' summaries here, a JSON line each (the file is replaced)")
    o = p.parse_args(argv)
    scenes = read_scene_list(o.list)
    for sid, args in scenes:  # a wrong line fails now, not after the scenes before it
        try:
            parse_scene(args)
        except ValueError as e:
            p.error(f"{o.list}: scene {sid}: {e}")
    if o.only:
        unknown = sorted(set(o.only) - {sid for sid, _ in scenes})
        if unknown:
            p.error(f"not in {o.list}: {' '.join(unknown)}")
        scenes = [s for s in scenes if s[0] in o.only]
    common = _common()
    print(f"# {common.cpu_model()} | {os.cpu_count()} cores | torch {torch.__version__} | torchbend commit {git_commit()}")
    print(f"# {os.path.relpath(o.list, os.getcwd())}: {len(scenes)} scenes, one at a time, OMP_NUM_THREADS=1, "
          f"timeout {o.timeout:g} s; intersections: "
          + ("ipctk" if have_ipctk() else "ipctk is not installed (the test extra): the exact edge-triangle crossing test"))
    print(ROW.format("id", "steps", "max it", "step s", "wall s", "min dist", "result"), flush=True)
    records, passed = [], 0
    for sid, args in scenes:
        rec = run_child(sid, args, o.timeout)
        records.append(rec)
        passed += rec.get("fail", True) is None
        print(table_row(rec), flush=True)
    if o.out:
        with open(o.out, "w") as f:
            f.writelines(json.dumps(r) + "\n" for r in records)
    print(f"{passed} of {len(scenes)} scenes passed")
    return 0 if passed == len(scenes) else 1


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or any(a.startswith("-") for a in argv):
        return runner_main(argv)
    return scene_main(argv)


if __name__ == "__main__":
    sys.exit(main())
