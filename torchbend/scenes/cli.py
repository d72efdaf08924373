"""Command-line conventions shared by ``python -m torchbend.scenes`` and the training scripts.

Every script takes the same options (:func:`add_common_args`): ``--config PATH`` (YAML),
``--set KEY=VALUE`` (override a config key, repeatable: ``--set solver.tol=1e-8``), ``--seed``,
``--device`` (an unavailable device exits with one line, no traceback), ``--out DIR``, ``--resume``
(continue from ``<out>/checkpoint.pt``), ``--log-level`` and ``--no-progress``.  Messages go through
:mod:`logging` (:func:`setup_logging`: loggers ``torchbend.*`` and ``train.*``, INFO by default, to
stderr); progress bars are tqdm's.  Checkpoints (:func:`save_checkpoint`, :func:`load_checkpoint`)
hold only tensors and plain Python values and load with ``torch.load(..., weights_only=True)``;
:func:`resume_checkpoint` and :func:`restore` check that one fits the run it continues.

A user's mistake (a bad option or config value, a missing or unreadable file, a checkpoint of
another run) ends the command with one line on stderr, ``prog: error: ...``, and a non-zero exit
status, never a traceback: usage errors exit with status 2 (:func:`add_common_args` makes the
parser's errors one line), the rest with status 1 (:func:`run_main`).  Messages quote at most about
200 characters of an offending value (:func:`torchbend.scenes.config.one_line`).
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import random
import re
import sys
import traceback
import zipfile
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np
import torch

from .schema import SEED_LIMIT
from .wording import ConfigError, one_line, short_repr

__all__ = ["add_common_args", "parse_args", "setup_logging", "resolve_device", "seed_everything", "save_checkpoint",
           "load_checkpoint", "resume_checkpoint", "restore", "changed_keys", "run_main", "LOG_LEVELS",
           "positive_int", "positive_float", "seed", "DEVICE_TYPES"]

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
DEVICE_TYPES = ("cpu", "cuda")
"""The device types torchbend's scenes and training scripts run on."""


# ------------------------------------------------------------------------------ option types
def _integer(text: str, what: str) -> int:
    try:
        return int(str(text).strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {what}, got {short_repr(text)}") from None


def positive_int(text: str) -> int:
    """An option's value as an integer >= 1 (argparse ``type=``): ``--steps 0`` is a usage error."""
    value = _integer(text, "a positive integer")
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


def positive_float(text: str) -> float:
    """An option's value as a positive, finite number (argparse ``type=``)."""
    try:
        value = float(str(text).strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {short_repr(text)}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive, finite number, got {short_repr(text)}")
    return value


def seed(text: str) -> int:
    """A ``--seed``: an integer in [0, 2**32) (argparse ``type=``)."""
    value = _integer(text, f"an integer in [0, {SEED_LIMIT})")
    if not 0 <= value < SEED_LIMIT:
        raise argparse.ArgumentTypeError(f"must be an integer in [0, {SEED_LIMIT}), got {short_repr(value)}")
    return value


def _one_line_errors(parser: argparse.ArgumentParser) -> None:
    """Make ``parser``'s usage errors one line: ``prog: error: message (see --help)``, exit status 2."""
    def error(message: str):
        parser.exit(2, f"{parser.prog}: error: {one_line(message)} (see --help)\n")

    vars(parser)["error"] = error  # the instance's own error(), in place of argparse's usage + message


def add_common_args(parser: argparse.ArgumentParser, *, config: str | None = None, out: str | None = None,
                    device: str = "cpu", config_positional: bool = False) -> argparse.ArgumentParser:
    """Add the shared options to ``parser`` (defaults: ``config``, ``out``, ``device``).

    ``config_positional`` also accepts the config path as the first positional argument
    (``python -m torchbend.scenes configs/beams.yaml``), stored in ``config`` like ``--config``."""
    _one_line_errors(parser)
    g = parser.add_argument_group("common options (every torchbend script)")
    if config_positional:
        parser.add_argument("config_path", nargs="?", metavar="CONFIG", help="YAML config (same as --config)")
    g.add_argument("--config", default=config, metavar="PATH",
                   help="YAML config" + (f" (default {config})" if config else ""))
    g.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key, value read as YAML, e.g. --set solver.tol=1e-8 (repeatable)")
    g.add_argument("--seed", type=seed, help=f"random seed in [0, {SEED_LIMIT}) (overrides the config's)")
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
    out = getattr(a, "out", None)
    if out is not None and os.path.exists(out) and not os.path.isdir(out):
        parser.error(f"argument --out: {short_repr(out)} exists and is not a directory")
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
    (``prog: error: --device cuda: ...``).  ``supported`` restricts the device types (default
    :data:`DEVICE_TYPES`: ``cpu`` and ``cuda``; ``why`` says why)."""
    prog = prog or _prog()
    shown = one_line(name)

    def fail(msg: str):
        raise SystemExit(f"{prog}: error: --device {shown}: {msg}")

    try:
        dev = torch.device(str(name).strip())
    except (RuntimeError, ValueError, TypeError):
        fail("not a torch device (expected cpu, cuda, cuda:N, ...)")
    custom = supported is not None
    supported = tuple(supported) if supported is not None else DEVICE_TYPES
    if dev.type not in supported:
        if custom:
            fail(f"this script runs on {' or '.join(supported)} only{' (' + why + ')' if why else ''}")
        fail(f"torchbend runs on {' or '.join(supported)} only, not on {dev.type}")
    if dev.index is not None and dev.index < 0:
        fail("a device index must be >= 0")
    problem = _device_problem(dev)
    if problem:
        fail(problem)
    return dev


def _device_problem(dev: torch.device) -> str | None:
    """Why ``dev`` (of a supported type, index >= 0) cannot be used here; None when it can."""
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            built = "this torch build has no CUDA support" if torch.version.cuda is None else "no CUDA GPU is visible"
            return f"CUDA is not available ({built}); use --device cpu"
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            return f"only {torch.cuda.device_count()} CUDA device(s) visible"
        return None
    if dev.type == "cpu":
        return None if dev.index in (None, 0) else "there is one CPU device: use --device cpu"
    if dev.type == "mps":
        return None if torch.backends.mps.is_available() else "MPS is not available on this machine; use --device cpu"
    try:
        torch.empty(1, device=dev)
    except Exception as e:  # any backend's "not available / not compiled" error
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        return f"not available ({first})"
    return None


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
    :class:`ConfigError` naming the path if it is missing, unreadable (truncated, not a checkpoint)
    or holds other objects."""
    if not os.path.isfile(path):
        raise ConfigError(f"--resume/--init: no checkpoint at {path}")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # UnpicklingError of a checkpoint with arbitrary objects, a truncated file, ...
        if not zipfile.is_zipfile(path):  # torch.save writes zip archives
            raise ConfigError(f"checkpoint {path} is not a torch checkpoint (a truncated file, or another kind of "
                              "file)") from None
        raise ConfigError(f"checkpoint {path} cannot be read with weights_only=True: {_load_error(e)}") from None
    if not isinstance(state, dict):
        raise ConfigError(f"checkpoint {path} holds a {type(state).__name__}, expected a dict")
    return state


def _load_error(e: Exception) -> str:
    """What went wrong in a ``torch.load(..., weights_only=True)``, in a few words."""
    text = str(e)
    m = re.search(r"Unsupported global: GLOBAL (\S+)", text)
    if m:
        return f"it holds a {m.group(1)} (a checkpoint holds only tensors and plain Python values)"
    if "WeightsUnpickler error" in text:  # the unpickler's own reason: the line after the marker
        after = [line.strip() for line in text.split("WeightsUnpickler error:", 1)[1].splitlines() if line.strip()]
        return f"corrupt data ({after[0]})" if after else "corrupt data"
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[0] if lines else type(e).__name__


def resume_checkpoint(path: str, config: dict, fields: Mapping[str, Any], *, ignore: Iterable[str] = (),
                      map_location=None, flag: str = "--resume") -> tuple[dict, list[str]]:
    """The checkpoint at ``path`` (:func:`load_checkpoint`) to continue a run of the validated config
    ``config`` from, and the config keys at which the two differ (but ``ignore``, e.g. the step count a
    resumed run extends).  :class:`ConfigError` naming the path when it is not a checkpoint of this
    script: its config has other sections, its ``step`` is no count, or an entry of ``fields``
    (``{name: type or tuple of types}``, e.g. ``{"model": dict}``) is missing or of another type."""
    ck = load_checkpoint(path, map_location)
    old = ck.get("config")
    if not isinstance(old, dict):
        raise ConfigError(f"{flag}: {path} is not a checkpoint of this script (it holds no config)")
    if set(old) != set(config):
        raise ConfigError(f"{flag}: {path} was written by another script (its config has the sections "
                          f"{', '.join(sorted(map(str, old)))}; this script's: {', '.join(sorted(config))})")
    step = ck.get("step")
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise ConfigError(f"{flag}: {path} is not a checkpoint of this script (its step is {short_repr(step)})")
    for name, kind in fields.items():
        if not isinstance(ck.get(name), kind):
            got = "missing" if name not in ck else f"a {type(ck[name]).__name__}"
            raise ConfigError(f"{flag}: {path} is not a checkpoint of this script ({name!r} is {got})")
    return ck, changed_keys(old, config, ignore)


def _check_optimizer_state(opt: torch.optim.Optimizer) -> None:
    """The restored state tensors of ``opt`` have its parameters' shapes (``load_state_dict`` checks
    only the parameter counts; a mismatch would fail at the next step)."""
    params = [p for group in opt.param_groups for p in group["params"]]
    if isinstance(opt, torch.optim.LBFGS):  # one flat state over all parameters
        n = sum(p.numel() for p in params)
        state = opt.state.get(params[0], {}) if params else {}
        for key in ("d", "prev_flat_grad"):
            v = state.get(key)
            if isinstance(v, torch.Tensor) and v.numel() != n:
                raise ValueError(f"optimizer state {key!r} has {v.numel()} entries, the parameters {n}")
        return
    for i, p in enumerate(params):
        for key, v in opt.state.get(p, {}).items():
            if isinstance(v, torch.Tensor) and v.ndim > 0 and v.shape != p.shape:
                raise ValueError(f"optimizer state {key!r} of parameter {i} has shape {tuple(v.shape)}, "
                                 f"the parameter {tuple(p.shape)}")


def restore(path: str, changed: Iterable[str], *pairs: tuple[Any, Any], what: str = "network",
            hint: str = "the same config", flag: str = "--resume") -> None:
    """Load each ``(module or optimizer, state dict)`` of ``pairs`` from the checkpoint at ``path``.
    A state that does not fit (another mesh or network size) is a :class:`ConfigError`:
    ``--resume: PATH does not fit this network (config differs at model.hidden): ...``, naming the
    config keys ``changed`` (:func:`resume_checkpoint`; ``hint`` in their place when none differs)."""
    try:
        for obj, state in pairs:
            obj.load_state_dict(state)
            if isinstance(obj, torch.optim.Optimizer):
                _check_optimizer_state(obj)
    except (RuntimeError, ValueError, KeyError, TypeError, IndexError, AttributeError) as e:
        text = str(e).strip()
        first = text.splitlines()[-1].strip() if text else type(e).__name__
        differs = f"config differs at {', '.join(changed)}" if changed else hint
        raise ConfigError(f"{flag}: {path} does not fit this {what} ({differs}): {first}") from None


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


def _out_of_memory(e: BaseException) -> bool:
    if isinstance(e, (MemoryError, torch.OutOfMemoryError)):
        return True
    text = str(e)
    return isinstance(e, RuntimeError) and any(
        m in text for m in ("can't allocate memory", "not enough memory", "out of memory"))


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def run_main(main: Callable[[], Any], prog: str | None = None) -> None:
    """Run ``main()`` as a command.  A user's mistake exits with one line ``prog: error: message``
    on stderr (exit status 1) instead of a traceback: a :class:`ConfigError` or other ``ValueError``
    (torchbend's error for invalid input: a bad mesh, URDF, joint vector, ...), an ``OSError`` (a
    file or folder that cannot be read or written) and running out of memory; Ctrl-C exits with
    status 130.  Any other exception is a bug and keeps its traceback.  With ``--log-level DEBUG``
    the traceback of a one-line error is printed too."""
    prog = prog or _prog()

    def fail(message: str):
        if logging.getLogger("torchbend").isEnabledFor(logging.DEBUG):
            traceback.print_exc()
        raise SystemExit(f"{prog}: error: {one_line(message)}") from None

    try:
        main()
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        raise SystemExit(130) from None
    except ValueError as e:
        fail(str(e) or type(e).__name__)
    except OSError as e:
        where = f": {e.filename}" if e.filename is not None else ""
        fail(f"{e.strerror}{where}" if e.strerror else _first_line(e))
    except (MemoryError, RuntimeError) as e:
        if not _out_of_memory(e):
            raise
        fail(f"out of memory ({_first_line(e)}); try a smaller mesh, batch or network")
