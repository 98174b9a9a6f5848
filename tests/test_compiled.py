"""The compiled extensions' one boundary (afvsgp_gym._compiled) and the backend switch: what
is built, what each backend runs, errors naming what is missing."""

import os
import pickle
import subprocess
import sysconfig

import numpy as np
import pytest

import afvsgp_gym
from afvsgp_gym import _compiled
from afvsgp_gym._compiled import Backend, resolve
from afvsgp_gym.cbf import FilterConfig, SafetyController

ALL = ("cones", "step", "bank", "arm")


def _c_compiler_fails(tmp_path) -> str | None:
    """None when the C compiler a build would use (``$CC``, else Python's) compiles a file
    that includes ``Python.h``, as every extension does; else why it cannot."""
    cc = (os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc").split()
    src = tmp_path / "probe.c"
    src.write_text("#include <Python.h>\nint probe(void) { return 0; }\n")
    cmd = [*cc, "-c", f"-I{sysconfig.get_paths()['include']}", str(src), "-o",
           str(tmp_path / "probe.o")]
    try:
        res = subprocess.run(cmd, capture_output=True, timeout=120)
    except (OSError, subprocess.SubprocessError) as exc:
        return f"no C compiler runs here ({' '.join(cc)}: {exc})"
    if res.returncode != 0:
        return (f"the C compiler {' '.join(cc)} does not compile against Python.h here "
                f"(exit {res.returncode})")
    return None


@pytest.mark.parametrize("module", list(_compiled.EXTENSIONS.values()))
def test_every_extension_is_built_where_a_c_compiler_runs(module, tmp_path):
    """Each of the package's C extensions is built wherever a C compiler compiles against
    Python.h, so that its parity tests (which skip where it is not built) run; installed
    without one, e.g. ``CC=/bin/false`` (CI's "nocc" row), the numpy paths run and this test
    is skipped, saying why."""
    why = _c_compiler_fails(tmp_path)
    if why is not None:
        pytest.skip(why)
    assert afvsgp_gym.compiled_extensions()[module], f"{module} was not built"


def test_backends_resolve_to_the_extensions_they_run(without_extensions):
    built = {name: _compiled.extension(name) is not None for name in ALL}
    assert resolve("numpy") == Backend("numpy")
    assert resolve("auto") == Backend("auto", **built)
    assert resolve("auto", ("bank",)) == Backend("auto", bank=built["bank"])
    backend = resolve("auto", ("step",))
    assert resolve(backend) is backend
    with pytest.raises(ValueError, match=r"backend must be one of \['auto', 'numpy', 'compiled'\]"):
        resolve("fast")
    without_extensions("cones", "bank")
    assert resolve("auto") == Backend("auto", step=built["step"], arm=built["arm"])
    step = "afvsgp_gym.cbf._step, " if not built["step"] else ""
    arm = ", afvsgp_gym.robots._arm" if not built["arm"] else ""
    with pytest.raises(ImportError, match=rf"needs afvsgp_gym\.cbf\._cones, {step}"
                                          rf"afvsgp_gym\.gp\._bank{arm}, which were not built"):
        resolve("compiled")
    if built["step"]:
        assert resolve("compiled", ("step",)) == Backend("compiled", step=True)


def test_an_extension_built_from_other_sources_counts_as_not_built(monkeypatch):
    """An editable install not rebuilt after the calling convention changed: a warning says
    to rebuild, and the numpy path runs."""
    if _compiled.extension("bank") is None:
        pytest.skip("afvsgp_gym.gp._bank not built")
    monkeypatch.setitem(_compiled.ABI, "bank", _compiled.ABI["bank"] + 1)
    monkeypatch.delitem(_compiled._loaded, "bank")
    with pytest.warns(RuntimeWarning, match=r"afvsgp_gym\.gp\._bank was built from other "
                                            r"sources .* rebuild it"):
        assert _compiled.extension("bank") is None
    assert not resolve("auto").bank


def test_a_backend_unpickled_where_an_extension_is_missing_runs_numpy(without_extensions):
    blob = pickle.dumps(Backend("compiled", cones=True, step=True, bank=True))
    without_extensions("step")
    assert pickle.loads(blob) == Backend("compiled", cones=_compiled.extension("cones") is not None,
                                         bank=_compiled.extension("bank") is not None)


def test_filter_config_backend_is_checked_and_the_old_switches_are_named():
    assert FilterConfig().backend == "auto"
    assert FilterConfig(backend=resolve("numpy")).backend == Backend("numpy")
    with pytest.raises(ValueError, match="backend must be one of"):
        FilterConfig(backend=True)
    for old in ("compiled_solver", "compiled_learners"):
        with pytest.raises(ValueError, match=f"{old} was replaced by backend"):
            SafetyController(-np.ones(2), np.ones(2), **{old: False})


def _fitted(backend, **kw):
    rng = np.random.default_rng(0)
    xi, u, z = rng.normal(size=(60, 4)), rng.uniform(-1, 1, size=(60, 2)), rng.normal(size=60)
    return SafetyController(-np.ones(2), np.ones(2), 2, dataset=(xi, u, z), backend=backend,
                            learner_kwargs={"num_inducing": 6, "window": 30},
                            learn_hyperparameters=False, **kw)


def test_the_backend_reaches_every_part_of_the_filter():
    built = {name: _compiled.extension(name) is not None for name in ALL}
    for backend, want in (("numpy", dict.fromkeys(ALL, False)), ("auto", built)):
        ctrl = _fitted(backend)
        assert ctrl.backend == Backend(backend, **want)
        assert ctrl.socp.compiled is want["cones"]
        assert ctrl.bank.bank.compiled is want["bank"]
        assert ctrl.residuals.backend.step is want["step"]


def test_backend_compiled_without_an_extension_is_an_import_error(without_extensions):
    without_extensions("step")
    with pytest.raises(ImportError, match=r"needs (\S+, )*afvsgp_gym\.cbf\._step,? .*not built"):
        SafetyController(-np.ones(2), np.ones(2), backend="compiled")
    assert not SafetyController(-np.ones(2), np.ones(2)).backend.step


class _Refuse:
    """An extension module that records and refuses any lookup of its functions (the filter
    catches a learner's exceptions: the record is what the test reads)."""

    def __init__(self, name, calls):
        self.name, self.calls = name, calls

    def __getattr__(self, attr):
        self.calls.append(f"{self.name}.{attr}")
        raise AssertionError(f"the backend 'numpy' called {self.name}.{attr}")


def test_backend_numpy_runs_no_compiled_code(monkeypatch):
    """A whole-arm AFVSGP episode through warm-up and the obstacle's approach with every
    extension's functions refusing to be called: the backend "numpy" never calls one."""
    import gymnasium as gym

    from afvsgp_gym.agents import NominalController
    from afvsgp_gym.cbf import binding_cones, controller, exploration, measurement, residuals
    from afvsgp_gym.gp import afvsgp_bank
    from afvsgp_gym.wrappers import SafetyFilter

    calls = []
    for mod, attr in ((binding_cones, "_cones"), (controller, "_step"), (exploration, "_step"),
                      (measurement, "_step"), (residuals, "_step"), (afvsgp_bank, "_core")):
        monkeypatch.setattr(mod, attr, _Refuse(f"{mod.__name__}.{attr}", calls))
    env = SafetyFilter(gym.make("afvsgp_gym/FrankaObstacleStatic-v0"), learner="afvsgp",
                       seed=0, backend="numpy")
    policy = NominalController(env)
    obs, _ = env.reset(seed=0)
    active = 0
    for _ in range(800):
        obs, _, _, _, info = env.step(policy(obs))
        active += info["filter_n_active"] > 1 and not info["warmup"]
    env.close()
    assert not calls and env.controller.last_error is None
    assert active > 20  # several barriers in the program after warm-up
