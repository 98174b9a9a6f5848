"""Helpers shared by the scripts that write the measurement pages of the documentation.

Each ``benchmarks/page_*.py`` reads one results file kept in the tree and writes one page under
``docs/``; ``--check`` compares instead of writing (exit status 1 when the page is not what the
script generates), which is how CI keeps the pages and their results files together. Only the
standard library is used, so the check runs in the docs build's environment without the
package or numpy installed.

The statistics are exact: the Clopper-Pearson bound by bisection on the binomial distribution,
the Wilson interval in closed form, Welch's t-test through the regularised incomplete beta
function (a continued fraction, Numerical Recipes 6.4).
"""

from __future__ import annotations

import argparse
import difflib
import gzip
import json
import math
import re
import statistics
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
DOCS = ROOT / "docs"

#: z of a two-sided 95 % normal interval
Z95 = 1.959963984540054


# --------------------------------------------------------------------------- statistics
def _log_binom_pmf(i: int, n: int, p: float) -> float:
    return (math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1)
            + i * math.log(p) + (n - i) * math.log1p(-p))


def binom_cdf(k: int, n: int, p: float) -> float:
    """P(X <= k) for X ~ Binomial(n, p)."""
    if p <= 0.0:
        return 1.0
    if p >= 1.0:
        return 1.0 if k >= n else 0.0
    return min(1.0, sum(math.exp(_log_binom_pmf(i, n, p)) for i in range(k + 1)))


def cp_upper(k: int, n: int, level: float = 0.95) -> float:
    """Exact one-sided Clopper-Pearson upper bound on a binomial rate (k events in n): the p
    at which P(X <= k) = 1 - level."""
    if n <= 0 or k >= n:
        return 1.0
    if k == 0:
        return 1.0 - (1.0 - level) ** (1.0 / n)
    lo, hi = 0.0, 1.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if binom_cdf(k, n, mid) > 1.0 - level:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def wilson(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial rate (two-sided, 95 % by default)."""
    if n <= 0:
        return 0.0, 1.0
    p = k / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, centre - half), min(1.0, centre + half)


def _betacf(a: float, b: float, x: float) -> float:
    tiny = 1e-300
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 1000):
        m2 = 2 * m
        for num in (m * (b - m) * x / ((a + m2 - 1) * (a + m2)),
                    -(a + m) * (a + b + m) * x / ((a + m2) * (a + m2 + 1))):
            d = 1.0 + num * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + num / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def betainc(a: float, b: float, x: float) -> float:
    """Regularised incomplete beta function I_x(a, b)."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
                     + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * _betacf(a, b, x) / a
    return 1.0 - front * _betacf(b, a, 1.0 - x) / b


def welch_p(x: Sequence[float], y: Sequence[float]) -> float:
    """Two-sided p-value of Welch's t-test (unequal variances) of the means of x and y."""
    vx, vy = statistics.variance(x) / len(x), statistics.variance(y) / len(y)
    if vx + vy == 0.0:
        return 1.0 if statistics.fmean(x) == statistics.fmean(y) else 0.0
    t = (statistics.fmean(x) - statistics.fmean(y)) / math.sqrt(vx + vy)
    df = (vx + vy) ** 2 / (vx * vx / (len(x) - 1) + vy * vy / (len(y) - 1))
    return betainc(df / 2.0, 0.5, df / (df + t * t))


def mean_se(values: Sequence[float]) -> tuple[float, float]:
    """Mean and standard error of the mean (sample standard deviation / sqrt(n))."""
    m = statistics.fmean(values)
    se = statistics.stdev(values) / math.sqrt(len(values)) if len(values) > 1 else 0.0
    return m, se


# --------------------------------------------------------------------------- files
def read_json(path: Path) -> dict:
    with open(path, encoding="utf-8") as fh:
        return json.load(fh)


def read_jsonl(path: Path) -> list[dict]:
    """Records of a JSON-lines file, plain or gzip-compressed (a sweep's results file); a torn
    last line (a sweep killed while writing it) is left out, as ``afvsgp-gym report`` does."""
    data = Path(path).read_bytes()
    if data[:2] == b"\x1f\x8b":
        data = gzip.decompress(data)
    lines = [line for line in data.decode().splitlines() if line.strip()]
    records = [json.loads(line) for line in lines[:-1]]
    try:
        records += [json.loads(line) for line in lines[-1:]]
    except ValueError:
        pass
    return records


def parse_output(text: str) -> dict[str, float]:
    """``name  value [us]`` lines of a benchmark's printed output as {name: value}; values in
    microseconds are returned in microseconds, lines that are not of that form (a version
    such as ``numpy 1.26.4`` among them) are skipped."""
    out = {}
    for line in text.splitlines():
        m = re.match(r"^(.*?)\s+(-?[0-9.]+(?:e[-+]?[0-9]+)?)(?: us)?$", line.strip())
        if m and not line.startswith(("machine", "calibration")):
            try:
                out[m.group(1).strip()] = float(m.group(2))
            except ValueError:
                continue
    return out


# --------------------------------------------------------------------------- markdown
def table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """A markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def provenance(script: str, sources: Sequence[str]) -> str:
    """The comment every generated page starts with."""
    return (f"<!-- Generated by `python {script}` from {', '.join(sources)}. "
            "Do not edit: change the script or the results file and run it again. -->")


def measured(meta: dict) -> str:
    """One line with the machine, the date and the code version of a results file."""
    parts = [f"**Machine:** {meta.get('machine') or 'not recorded'}",
             f"**date:** {meta.get('date') or 'not recorded'}"]
    if meta.get("code"):
        parts.append(f"**code:** `{meta['code']}`")
    return "; ".join(parts) + "."


def replace_block(text: str, name: str, block: str) -> str:
    """``text`` with the lines between ``<!-- NAME:start -->`` and ``<!-- NAME:end -->``
    replaced by ``block``."""
    pattern = re.compile(rf"(<!-- {name}:start[^>]*-->\n).*?(<!-- {name}:end -->)", re.S)
    if not pattern.search(text):
        raise SystemExit(f"no <!-- {name}:start --> ... <!-- {name}:end --> block found")
    return pattern.sub(lambda m: m.group(1) + block.rstrip("\n") + "\n" + m.group(2), text)


def emit(outputs: dict[Path, str], check: bool) -> int:
    """Write every ``path: text`` (or, with ``check``, compare and report the differences)."""
    stale = []
    for path, text in outputs.items():
        old = path.read_text(encoding="utf-8") if path.exists() else ""
        if old == text:
            continue
        if check:
            stale.append(path)
            diff = difflib.unified_diff(old.splitlines(), text.splitlines(), str(path),
                                        "generated", lineterm="", n=1)
            print("\n".join(list(diff)[:40]), file=sys.stderr)
        else:
            path.write_text(text, encoding="utf-8")
            print(f"wrote {path.relative_to(ROOT)}")
    if stale:
        names = ", ".join(str(p.relative_to(ROOT)) for p in stale)
        print(f"not what the script generates: {names}", file=sys.stderr)
        return 1
    return 0


def main(doc: str, build: Callable[[], dict[Path, str]]) -> int:
    """The command line of a page script: write its outputs, or ``--check`` them."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="compare with the files in the tree instead of writing them")
    return emit(build(), parser.parse_args().check)


# Which brake a record ran with. Records written from 920d688 on by ``run_spec`` carry
# ``brake_version`` (``FrankaObstacleEnv.BRAKE_VERSION``, bumped with every change of the
# brake's actions); the code lists below tell the brakes of older records apart, and are
# frozen: a later brake change bumps the version instead of adding codes to a list.

#: Codes whose brake kept its hold point across feasible gaps of up to 0.1 s also while an
#: obstacle moved (``brake_hold_memory=0.1``, their default, before 2ac8a9b).
HOLD_WHILE_MOVING_CODES = ("2b31452", "104f9db", "49e78fd", "7562164")
#: Codes of the results files whose brake took a fresh hold point at every engagement
#: (``brake_hold_memory=0``, the default from b492550, or before the option existed) unless
#: the record says otherwise. Every later code keeps it 0.1 s while the obstacles stand
#: still, as 2ac8a9b did.
FRESH_HOLD_CODES = ("b492550", "f6aeb98", "f6db547", "363f5f1", "601de67", "6282fe2",
                    "649b602", "790bff7", "2ab9b5a", "e3180a8", "17bfd50", "a2fda25",
                    "685f36b", "7b50257", "e6d2df1", "bf2338d", "408eb6a", "f2600ff")


def hold_memory_of(rec: dict) -> str:
    """How the brake of a record's episode kept its hold point: ``"still"`` (0.1 s while the
    obstacles stand still, today's default), ``"fresh"`` (anew at every engagement) or
    ``"moving"`` (0.1 s, also while an obstacle moved)."""
    given = {**rec["config"]["env_kwargs"], **rec.get("ran_with", {})}.get("brake_hold_memory")
    if brake_version(rec) >= 1:
        return "fresh" if given == 0 else "still"
    code = str(rec.get("code_version"))
    if given is not None:
        return "fresh" if given == 0 else ("moving" if code in HOLD_WHILE_MOVING_CODES
                                           else "still")
    if code in HOLD_WHILE_MOVING_CODES:
        return "moving"
    return "fresh" if code in FRESH_HOLD_CODES else "still"


#: The first code whose brake's give-way holds every other pair within ``EVADE_DISTANCE``
#: from closing in (8eee042) and keeps giving way to a pair until ``EVADE_HYSTERESIS``
#: beyond it; before 8eee042, giving way to a moving obstacle could drive the arm into
#: another (a hand 32 cm into the tabletop's table).
GIVE_WAY_FIX_CODE = "920d688"
#: The codes of the results files before it.
OLD_GIVE_WAY_CODES = (*FRESH_HOLD_CODES, *HOLD_WHILE_MOVING_CODES, "da952a6", "e3180a8",
                      "72a23a8", "8eee042")
_CAMERA_OPTIONS = ("obstacle_noise", "obstacle_rate", "obstacle_delay")


def brake_version(rec: dict) -> int:
    """The brake a record's episode ran with: its ``brake_version``; for a record written
    before the field, 0 (an older brake) if its code is in one of the lists above, else 1."""
    if rec.get("brake_version") is not None:
        return int(rec["brake_version"])
    code = str(rec.get("code_version"))
    return 0 if code in OLD_GIVE_WAY_CODES else 1


def may_give_way(rec: dict) -> bool:
    """Whether the brake of a record's episode may give way: its obstacles move, or the
    robot senses them through a camera (the estimate's velocity is not exactly zero)."""
    c = rec["config"]
    kwargs = c["env_kwargs"]
    static = any(s in c["env_id"] for s in ("Static", "Shelf")) and "obstacles" not in kwargs
    return not static or any(kwargs.get(k) for k in _CAMERA_OPTIONS)


def give_way_caveat(recs: list[dict]) -> list[str]:
    """Sentences on the episodes that reached the brake where it may give way: those run
    again with today's give-way and those that ran with the older one."""
    braking = [r for r in recs if r["infeasible_steps"] > 0 and may_give_way(r)]
    rerun = [r for r in braking if str(r.get("code_version")) == GIVE_WAY_FIX_CODE]
    old = [r for r in braking if brake_version(r) == 0]
    out = []
    if rerun:
        out.append(f"{len(rerun)} of the episodes that reached the brake with moving obstacles "
                   f"were run again at `{GIVE_WAY_FIX_CODE}`, once the brake's give-way to a "
                   "moving obstacle stopped closing in on the others (it had driven a hand "
                   "32 cm into the tabletop's table) and kept giving way to a pair until "
                   "1 cm beyond its 10 cm distance.")
    if old:
        out.append(f"**Caveat.** {len(old)} episodes that reached the brake with moving (or "
                   "camera-sensed) obstacles ran with the older give-way, which could close in "
                   "on another obstacle, and have not been run again.")
    return out


def hold_memory_caveat(recs: list[dict]) -> list[str]:
    """A paragraph on the episodes that reached the brake with a brake that kept its hold
    point otherwise than today's default, or gave way with the older give-way (none
    without them)."""
    braking = [r for r in recs if r["infeasible_steps"] > 0]
    fresh = [r for r in braking if hold_memory_of(r) == "fresh"]
    moving = [r for r in braking if hold_memory_of(r) == "moving"]
    rerun = [r for r in braking if r.get("ran_with", {}).get("brake_hold_memory")]
    out = []
    if rerun:
        codes = " / ".join(sorted({f"`{r['code_version']}`" for r in rerun}))
        out.append(f"{len(rerun)} of the episodes that reached the brake were run again at "
                   f"{codes} with `brake_hold_memory=0.1` (the brake keeps its hold point "
                   "across feasible gaps of up to 0.1 s while the obstacles stand still), "
                   "the default since; the others run identically under it "
                   "(`benchmarks/rerun_braking.py`).")
    if fresh or moving:
        parts = []
        if fresh:
            parts.append(f"{len(fresh)} took a fresh hold point at every engagement "
                         "(`brake_hold_memory=0`, or before the option existed)")
        if moving:
            parts.append(f"{len(moving)} kept it for 0.1 s also while an obstacle moved")
        out.append(f"**Caveat.** Of the episodes that reached the brake, {' and '.join(parts)}"
                   ": their brake is not today's default (the hold point kept for 0.1 s while "
                   "the obstacles stand still), and they have not been run again. With "
                   "nothing known, the fresh hold point had cost in 6 of the scenes' 137 "
                   "braking episodes where the kept one had none.")
    out += give_way_caveat(recs)
    return [" ".join(out), ""] if out else []
