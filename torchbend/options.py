"""Closed sets of options (enums) and the one helper that parses them.

Every option the library takes as a string (``model="tan"``, ``projection="clamp"``,
``assembly="triangle"``, ``backend="auto"``, ...) is a ``str`` enum deriving from :class:`Option`, so
``Projection("clamp") == "clamp"`` and an unknown value is a ``ValueError`` that lists the allowed
ones.  :class:`Projection` is shared by every energy and the solver; each says which members it
supports (``supported=`` of :meth:`Option.parse`).
"""
from __future__ import annotations

import enum
from collections.abc import Iterable
from typing import TypeVar

__all__ = ["Option", "Projection", "Assembly", "Backend", "parse_option", "projection_argument"]

E = TypeVar("E", bound="Option")


class Option(str, enum.Enum):
    """Base of the library's option enums: ``parse`` turns a string (or member) into a member."""

    @classmethod
    def aliases(cls) -> dict:
        """Extra spellings accepted by :meth:`parse` (e.g. ``None`` for ``Projection.NONE``)."""
        return {}

    @classmethod
    def parse(cls: type[E], value, *, what: str | None = None, supported: Iterable[E] | None = None) -> E:
        """The member named by ``value``; ``ValueError`` naming ``what`` and the allowed values otherwise."""
        return parse_option(cls, value, what=what, supported=supported)


def parse_option(cls: type[E], value, *, what: str | None = None, supported: Iterable[E] | None = None) -> E:
    """Parse ``value`` into a member of the option enum ``cls`` (see :class:`Option`).

    ``supported`` restricts the accepted members (a ``ValueError`` names the ones that are)."""
    if supported is None and type(value) is cls:  # a member already (the hot paths pass their stored members)
        return value
    what = what or getattr(cls, "__label__", cls.__name__)
    allowed = list(cls) if supported is None else list(supported)
    aliases = cls.aliases()
    try:
        member = aliases[value] if _hashable(value) and value in aliases else cls(value)
    except ValueError:
        member = None
    if member is None or member not in allowed:
        names = ", ".join(repr(m.value) for m in allowed)
        raise ValueError(f"unknown {what} {value!r}; {what} must be one of {names}")
    return member


def _hashable(value) -> bool:
    try:
        hash(value)
    except TypeError:
        return False
    return True


class Projection(Option):
    """How a Hessian is made positive semi-definite.

    ``none`` (also ``None`` and ``"exact"``) keeps the exact, possibly indefinite Hessian; ``clamp``
    / ``abs`` replace eigenvalues by ``max(l, 0)`` / ``|l|`` (bending: per 12x12 hinge block;
    membrane: the closed-form eigenvalues in ``F``); ``gauss_newton`` keeps only the rank-one
    ``max(psi'', 0) g g^T`` part of each hinge; ``reduced`` clamps the eigenvalues of a hinge block in
    its 9 translation-free coordinates.  Colliders drop their (concave) curvature term for every
    member but ``none``.
    """

    __label__ = "Hessian projection"

    NONE = "none"
    CLAMP = "clamp"
    ABS = "abs"
    GAUSS_NEWTON = "gauss_newton"
    REDUCED = "reduced"

    @classmethod
    def aliases(cls) -> dict:
        return {None: cls.NONE, "exact": cls.NONE}

    def restricted(self, supported: Iterable[Projection]) -> Projection:
        """This projection if ``supported``, else the PSD projection ``clamp`` (used by the solver to
        give each energy the nearest projection it supports)."""
        return self if self in set(supported) else Projection.CLAMP


def projection_argument(projection, project, where: str, *, old: str = "project") -> Projection:
    """The projection of a call that takes ``projection=`` and, for one release, the deprecated alias
    ``project=`` (or ``hessian=`` for the solvers: ``old``): the alias warns (``DeprecationWarning``), and
    both given with different values is a ``ValueError`` naming ``where``."""
    if project is not None:
        import warnings

        warnings.warn(f"{where}: {old}= is deprecated, use projection=", DeprecationWarning, stacklevel=3)
        if projection is not None and Projection.parse(projection) is not Projection.parse(project):
            raise ValueError(f"{where}: projection={projection!r} and {old}={project!r} disagree; give projection= only")
        projection = project
    return Projection.parse(projection)


class Assembly(Option):
    """How the bending Hessian is assembled: scattering 12x12 hinge blocks or 9x9 triangle blocks
    (paper eq. 7); both give the same matrix."""

    __label__ = "assembly"

    HINGE = "hinge"
    TRIANGLE = "triangle"


class Backend(Option):
    """Which code evaluates an operation: ``auto`` (compiled where it applies, else eager),
    ``eager`` (PyTorch operations) or ``native`` (the compiled kernels; an error where they cannot
    run).  The choice is made by :func:`torchbend.backends.select_backend`."""

    __label__ = "backend"

    AUTO = "auto"
    EAGER = "eager"
    NATIVE = "native"
