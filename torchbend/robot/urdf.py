"""URDF robots through pytorch-kinematics: loading, validation and float64 link transforms (see
:mod:`torchbend.robot`)."""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET

import torch
from torch import Tensor

from .._extras import require

__all__ = ["Robot", "asset_path"]

_ASSETS = os.path.join(os.path.dirname(__file__), "assets")
_JOINT_TYPES = {"revolute", "continuous", "prismatic", "fixed"}


def asset_path(name: str) -> str:
    """Path of a file shipped in ``torchbend/assets`` (``ValueError`` listing them if absent)."""
    path = os.path.join(_ASSETS, name)
    if not os.path.isfile(path):
        raise ValueError(f"no asset named {name!r}; shipped assets: {sorted(os.listdir(_ASSETS))}")
    return path


def _read_urdf(urdf: str) -> tuple[str, str]:
    """``(xml text, where)`` from an XML string, a file path or an asset name."""
    if not isinstance(urdf, str):
        raise ValueError(f"urdf must be a path, an asset name or an XML string, got {type(urdf).__name__}")
    if urdf.lstrip().startswith("<"):
        return urdf, "URDF string"
    path = urdf if os.path.isfile(urdf) else os.path.join(_ASSETS, urdf)
    if not os.path.isfile(path):
        raise ValueError(f"URDF file not found: {urdf!r} (neither a file nor one of the shipped assets "
                         f"{sorted(os.listdir(_ASSETS))})")
    with open(path) as f:
        return f.read(), path


def _names(elements, kind: str, where: str) -> list:
    """The ``name`` attributes of URDF elements (``ValueError`` for a missing or repeated one)."""
    names: list = []
    for i, el in enumerate(elements):
        name = el.get("name")
        if not name:
            raise ValueError(f"malformed URDF ({where}): <{kind}> number {i} has no name")
        if name in names:
            raise ValueError(f"malformed URDF ({where}): {kind} {name!r} is declared twice")
        names.append(name)
    return names


def _check_joint(joint, name: str, links: list, where: str) -> str:
    """Checks of one ``<joint>``: type, declared parent/child links, 3-number origin and axis; returns the child link."""
    jtype = joint.get("type")
    if jtype not in _JOINT_TYPES:
        raise ValueError(f"malformed URDF ({where}): joint {name!r} has type {jtype!r}; supported: "
                         f"{sorted(_JOINT_TYPES)}")
    named = {}
    for tag in ("parent", "child"):
        el = joint.find(tag)
        link = None if el is None else el.get("link")
        if link is None:
            raise ValueError(f"malformed URDF ({where}): joint {name!r} has no <{tag} link=...>")
        if link not in links:
            raise ValueError(f"malformed URDF ({where}): joint {name!r} names {tag} link {link!r}, "
                             f"which is not declared")
        named[tag] = link
    for tag, attrs in (("origin", ("xyz", "rpy")), ("axis", ("xyz",))):
        el = joint.find(tag)
        for attr in attrs:
            value = None if el is None else el.get(attr)
            if value is not None and not _three_numbers(value):
                raise ValueError(f"malformed URDF ({where}): joint {name!r} <{tag} {attr}={value!r}> "
                                 f"must be three numbers")
    return named["child"]


def _three_numbers(value: str) -> bool:
    try:
        return len([float(v) for v in value.split()]) == 3
    except ValueError:
        return False


def _validate_urdf(text: str, where: str) -> None:
    """Structural checks with messages naming the bad element (pytorch-kinematics fails obscurely)."""
    try:
        root = ET.fromstring(text.encode() if text.lstrip().startswith("<?xml") else text)
    except ET.ParseError as e:
        raise ValueError(f"malformed URDF ({where}): XML syntax error: {e}") from None
    if root.tag != "robot":
        raise ValueError(f"malformed URDF ({where}): the root element must be <robot>, got <{root.tag}>")
    links = _names(root.findall("link"), "link", where)
    joints = root.findall("joint")
    if not joints:
        raise ValueError(f"malformed URDF ({where}): no <joint> elements (a robot needs at least one)")
    children: dict[str, str] = {}
    for name, joint in zip(_names(joints, "joint", where), joints):
        child = _check_joint(joint, name, links, where)
        if child in children:
            raise ValueError(f"malformed URDF ({where}): link {child!r} is the child of two joints "
                             f"({children[child]!r} and {name!r})")
        children[child] = name
    roots = [link for link in links if link not in children]
    if len(roots) != 1:
        raise ValueError(f"malformed URDF ({where}): expected one root link (a tree), found {roots}")


def _float64_chain(text: str, device):
    """pytorch-kinematics chain with float64 joint offsets and axes (its URDF reader rounds to float32)."""
    pk = require("pytorch_kinematics", "robot scenes (URDF kinematics)")
    import pytorch_kinematics.transforms as tf
    from pytorch_kinematics.urdf_parser_py.urdf import URDF

    chain = pk.build_chain_from_urdf(text)
    model = URDF.from_xml_string(text)
    joints = {j.name: j for j in model.joints}
    links = {link.name: link for link in model.links}

    def transform(origin):
        if origin is None:
            return tf.Transform3d(dtype=torch.float64)
        rpy = torch.tensor(origin.rpy, dtype=torch.float64)
        return tf.Transform3d(rot=tf.quaternion_from_euler(rpy, "sxyz"), pos=list(origin.xyz), dtype=torch.float64)

    def visit(frame):
        j = joints.get(frame.joint.name)
        if j is not None:
            frame.joint.offset = transform(j.origin)
            axis = torch.tensor(j.axis if j.axis is not None else (0.0, 0.0, 1.0), dtype=torch.float64)
            frame.joint.axis = axis / axis.norm()
        link = links.get(frame.link.name)
        frame.link.offset = transform(link.origin if link is not None else None)
        for child in frame.children:
            visit(child)

    visit(chain._root)
    return pk.Chain(chain._root, dtype=torch.float64, device=device)


class Robot:
    """A URDF robot with batched forward kinematics (pytorch-kinematics), float64 by default.

    Args:
        urdf: a URDF file path, an XML string, or an asset name (``"folding_arm.urdf"``).
        dtype, device: of the transforms returned (joint vectors are cast to them).
    """

    def __init__(self, urdf: str = "folding_arm.urdf", *, dtype=torch.float64, device=None):
        text, where = _read_urdf(urdf)
        _validate_urdf(text, where)
        try:
            chain = _float64_chain(text, device or "cpu")
        except ImportError:
            raise  # the robot extra is missing: the error says so
        except Exception as e:  # the parser's errors are not ValueErrors
            raise ValueError(f"malformed URDF ({where}): {type(e).__name__}: {e}") from None
        self.chain = chain.to(dtype=dtype, device=device or "cpu")
        self.source = where
        self.name = ET.fromstring(text.encode() if text.lstrip().startswith("<?xml") else text).get("name", "robot")
        self.joint_names: list[str] = list(self.chain.get_joint_parameter_names())
        self.link_names: list[str] = list(self.chain.get_frame_names(exclude_fixed=False))
        self.dtype = dtype

    @property
    def joint_count(self) -> int:
        return len(self.joint_names)

    def __repr__(self) -> str:
        return f"Robot({self.name!r}, joints={self.joint_names}, links={self.link_names})"

    def joint_limits(self) -> tuple[Tensor, Tensor]:
        """``(lower, upper)`` ``(J,)`` from the URDF."""
        low, high = self.chain.get_joint_limits()
        return torch.as_tensor(low, dtype=self.dtype), torch.as_tensor(high, dtype=self.dtype)

    def check_joints(self, q, name: str = "q") -> Tensor:
        """``q`` as a floating tensor ``(..., J)`` (``ValueError`` naming a wrong length or bad values)."""
        q = torch.as_tensor(q)
        if not q.is_floating_point():
            q = q.to(self.dtype)
        if q.ndim == 0 or q.shape[-1] != self.joint_count:
            got = "a scalar" if q.ndim == 0 else f"length {q.shape[-1]}"
            raise ValueError(f"joint vector {name} has {got} but robot {self.name!r} has {self.joint_count} "
                             f"movable joints {self.joint_names}")
        if not bool(torch.isfinite(q).all()):
            raise ValueError(f"joint vector {name} holds non-finite values")
        return q

    def check_link(self, link: str, where: str = "link") -> str:
        if link not in self.link_names:
            raise ValueError(f"{where}: robot {self.name!r} has no link {link!r}; links: {self.link_names}")
        return link

    def link_transforms(self, q, links) -> Tensor:
        """World transforms of ``links`` (a list of names) for joints ``q (..., J)``: ``(..., L, 4, 4)``.

        Differentiable in ``q`` (first order; pytorch-kinematics' analytic Jacobian)."""
        q = self.check_joints(q)
        idx = torch.tensor([self.chain.frame_to_idx[self.check_link(n)] for n in links], dtype=torch.long)
        batch = q.shape[:-1]
        qb = q.reshape(-1, self.joint_count).to(dtype=self.chain.dtype, device=self.chain.device)
        T = self.chain.forward_kinematics_tensor(qb)  # (frames, B, 4, 4)
        T = T[idx.to(T.device)].transpose(0, 1)  # (B, L, 4, 4)
        return T.reshape(*batch, len(links), 4, 4).to(dtype=q.dtype)
