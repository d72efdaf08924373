"""Command-line conventions shared by ``python -m torchbend.scenes`` and the training scripts.

Every script takes the same options (:func:`add_common_args`): ``--config PATH`` (YAML),
``--set KEY=VALUE`` (override a config key, repeatable: ``--set solver.tol=1e-8``), ``--seed``,
``--device`` (an unavailable device exits with one line, no traceback), ``--out DIR``, ``--resume``
(continue from ``<out>/checkpoint.pt``), ``--log-level`` and ``--no-progress``.  Messages go through
:mod:`logging` (:func:`setup_logging`: loggers ``torchbend.*`` and ``train.*``, INFO by default, to
stderr); progress bars are tqdm's.  Checkpoints (:func:`save_checkpoint`, :func:`load_checkpoint`)
hold only tensors and plain Python values and load with ``torch.load(..., weights_only=True)``.
"""
from __future__ import annotations

import argparse
import logging
import os
import random
import sys
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
import torch

from .config import ConfigError

__all__ = ["add_common_args", "parse_args", "setup_logging", "resolve_device", "seed_everything", "save_checkpoint",
           "load_checkpoint", "changed_keys", "run_main", "LOG_LEVELS"]

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


def add_common_args(parser: argparse.ArgumentParser, *, config: str | None = None, out: str | None = None,
                    device: str = "cpu", config_positional: bool = False) -> argparse.ArgumentParser:
    """Add the shared options to ``parser`` (defaults: ``config``, ``out``, ``device``).

    ``config_positional`` also accepts the config path as the first positional argument
    (``python -m torchbend.scenes configs/beams.yaml``), stored in ``config`` like ``--config``."""
    g = parser.add_argument_group("common options (every torchbend script)")
    if config_positional:
        parser.add_argument("config_path", nargs="?", metavar="CONFIG", help="YAML config (same as --config)")
    g.add_argument("--config", default=config, metavar="PATH",
                   help="YAML config" + (f" (default {config})" if config else ""))
    g.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key, value read as YAML, e.g. --set solver.tol=1e-8 (repeatable)")
    g.add_argument("--seed", type=int, help="random seed (overrides the config's)")
    g.add_argument("--device", default=device, help=f"torch device: cpu, cuda, cuda:1, mps, ... (default {device})")
    g.add_argument("--out", default=out, metavar="DIR", help="output directory" + (f" (default {out})" if out else ""))
    g.add_argument("--resume", action="store_true", help="continue from <out>/checkpoint.pt")
    g.add_argument("--log-level", default="INFO", type=str.upper, choices=LOG_LEVELS, help="logging level (default INFO)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def parse_args(parser: argparse.ArgumentParser, argv=None) -> argparse.Namespace:
    """``parser.parse_args(argv)`` with the config path of a positional ``CONFIG`` merged into ``config``
    (a missing config is a usage error), logging set up at ``--log-level``."""
    a = parser.parse_args(argv)
    positional = getattr(a, "config_path", None)
    if positional is not None:
        if a.config is not None and a.config != positional:
            parser.error(f"two configs given: {positional} and --config {a.config}")
        a.config = positional
    if a.config is None:
        parser.error("a config is required: CONFIG or --config PATH")
    setup_logging(a.log_level)
    return a


def setup_logging(level: str | int = "INFO", names: Iterable[str] = ("torchbend", "train")) -> None:
    """Messages of the loggers ``names`` (and their children) at ``level`` and above go to stderr
    (a handler is added to the root logger only if it has none: an application's setup is kept)."""
    root = logging.getLogger()
    if not root.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        root.addHandler(handler)
    for name in names:
        logging.getLogger(name).setLevel(level)


def _prog() -> str:
    return os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "torchbend"


def resolve_device(name: str, *, prog: str | None = None, supported: Iterable[str] | None = None,
                   why: str = "") -> torch.device:
    """``torch.device(name)`` when it exists and is usable here; else ``SystemExit`` with one line
    (``prog: error: --device cuda: ...``).  ``supported`` restricts the device types (``why`` says why)."""
    prog = prog or _prog()

    def fail(msg: str):
        raise SystemExit(f"{prog}: error: --device {name}: {msg}")

    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError, TypeError):
        fail("not a torch device (expected cpu, cuda, cuda:N, mps, ...)")
    supported = tuple(supported) if supported is not None else None
    if supported is not None and dev.type not in supported:
        fail(f"this script runs on {' or '.join(supported)} only{' (' + why + ')' if why else ''}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            built = "this torch build has no CUDA support" if torch.version.cuda is None else "no CUDA GPU is visible"
            fail(f"CUDA is not available ({built}); use --device cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            fail(f"only {torch.cuda.device_count()} CUDA device(s) visible")
    elif dev.type == "mps":
        if not torch.backends.mps.is_available():
            fail("MPS is not available on this machine; use --device cpu")
    elif dev.type != "cpu":
        try:
            torch.empty(1, device=dev)
        except Exception as e:  # any backend's "not available / not compiled" error
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            fail(f"not available ({first})")
    return dev


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's and torch's (every device's) random generators."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def save_checkpoint(path: str, **state: Any) -> None:
    """Write ``state`` (tensors, ``state_dict()`` s and plain Python values only) to ``path`` atomically."""
    tmp = path + ".tmp"
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str, map_location=None) -> dict:
    """A checkpoint of :func:`save_checkpoint`, read with ``weights_only=True`` (no code runs);
    :class:`ConfigError` naming the path if it is missing or holds other objects."""
    if not os.path.isfile(path):
        raise ConfigError(f"--resume/--init: no checkpoint at {path}")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # UnpicklingError of a checkpoint with arbitrary objects, a truncated file, ...
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(f"checkpoint {path} cannot be read with weights_only=True: {first}") from None
    if not isinstance(state, dict):
        raise ConfigError(f"checkpoint {path} holds a {type(state).__name__}, expected a dict")
    return state


def changed_keys(old: Any, new: Any, ignore: Iterable[str] = (), prefix: str = "") -> list[str]:
    """Dotted paths at which two configs (dicts of plain values) differ, except those in ``ignore``
    (e.g. the step count a resumed run extends)."""
    ignore = tuple(ignore)
    if prefix in ignore:
        return []
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new), key=str):
            out += changed_keys(old.get(k), new.get(k), ignore, f"{prefix}.{k}" if prefix else str(k))
        return out
    return [] if old == new else [prefix or "(root)"]


def run_main(main: Callable[[], Any], prog: str | None = None) -> None:
    """Run ``main()`` as a command: a config error (:class:`ConfigError`) exits with its one-line
    message instead of a traceback."""
    try:
        main()
    except ConfigError as e:
        raise SystemExit(f"{prog or _prog()}: error: {e}") from None
