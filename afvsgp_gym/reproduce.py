"""The paper's section VI experiments in simulation: Table I, Fig. 2, Fig. 4 and Fig. 6.

One public function, :func:`reproduce`, over private steps:

1. **Streams** (static scenario, paper Fig. 3). Two episodes are recorded with the oracle
   filter around the nominal tracker (the same trajectory for every learner): a *training*
   episode with the motion along y only (``switch_time`` pushed out) and an *evaluation*
   episode that switches from y to z (unseen data). Per step: the pre-step feature ``xi`` and
   the applied action ``u`` with the env's ``delta_b_true`` (true minus nominal ``h''``, the
   quantity the learners predict), and the eq. 48 measurement ``(xi_mid, z)`` the filter would
   learn from.
2. **Table I / Fig. 2** (one-step-ahead prediction). AFVSGP fits on ``n_prelim`` = 200
   preliminary samples (the start of the y-axis training data) with 20 inducing points; VSGP,
   GP and SOGP fit offline on ``n_offline`` = 2000 samples of the y-axis motion (the GP learns
   its hyperparameters on a 500-sample subset, then conditions on all 2000). Hyperparameters
   are learned as the safety filter learns them (``SafetyController(dataset=...)``: the same
   kernel initialisation, the bound or the marginal likelihood maximised). Then every learner
   runs predict-then-update over the same evaluation stream: predict ``delta_b`` at
   ``(xi_t, u_t)``, compare with the true value, update with the measurement. The GP is the
   paper's offline baseline (no update, no update time). MSE over the whole stream and after
   the switch; mean wall time of ``update``. A second pass emulates the real-time loop: an
   update that takes longer than the control period drops the samples that arrive meanwhile
   (``mse_realtime``, ``samples_used_realtime``; wall-clock dependent).
3. **Dynamic obstacle / Fig. 4**: closed-loop filtered episodes on the dynamic scenario with
   learners ``none``, ``sogp``, ``afvsgp`` and ``oracle``: steps with ``h < 0`` and min ``h``.
4. **Conservatism margin / Fig. 6**: min ``h`` of AFVSGP against the oracle (the model-based
   filter) on the same episodes.
5. **Whole arm** (beyond the paper): the dynamic episodes again with the default whole-arm
   safety spheres (one barrier per sphere), learners ``arm_learners``: episodes with cost
   (some h < 0 or an arm contact), contact steps, min ``h`` over every barrier.

JSON (``reproduce.json``)::

    {"table1": {"afvsgp": {"mse": x, "update_time_s": y, ...}, "vsgp": ..., "gp": ...,
                "sogp": ...},
     "dynamic": {"afvsgp": {"violations": n, "min_h": x, ...}, "sogp": ..., ...},
     "margin": {"afvsgp_min_h": x, "oracle_min_h": y, "conservatism": x - y, ...},
     "dynamic_arm": {"afvsgp": {"episodes_with_cost": n, "contact_steps": n, ...}, ...}}
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["PAPER", "ReproduceConfig", "reproduce"]

#: The paper's Table I (Gazebo) and real-robot margin, for side-by-side reporting.
PAPER = {
    "table1": {
        "afvsgp": {"mse": 0.5863, "update_time_s": 0.00613},
        "vsgp": {"mse": 1.4844, "update_time_s": 0.03562},
        "gp": {"mse": 6.6029, "update_time_s": None},
        "sogp": {"mse": 0.8118, "update_time_s": 0.08724},
    },
    "margin_m": 0.07,
}

TABLE1_METHODS = ("afvsgp", "vsgp", "gp", "sogp")


@dataclass(frozen=True)
class ReproduceConfig:
    """Sizes of the experiments (the defaults are the paper's protocol: the barrier of the
    end-effector sphere only, ``env_kwargs={"safety_spheres": "ee"}``).

    The exact GP learns its hyperparameters on ``gp_hyper_samples`` evenly spaced samples of its
    training set (the marginal likelihood costs O(N^3) per evaluation) and is then conditioned
    on all ``n_offline`` samples.

    ``stream_start`` / ``stream_end`` are step indices of the evaluation episode (None: right
    after the warm-up and amplitude ramp / the end of the episode); ``train_start`` likewise
    for the training episode.
    """

    static_env: str = "afvsgp_gym/FrankaObstacleStatic-v0"
    dynamic_env: str = "afvsgp_gym/FrankaObstacleDynamic-v0"
    env_kwargs: dict = field(default_factory=lambda: {"safety_spheres": "ee"})
    dynamic_env_kwargs: dict = field(default_factory=dict)
    n_prelim: int = 200
    n_offline: int = 2000
    num_inducing: int = 20
    window: int = 200
    gp_hyper_samples: int = 500
    forgetting: float = 0.99
    train_start: int | None = None
    stream_start: int | None = None
    stream_end: int | None = None
    dynamic_learners: tuple[str, ...] = ("none", "sogp", "afvsgp", "oracle")
    dynamic_episodes: int = 3
    arm_learners: tuple[str, ...] = ("none", "afvsgp", "oracle")
    dynamic_max_steps: int | None = None
    seed: int = 0

    @classmethod
    def quick(cls, **overrides: Any) -> ReproduceConfig:
        """Smaller sizes for ``--quick``: 500 offline samples, a 1200-step stream around the
        switch, one dynamic episode per learner."""
        base = cls(n_offline=500, stream_start=1900, stream_end=3100, dynamic_episodes=1)
        return replace(base, **overrides)


# ----------------------------------------------------------------------------- streams


def _record(env_id: str, env_kwargs: dict, seed: int, n_steps: int) -> dict[str, np.ndarray]:
    """Run the oracle-filtered nominal tracker; per-step prediction and measurement data."""
    import gymnasium as gym

    from afvsgp_gym.agents import NominalController
    from afvsgp_gym.cbf import measure
    from afvsgp_gym.wrappers import SafetyFilter

    env = SafetyFilter(gym.make(env_id, **env_kwargs), learner="oracle")
    base = env.unwrapped
    policy = NominalController(env)
    cols: dict[str, list] = {k: [] for k in ("t", "xi", "u", "truth", "xi_mid", "z", "h")}
    try:
        obs, _ = env.reset(seed=seed)
        switch_time = float(base.reference.switch_time)
        for _ in range(n_steps):
            before = base.barrier_terms("nominal")[0]
            obs, _, terminated, truncated, info = env.step(policy(obs))
            after = base.barrier_terms("nominal")[0]
            u = np.asarray(info["action_applied"], dtype=np.float64)
            xi_mid, z = measure(before, u, after, float(base.dt))
            cols["t"].append(float(info.get("time", len(cols["t"]) * base.dt)))
            cols["xi"].append(np.asarray(before.xi, dtype=np.float64))
            cols["u"].append(u)
            cols["truth"].append(float(np.ravel(info["delta_b_true"])[0]))
            cols["xi_mid"].append(xi_mid)
            cols["z"].append(z)
            cols["h"].append(float(info["h"]))
            if terminated or truncated:
                break
    finally:
        env.close()
    out = {k: np.asarray(v, dtype=np.float64) for k, v in cols.items()}
    out["switch_time"] = np.float64(switch_time)
    return out


def _slice(rec: dict, start: int, stop: int) -> dict:
    return {k: (v[start:stop] if np.ndim(v) else v) for k, v in rec.items()}


def _default_start(env_id: str, env_kwargs: dict) -> int:
    """First step after warm-up and the 1 s amplitude ramp."""
    import gymnasium as gym

    env = gym.make(env_id, **env_kwargs)
    try:
        base = env.unwrapped
        return int(base.warmup_steps + round(1.0 / float(base.dt)))
    finally:
        env.close()


# ----------------------------------------------------------------------------- Table I


def _fit_learner(name: str, cfg: ReproduceConfig, xi, u, z, action_dim: int):
    """Fit as the safety filter does (its kernel initialisation and hyperparameter fit)."""
    from afvsgp_gym.cbf import make_learner
    from afvsgp_gym.gp.warmup_fit import fit_with_restarts

    kwargs: dict[str, Any] = {
        "afvsgp": {"num_inducing": cfg.num_inducing, "window": cfg.window,
                   "forgetting": cfg.forgetting},
        "vsgp": {"num_inducing": cfg.num_inducing},
        "sogp": {"num_inducing": cfg.num_inducing},
        "gp": {"online": False},
    }[name]
    n = len(z)
    sub = slice(None)
    if name == "gp" and n > cfg.gp_hyper_samples:  # O(N^3) per bound evaluation
        sub = np.linspace(0, n - 1, cfg.gp_hyper_samples).round().astype(int)
    learner = fit_with_restarts(lambda **kw: make_learner(name, action_dim, **{**kwargs, **kw}),
                                xi[sub], u[sub], z[sub])
    if name == "gp" and n > cfg.gp_hyper_samples:
        from afvsgp_gym.gp import ExactGP

        learner = ExactGP(learner.kernel_, learner.noise_variance_, online=False)
        learner.fit(xi, u, z, learn_hyperparameters=False)
    return learner


def _refit(learner, xi, u, z):
    """Same class, parameters and learned hyperparameters, fitted again without optimising."""
    params = {k: v for k, v in vars(learner).items() if not k.endswith("_")
              and not k.startswith("_")}
    params.update(kernel=learner.kernel_, noise_variance=learner.noise_variance_)
    return type(learner)(**params).fit(xi, u, z, learn_hyperparameters=False)


def _predict_then_update(learner, stream: dict, online: bool,
                         realtime_dt: float | None = None) -> dict[str, np.ndarray]:
    """Predict at ``(xi_t, u_t)``, then update with the eq. 48 sample of step t.

    ``realtime_dt``: emulate a control loop of that period in which an update that takes
    ``tau`` seconds keeps the learner busy, so the next ``ceil(tau / dt) - 1`` samples are
    dropped (the paper's data-density argument, Fig. 2(c, d)).
    """
    n = len(stream["truth"])
    mean, var = np.full(n, np.nan), np.full(n, np.nan)
    upd = np.full(n, np.nan)
    busy_until = 0
    for t in range(n):
        m, v = learner.predict(stream["xi"][t][None], stream["u"][t][None])
        mean[t], var[t] = m[0], v[0]
        if online and t >= busy_until:
            t0 = time.perf_counter()
            learner.update(stream["xi_mid"][t], stream["u"][t], float(stream["z"][t]))
            upd[t] = time.perf_counter() - t0
            if realtime_dt is not None:
                busy_until = t + max(1, int(np.ceil(upd[t] / realtime_dt)))
    return {"mean": mean, "std": np.sqrt(np.clip(var, 0.0, None)), "update_time": upd}


def _table1(cfg: ReproduceConfig, train: dict, stream: dict, log: Callable[[str], None]):
    action_dim = train["u"].shape[1]
    after = stream["t"] >= float(stream["switch_time"])
    rows, series = {}, {}
    for name in TABLE1_METHODS:
        n_fit = cfg.n_prelim if name == "afvsgp" else cfg.n_offline
        t0 = time.perf_counter()
        learner = _fit_learner(name, cfg, train["xi_mid"][:n_fit], train["u"][:n_fit],
                               train["z"][:n_fit], action_dim)
        fit_s = time.perf_counter() - t0
        online = name != "gp"
        # a second learner with the same hyperparameters for the real-time pass
        learner_rt = _refit(learner, train["xi_mid"][:n_fit], train["u"][:n_fit],
                            train["z"][:n_fit]) if online else None
        res = _predict_then_update(learner, stream, online)
        err2 = (res["mean"] - stream["truth"]) ** 2
        upd = res["update_time"][np.isfinite(res["update_time"])]
        rt: dict[str, Any] = {}
        if online:
            ctrl_dt = float(np.median(np.diff(stream["t"]))) if len(stream["t"]) > 1 else 1.0
            res_rt = _predict_then_update(learner_rt, stream, True, realtime_dt=ctrl_dt)
            e2 = (res_rt["mean"] - stream["truth"]) ** 2
            rt = {"mse_realtime": float(np.mean(e2)),
                  "mse_after_switch_realtime": float(np.mean(e2[after])) if after.any() else None,
                  "samples_used_realtime": int(np.isfinite(res_rt["update_time"]).sum()),
                  "control_period_s": ctrl_dt}
        rows[name] = {
            "mse": float(np.mean(err2)),
            "update_time_s": float(np.mean(upd)) if online else None,
            "mse_before_switch": float(np.mean(err2[~after])) if (~after).any() else None,
            "mse_after_switch": float(np.mean(err2[after])) if after.any() else None,
            "update_time_median_s": float(np.median(upd)) if online else None,
            "update_time_p99_s": float(np.percentile(upd, 99)) if online else None,
            "n_fit": int(n_fit),
            "n_stream": int(len(err2)),
            "fit_time_s": fit_s,
            **rt,
        }
        series[name] = {"t": stream["t"], "truth": stream["truth"], "mean": res["mean"],
                        "std": res["std"]}
        log(f"table1 {name:6s} mse={rows[name]['mse']:.4g} "
            f"after_switch={rows[name]['mse_after_switch']} "
            f"update={rows[name]['update_time_s']} fit={fit_s:.1f}s")
    return rows, series


# ----------------------------------------------------------------------------- Figs. 4, 6


def _dynamic(cfg: ReproduceConfig, log: Callable[[str], None], learners=None,
             env_kwargs: dict | None = None, label: str = "dynamic"):
    from afvsgp_gym.evaluation import evaluate

    kw = {**cfg.env_kwargs, **cfg.dynamic_env_kwargs} if env_kwargs is None else env_kwargs
    res = evaluate(cfg.dynamic_env, agent="nominal",
                   learners=list(cfg.dynamic_learners if learners is None else learners),
                   episodes=cfg.dynamic_episodes, seed=cfg.seed, max_steps=cfg.dynamic_max_steps,
                   env_kwargs=kw, traces=True)
    rows = {}
    for name, s in res["summary"].items():
        rows[name] = {
            "violations": s["violation_steps"],
            "min_h": s["min_h"],
            "episodes": s["episodes"],
            "episodes_with_violations": s["episodes_with_violation"],
            "episodes_with_cost": s["episodes_with_cost"],
            "cost_steps": s["cost_steps"],
            "tracking_error_mean": s["tracking_error_mean"],
            "collisions": s["contact_steps"],
            "interventions": s["interventions"],
            "infeasible_steps": s["infeasible_steps"],
            "filter_time_median_s": s["filter_time_median_s"],
            "filter_time_p99_s": s["filter_time_p99_s"],
            "min_h_per_episode": [r["min_h"] for r in res["episodes"] if r["learner"] == name],
            "violations_per_episode": [r["violation_steps"] for r in res["episodes"]
                                       if r["learner"] == name],
        }
        log(f"{label} {name:6s} violations={s['violation_steps']} "
            f"contacts={s['contact_steps']} min_h={s['min_h']:.4f}")
    traces = {name: tr[0] for name, tr in res["traces"].items()}  # first episode per learner
    return rows, traces


def _margin(dynamic: dict) -> dict:
    out: dict[str, Any] = {"scenario": "dynamic", "paper_real_robot_m": PAPER["margin_m"]}
    a = dynamic.get("afvsgp", {}).get("min_h")
    o = dynamic.get("oracle", {}).get("min_h")
    out["afvsgp_min_h"] = a
    out["oracle_min_h"] = o
    out["conservatism"] = (a - o) if a is not None and o is not None else None
    pa = dynamic.get("afvsgp", {}).get("min_h_per_episode")
    po = dynamic.get("oracle", {}).get("min_h_per_episode")
    if pa and po:  # same seeds: episode-wise differences
        out["afvsgp_min_h_per_episode"] = pa
        out["oracle_min_h_per_episode"] = po
        out["conservatism_mean"] = float(np.mean(np.subtract(pa, po)))
    return out


# ----------------------------------------------------------------------------- driver


def reproduce(
    config: ReproduceConfig | None = None,
    *,
    out_dir: str | Path | None = None,
    json_path: str | Path | None = None,
    figures: bool = True,
    log: Callable[[str], None] | None = None,
) -> dict:
    """Run the protocol of the module docstring; returns the JSON dict.

    ``out_dir`` receives ``fig2_uncertainty.png``, ``fig4_barrier.png``, ``fig6_margin.png``,
    ``table1.md``, ``traces.npz`` (for ``afvsgp-gym plot``) and ``reproduce.json`` (unless
    ``json_path`` names another file).
    """
    import afvsgp_gym  # noqa: F401  (registers the ids)

    cfg = config or ReproduceConfig()
    log = log or (lambda msg: None)
    if cfg.n_prelim > cfg.n_offline:
        raise ValueError(f"n_prelim ({cfg.n_prelim}) must not exceed n_offline ({cfg.n_offline})")
    t_start = time.perf_counter()
    kw = dict(cfg.env_kwargs)
    train_start = cfg.train_start
    if train_start is None:
        train_start = _default_start(cfg.static_env, kw)
    stream_start = cfg.stream_start if cfg.stream_start is not None else train_start
    # training episode: y motion only; evaluation episode: the scenario's y -> z switch
    train_kw = {**kw, "switch_time": 1e6}
    log(f"recording the y-axis training stream ({cfg.n_offline} samples)")
    train = _slice(_record(cfg.static_env, train_kw, cfg.seed, train_start + cfg.n_offline),
                   train_start, train_start + cfg.n_offline)
    if len(train["z"]) < cfg.n_offline:
        raise ValueError(f"the training episode gave {len(train['z'])} samples after step "
                         f"{train_start}, fewer than n_offline={cfg.n_offline}")
    end = cfg.stream_end if cfg.stream_end is not None else 10**9
    log("recording the evaluation stream (y -> z switch)")
    full = _record(cfg.static_env, kw, cfg.seed + 1, end)
    stream = _slice(full, stream_start, end)
    log(f"stream: {len(stream['z'])} samples, switch at t = {float(stream['switch_time']):g} s")
    table1, series = _table1(cfg, train, stream, log)
    dynamic, h_traces = _dynamic(cfg, log)
    result = {"table1": table1, "dynamic": dynamic, "margin": _margin(dynamic)}
    if cfg.arm_learners:
        arm_kw = {**cfg.env_kwargs, **cfg.dynamic_env_kwargs}
        arm_kw.pop("safety_spheres", None)  # the env's default: the whole arm
        result["dynamic_arm"], _ = _dynamic(cfg, log, cfg.arm_learners, arm_kw, "whole-arm")
    protocol = {"config": _jsonable(asdict(cfg)), "train_start": train_start,
                "stream_start": stream_start, "switch_time_s": float(stream["switch_time"]),
                "elapsed_s": time.perf_counter() - t_start, "code": _code_version(),
                "paper": PAPER}
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        _save_traces(out / "traces.npz", series, float(stream["switch_time"]), h_traces)
        (out / "table1.md").write_text(table1_markdown(result))
        (out / "reproduce_protocol.json").write_text(json.dumps(protocol, indent=2) + "\n")
        if figures:
            render_figures(out / "traces.npz", out)
        if json_path is None:
            json_path = out / "reproduce.json"
    if json_path is not None:
        Path(json_path).write_text(json.dumps(_jsonable(result), indent=2) + "\n")
    log(f"done in {time.perf_counter() - t_start:.0f} s")
    return result


def _code_version() -> dict:
    """The package's version and :func:`~afvsgp_gym.evaluation.code_version` (in a git
    checkout its commit, ``-dirty`` when the tree was modified), as episode records say it."""
    import afvsgp_gym
    from afvsgp_gym.evaluation import code_version

    return {"version": afvsgp_gym.__version__, "code_version": code_version()}


def _jsonable(x: Any) -> Any:
    from afvsgp_gym.evaluation import jsonable

    return jsonable(x)


def _save_traces(path: Path, series: dict, switch_time: float, h_traces: dict) -> None:
    arrays: dict[str, np.ndarray] = {"switch_time": np.float64(switch_time)}
    for name, s in series.items():
        for k, v in s.items():
            arrays[f"fig2/{name}/{k}"] = np.asarray(v)
    for name, tr in h_traces.items():
        arrays[f"fig4/{name}/t"] = tr["t"]
        arrays[f"fig4/{name}/h"] = tr["h"]
    np.savez_compressed(path, **arrays)


_LABELS = {"afvsgp": "AFVSGP (ours)", "vsgp": "VSGP", "gp": "GP (offline)", "sogp": "SOGP",
           "none": "no learning", "oracle": "oracle (true model)"}


def render_figures(traces: str | Path, out_dir: str | Path) -> list[Path]:
    """Fig. 2, 4 and 6-like PNGs from a ``traces.npz`` written by :func:`reproduce`."""
    from afvsgp_gym.plotting import plot_barrier, plot_uncertainty

    data = np.load(traces)
    out = Path(out_dir)
    groups: dict[str, dict[str, dict[str, np.ndarray]]] = {"fig2": {}, "fig4": {}}
    for key in data.files:
        if key.count("/") == 2:
            fig, name, col = key.split("/")
            groups[fig].setdefault(name, {})[col] = data[key]
    paths = []
    fig2 = {_LABELS.get(n, n): s for n, s in _ordered(groups["fig2"], TABLE1_METHODS)}
    if fig2:
        paths.append(plot_uncertainty(
            fig2, out / "fig2_uncertainty.png", switch_time=float(data["switch_time"]),
            title="One-step-ahead prediction of the HOCBF uncertainty, static obstacle, "
                  "y -> z switch"))
    order4 = ("none", "sogp", "afvsgp", "oracle")
    fig4 = {_LABELS.get(n, n): s for n, s in _ordered(groups["fig4"], order4)
            if n in ("none", "sogp", "afvsgp")}
    if fig4:
        paths.append(plot_barrier(fig4, out / "fig4_barrier.png",
                                  title="h over time, dynamic obstacle (first episode)"))
    fig6 = {_LABELS.get(n, n): s for n, s in _ordered(groups["fig4"], ("oracle", "afvsgp"))
            if n in ("oracle", "afvsgp")}
    if len(fig6) == 2:
        paths.append(plot_barrier(fig6, out / "fig6_margin.png",
                                  title="Conservatism: model-based (oracle) vs AFVSGP, dynamic "
                                        "obstacle (first episode)"))
    return paths


def _ordered(d: dict, order: Sequence[str]):
    keys = [k for k in order if k in d] + [k for k in d if k not in order]
    return [(k, d[k]) for k in keys]


def table1_markdown(result: dict) -> str:
    """Markdown tables: Table I next to the paper's numbers, the dynamic case, the margin and
    the whole-arm episodes."""
    from afvsgp_gym.tables import format_table, format_value

    def ms(x):
        return None if x is None else 1e3 * x

    rows = []
    for name in TABLE1_METHODS:
        r = result["table1"].get(name)
        if r is None:
            continue
        p = PAPER["table1"][name]
        rows.append({"model": _LABELS[name], "mse": r["mse"],
                     "after": r.get("mse_after_switch"), "upd": ms(r["update_time_s"]),
                     "paper_mse": p["mse"], "paper_upd": ms(p["update_time_s"]),
                     "rt": r.get("mse_realtime"),
                     "used": f"{r.get('samples_used_realtime', '-')} / {r['n_stream']}"})
    parts = [format_table(rows, ["model", "mse", "after", "upd", "paper_mse", "paper_upd", "rt",
                                 "used"],
                          ["Model", "MSE (stream)", "MSE after switch", "mean update time [ms]",
                           "paper MSE", "paper update time [ms]", "MSE, real-time loop",
                           "samples used, real-time"], markdown=True)]
    dyn = [{"name": _LABELS.get(k, k), **v} for k, v in result["dynamic"].items()]
    parts.append(format_table(dyn, ["name", "violations", "min_h", "collisions"],
                              ["Dynamic obstacle (end-effector barrier)", "steps with h < 0",
                               "min h [m]", "arm contact steps"], markdown=True))
    m = result["margin"]
    f = format_value
    text = (f"Conservatism margin (dynamic obstacle): min h AFVSGP = {f(m['afvsgp_min_h'])} m, "
            f"oracle = {f(m['oracle_min_h'])} m, difference = {f(m['conservatism'])} m "
            f"(paper, real robot: {PAPER['margin_m']} m).")
    if "conservatism_mean" in m:
        per = ", ".join(f"{a:.4f} vs {o:.4f}" for a, o in
                        zip(m["afvsgp_min_h_per_episode"], m["oracle_min_h_per_episode"],
                            strict=False))
        text += (f"\nPer episode, min h AFVSGP vs oracle [m]: {per}; mean difference "
                 f"{f(m['conservatism_mean'])} m.")
    parts.append(text)
    if "dynamic_arm" in result:
        arm = [{"name": _LABELS.get(k, k), **v} for k, v in result["dynamic_arm"].items()]
        parts.append(format_table(
            arm, ["name", "episodes_with_cost", "cost_steps", "collisions", "min_h",
                  "tracking_error_mean"],
            ["Dynamic obstacle, whole arm", "episodes with cost", "cost steps",
             "arm contact steps", "min h [m]", "tracking error [m]"], markdown=True))
    return "\n\n".join(parts) + "\n"
