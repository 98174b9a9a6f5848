"""The compiled extensions and the backend switch: the one place that imports them.

``setup.py`` builds four optional C extensions where a C compiler is there (without one the
install goes on and the package runs its numpy paths, the reference of the compiled ones):

- ``afvsgp_gym.cbf._cones`` (``"cones"``): the cone program's one-cone and several-cones
  paths (:mod:`afvsgp_gym.cbf.binding_cones`);
- ``afvsgp_gym.cbf._step`` (``"step"``): the controller's per-step glue (cone matrices,
  exploration gate, barriers in the program, learned terms, eq. 48 samples, residuals);
- ``afvsgp_gym.gp._bank`` (``"bank"``): the AFVSGP learners' per-step arithmetic
  (:class:`~afvsgp_gym.gp.afvsgp_bank.AFVSGPBank`);
- ``afvsgp_gym.robots._arm`` (``"arm"``): the Franka bridge's sphere kinematics and pair
  terms (:class:`~afvsgp_gym.robots.kinematics.SphereKinematics`,
  :class:`~afvsgp_gym.robots.terms.BarrierModel`).

A module that runs compiled code takes its extension from :func:`extension` and is told by a
:class:`Backend` whether to use it. One setting selects the backend of the whole filter,
``FilterConfig(backend=...)`` (:data:`BACKENDS`):

- ``"auto"`` (default): every extension that is built;
- ``"numpy"``: none, only the numpy paths;
- ``"compiled"``: all of them; ``ImportError`` naming those that were not built.

The extensions are imported on first use, not when this module is, so that ``afvsgp_gym.gp``
never imports ``afvsgp_gym.cbf`` (the layers import downward).
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from types import ModuleType

__all__ = ["ABI", "BACKENDS", "EXTENSIONS", "Backend", "available", "extension", "resolve"]

#: The values of ``FilterConfig.backend`` (and of every ``backend`` argument).
BACKENDS = ("auto", "numpy", "compiled")

#: Short name -> the extension's module.
EXTENSIONS = {
    "cones": "afvsgp_gym.cbf._cones",
    "step": "afvsgp_gym.cbf._step",
    "bank": "afvsgp_gym.gp._bank",
    "arm": "afvsgp_gym.robots._arm",
}

#: The calling convention (the module's ``ABI``, 1 when it has none) each extension must have:
#: one built from older sources (an editable install not rebuilt) counts as not built.
ABI = {"cones": 1, "step": 1, "bank": 2, "arm": 1}

_loaded: dict[str, ModuleType | None] = {}


def extension(name: str) -> ModuleType | None:
    """The extension ``name`` (``"cones"``, ``"step"``, ``"bank"`` or ``"arm"``), imported on
    the first call; None when it was not built (or does not load, or was built from other sources: a
    ``RuntimeWarning`` says to rebuild it)."""
    try:
        return _loaded[name]
    except KeyError:
        pass
    try:
        mod = importlib.import_module(EXTENSIONS[name])
    except ImportError:
        mod = None
    if mod is not None and getattr(mod, "ABI", 1) != ABI[name]:
        warnings.warn(f"{EXTENSIONS[name]} was built from other sources (ABI "
                      f"{getattr(mod, 'ABI', 1)}, this package needs {ABI[name]}): the numpy "
                      "path runs; rebuild it (pip install -e . again, or python setup.py "
                      "build_ext --inplace)", RuntimeWarning, stacklevel=2)
        mod = None
    _loaded[name] = mod
    return mod


def available() -> dict[str, bool]:
    """``{module: built}`` of the extensions (e.g. ``"afvsgp_gym.gp._bank": True``)."""
    return {path: extension(name) is not None for name, path in EXTENSIONS.items()}


@dataclass(frozen=True)
class Backend:
    """Which extensions a component uses: ``name`` is the backend asked for, each flag True
    where that extension runs (see :func:`resolve`). Unpickled where an extension is not
    built, its flag is False (the numpy path)."""

    name: str
    cones: bool = False
    step: bool = False
    bank: bool = False
    arm: bool = False

    def __reduce__(self):
        return (_unpickled, (self.name, self.cones, self.step, self.bank, self.arm))


def _unpickled(name: str, cones: bool, step: bool, bank: bool, arm: bool = False) -> Backend:
    return Backend(name, *(flag and extension(part) is not None
                           for part, flag in (("cones", cones), ("step", step), ("bank", bank),
                                              ("arm", arm))))


def resolve(backend: str | Backend = "auto",
            parts: Iterable[str] = tuple(EXTENSIONS)) -> Backend:
    """The :class:`Backend` of ``backend`` (one of :data:`BACKENDS`; a ``Backend`` is returned
    as it is) for the extensions ``parts``, the others off. ``ValueError`` for another value;
    ``ImportError`` naming the extensions of ``parts`` not built when ``backend="compiled"``."""
    if isinstance(backend, Backend):
        return backend
    if not isinstance(backend, str) or backend not in BACKENDS:
        raise ValueError(f"backend must be one of {list(BACKENDS)}. Got: {backend!r}")
    parts = tuple(parts)
    if backend == "numpy":
        return Backend(backend)
    built = {part: extension(part) is not None for part in parts}
    missing = [EXTENSIONS[part] for part, ok in built.items() if not ok]
    if backend == "compiled" and missing:
        were = "was" if len(missing) == 1 else "were"
        raise ImportError(
            f"backend='compiled' needs {', '.join(missing)}, which {were} not built (install "
            "the package where a C compiler is available; backend='auto' uses the extensions "
            "that are built)")
    return Backend(backend, **built)
