"""A fidelity ladder for the tuner (issue 22, item 2): do cheaper simulations rank candidate
controllers like the plain problem that ``fosmc front`` reports on?

    .venv/bin/python tuning/fidelity.py                      # the realistic preset, 256 candidates
    .venv/bin/python tuning/fidelity.py --config tuning/configs/realistic_arm.toml unseen \\
        unseen_reference tuning/configs/arm_ideal_set2.toml  # tuning/results/fidelity.{json,md}

For each config (a TOML path, or ``unseen`` / ``unseen_reference``: the configs of
:data:`EXTRA`, built here from the realistic preset, on which nothing was tuned):

- the problems are built as ``fosmc front`` builds them: ``_config.tuning_problems(cfg)``, the
  plain problem (the config's ``[sim]``); each rung is the plain problem of a deep copy of the
  config with ``sim.dt`` and/or ``sim.t_final`` changed (and ``tune.train_dt`` /
  ``train_t_final`` cleared, which only the training problem reads);
- the candidates are the front's global stage at ``--seed`` (default 0, the front's):
  ``fs.global_factors(N, seed, fs.FrontSettings().grid_share)`` -> ``fs.from_factors(p0, z)`` (for N = 256:
  the start, a 6^3 grid of factors common to the joints, 39 per-joint draws), or with
  ``--candidates-from FILE`` the start and N - 1 of the points of a front.json or a reference.json
  (drawn without replacement at ``--seed``; all of them where it has fewer): the candidates near
  the best front known, where a surrogate's errors decide what a search keeps;
- rungs: dt / 2 (finer than the plain problem: its own discretization error, and the floor of
  every comparison); a digital loop (``controller.sample_period`` T > 0) dt = T / k, k in
  (1, 2, 5) (k RK4 steps per controller sample, the control held over the sample; the preset
  is k = 10); the ideal loop dt x 2 and x 5; every config the short horizon (plain dt,
  t_final = the cycloid's duration tau + 0.5 s: the reference's motion has ended) and the
  cheapest pair (dt = T, or dt x 2, with the short horizon); and the training step (dt = T, or
  the plain dt on an ideal loop) in float32 (``sim.precision``: AVX2 holds twice the lanes);
- every rung evaluates every candidate with a ``fs.Evaluator`` in chunks of 64 (the first
  chunk compiles; its time less the median warm chunk's is the compile time): mean metrics over
  each candidate's non-diverged rollouts, as the front's axes (mean over joints of
  ``rms_error`` and ``chattering_hf``).

Per rung, against the plain problem: the warm cost per candidate (median chunk / 64, with the
1-minute load average beside it: other jobs share the machine), Spearman's rho of each axis
over the candidates that diverged on neither problem, the largest and median relative
difference |rung - plain| / plain of each axis over the same candidates (and the largest over
the plain non-dominated ones, and the config's own parameters' difference), the candidates
whose ``chattering_hf`` agrees to 1e-9 (relative: the same held control sequence, up to
rounding), the diverged counts' agreement, and the non-dominated sets
(``fs.nondominated`` over every candidate): how many of the plain set stay non-dominated
on the rung, how many of the rung's are dominated on the plain problem, and the multiplicative
epsilon indicator ``fs.epsilon`` of the rung's non-dominated candidates, measured on the
plain problem, against the plain set (1: the plain set beats what the rung would pick nowhere;
1.05: somewhere by 5%).

Writes ``--out``.json (every number, per-candidate axes included) and ``--out``.md (one table per
config, the command and loads at the top). Progress lines go to stdout.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import time
import warnings
from pathlib import Path

import fosmc_jax

fosmc_jax.use_all_cores()  # every chunk split over every core, as `fosmc front` does
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from reference_front import params_of  # noqa: E402

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402
from fosmc_jax.io import jsonable, write_text  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PRESET = ROOT / "tuning" / "configs" / "realistic_arm.toml"
CHUNK = 64
#: dt = T / k for a digital loop (k RK4 steps per controller sample)
STEPS_PER_SAMPLE = (1, 2, 5)
#: dt x f for the ideal loop
DT_FACTORS = (2, 5)
#: the horizon rung: t_final = tau + HORIZON_MARGIN
HORIZON_MARGIN = 0.5


def _unseen(cfg: dict) -> dict:
    """The realistic preset at payloads 2 and 7 kg, a 2 kHz loop (T = 5e-4 s, dt = 5e-5 s: 10
    RK4 steps per sample as in the preset), a 2^20-count encoder and a 18 V limit."""
    cfg["plant"]["payloads"] = [2.0, 7.0]
    cfg["controller"]["sample_period"] = 5e-4
    cfg["sim"]["dt"] = 5e-5
    cfg["sensors"]["encoder_counts"] = [1_048_576] * 3
    cfg["actuator"]["u_max"] = [18.0, 18.0, 18.0]
    return cfg


def _unseen_reference(cfg: dict) -> dict:
    """:func:`_unseen` with another rest-to-rest cycloid (the only reference a config can set,
    ``[trajectory]``): other start and end angles (joint 3 moving back), tau = 1.5 s instead of
    2 s, and a 3 s horizon."""
    cfg = _unseen(cfg)
    cfg["trajectory"] = {"start": [-0.3, -1.2, 0.4], "end": [1.3, 0.3, -0.6], "duration": 1.5}
    cfg["sim"]["t_final"] = 3.0
    return cfg


#: Configs built here from the realistic preset (nothing was tuned on them): name -> edit.
EXTRA = {"unseen": _unseen, "unseen_reference": _unseen_reference}


def load_config(spec: str) -> tuple[str, dict, str]:
    """(name, resolved config, where it comes from) of a TOML path or an :data:`EXTRA` name."""
    if spec in EXTRA:
        cfg = EXTRA[spec](_config.load(PRESET).as_dict())
        return spec, _config.resolve(cfg), f"{PRESET.relative_to(ROOT)} edited by {EXTRA[spec].__name__}()"
    path = Path(spec)
    return path.stem, _config.load(path), str(path)


def rungs(cfg: dict) -> list[dict]:
    """The rungs of a config: name, dt, t_final (the plain problem first)."""
    dt, tf = cfg["sim"]["dt"], cfg["sim"]["t_final"]
    T_s = cfg["controller"]["sample_period"]
    short = cfg["trajectory"]["duration"] + HORIZON_MARGIN
    # a finer rung first: how far the plain problem itself is from its own limit (and the floor
    # of the comparisons: a switching loop's trajectory can part from a nearby one's)
    out = [{"name": "plain", "dt": dt, "t_final": tf}, {"name": "dt / 2 (finer)", "dt": dt / 2, "t_final": tf}]
    if T_s:
        for k in sorted(STEPS_PER_SAMPLE, reverse=True):
            if not np.isclose(T_s / k, dt, rtol=1e-9):
                out.append({"name": f"dt = T/{k}" if k > 1 else "dt = T", "dt": T_s / k, "t_final": tf})
        cheap = {"name": "dt = T, short horizon", "dt": T_s, "t_final": short}
    else:
        out += [{"name": f"dt x {f}", "dt": dt * f, "t_final": tf} for f in DT_FACTORS]
        cheap = {"name": f"dt x {DT_FACTORS[0]}, short horizon", "dt": dt * DT_FACTORS[0], "t_final": short}
    if short < tf:
        out.append({"name": f"short horizon ({short:g} s)", "dt": dt, "t_final": short})
        out.append(cheap)
    # the training step in float32: twice the SIMD lanes, if the quantized loop's ranks survive it
    train = {"name": "dt = T, float32", "dt": T_s} if T_s else {"name": "float32", "dt": dt}
    return out + [{**train, "t_final": tf, "precision": "float32"}]


def rung_config(cfg: dict, rung: dict) -> tuple[dict, list[str]]:
    """The resolved config of a rung, and the warnings resolving it gave (the integrator's
    stability limit)."""
    c = cfg.as_dict()
    c["sim"]["dt"], c["sim"]["t_final"] = rung["dt"], rung["t_final"]
    c["tune"]["train_dt"] = c["tune"]["train_t_final"] = 0.0
    c["sim"]["precision"] = rung.get("precision", c["sim"]["precision"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        c = _config.resolve(c)
    return c, [str(w.message) for w in caught]


def load_avg() -> float:
    return round(os.getloadavg()[0], 2)


def grid_size(n: int, grid_share: float, k: int = 3) -> int:
    """Values per axis of the grid over k parameters in ``fs.global_factors`` of size n (0 below
    n = 16): the front's own rule, which the library keeps private."""
    g = int((grid_share * n) ** (1 / k) + 1e-9) if n >= 16 else 0
    return g if 1 + g**k <= n else g - 1


def evaluate(problem: fs.Problem, params: fs.Params, n: int, log) -> tuple[dict, dict]:
    """Every candidate's mean metrics, chunk by chunk (chunks of :data:`CHUNK`), and the timing:
    compile time (first chunk less the median warm one), warm ms per candidate (median chunk),
    every chunk's seconds and the load average around them."""
    problem = fs.Evaluator(problem)  # compiled once, by the first chunk
    parts, times, loads = [], [], [load_avg()]
    for i in range(0, n, CHUNK):
        part = jax.tree.map(lambda x: x[i : i + CHUNK], params)
        t = time.perf_counter()
        parts.append(problem(part, CHUNK, log=lambda _: None))
        times.append(time.perf_counter() - t)
        loads.append(load_avg())
        log(f"    chunk {i // CHUNK + 1}/{-(-n // CHUNK)}  {times[-1]:6.2f} s  load {loads[-1]}")
    if len(times) == 1:  # one chunk: time it again warm
        t = time.perf_counter()
        problem(params, CHUNK, log=lambda _: None)
        times.append(time.perf_counter() - t)
        loads.append(load_avg())
    warm = statistics.median(times[1:])
    m = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    timing = {"compile_s": max(0.0, times[0] - warm), "ms_per_candidate": 1e3 * warm / CHUNK,
              "chunk_s": times, "load": loads}  # fmt: skip
    return m, timing


def _average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 0..n-1, tied values sharing the mean of their ranks (scipy.stats.rankdata's "average")."""
    r = np.empty(len(x))
    r[np.argsort(x, kind="stable")] = np.arange(len(x))
    _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    return (np.bincount(inverse, weights=r) / counts)[inverse]


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rho (average ranks for ties)."""
    if len(a) < 3:
        return float("nan")
    try:
        from scipy.stats import spearmanr
    except ImportError:  # numpy: Pearson's r of the average ranks
        return float(np.corrcoef(_average_ranks(a), _average_ranks(b))[0, 1])
    return float(spearmanr(a, b).statistic)


def compare(plain: dict, rung: dict) -> dict:
    """The rung's agreement with the plain problem (see the module docstring)."""
    (pe, pc), (re_, rc) = fs.axes(plain), fs.axes(rung)
    pd, rd = plain["diverged"], rung["diverged"]
    ok = (pd == 0) & (rd == 0) & np.isfinite(pe) & np.isfinite(re_)
    out = {"compared": int(ok.sum())}
    # the same held control to rounding: chattering_hf (the exact integral of the held control) equal
    chat_rel = np.abs(rc[ok] - pc[ok]) / np.abs(pc[ok])
    out["same_control"] = int(np.sum(chat_rel < 1e-9))
    for axis, p, r in (("rms_error", pe, re_), ("chattering_hf", pc, rc)):
        rel = np.abs(r[ok] - p[ok]) / np.abs(p[ok])
        worst = int(np.flatnonzero(ok)[np.argmax(rel)]) if rel.size else None
        out[axis] = {"spearman": spearman(p[ok], r[ok]),
                     "max_rel_diff": float(rel.max()) if rel.size else float("nan"),
                     "median_rel_diff": float(np.median(rel)) if rel.size else float("nan"),
                     "max_rel_diff_candidate": worst}  # fmt: skip
    front = np.flatnonzero(fs.nondominated(pe, pc) & ok)
    for axis, p, r in (("rms_error", pe, re_), ("chattering_hf", pc, rc)):
        rel = np.abs(r - p) / np.abs(p)
        out[axis]["plain_front_max_rel_diff"] = float(rel[front].max()) if front.size else float("nan")
        out[axis]["start_rel_diff"] = float(rel[0])  # candidate 0: the config's own parameters
    out["diverged"] = {"counts_agree": int(np.sum(pd == rd)), "plain_any": int(np.sum(pd > 0)),
                       "rung_any": int(np.sum(rd > 0)), "plain_only": int(np.sum((pd > 0) & (rd == 0))),
                       "rung_only": int(np.sum((pd == 0) & (rd > 0)))}  # fmt: skip
    nd_p, nd_r = fs.nondominated(pe, pc), fs.nondominated(re_, rc)
    picks = np.flatnonzero(nd_r & np.isfinite(pe) & np.isfinite(pc))  # the rung's picks, on the plain problem
    eps = fs.epsilon((pe[picks], pc[picks]), (pe[nd_p], pc[nd_p])) if picks.size else float("nan")
    out["front"] = {"plain_nondominated": int(nd_p.sum()), "rung_nondominated": int(nd_r.sum()),
                    "plain_kept": int(np.sum(nd_p & nd_r)), "rung_dominated_on_plain": int(np.sum(nd_r & ~nd_p)),
                    "epsilon_rung_picks_vs_plain": eps,
                    "plain_indices": np.flatnonzero(nd_p).tolist(), "rung_indices": np.flatnonzero(nd_r).tolist()}  # fmt: skip
    return out


def study(spec: str, n: int, seed: int, log, candidates_from: str | None = None) -> dict:
    name, cfg, source = load_config(spec)
    plain0, _, p0 = _config.tuning_problems(cfg)
    space = fs.space_of(p0)
    if candidates_from:  # the start (candidate 0, as in the global stage), then a front's points
        pts = json.loads(Path(candidates_from).read_text())["points"]
        pts = [pts[i] for i in np.random.default_rng(seed).permutation(len(pts))[: n - 1]]
        z = np.concatenate([np.zeros((1, 3 * len(p0))), fs.to_factors(p0, params_of(pts, p0))])
        n = len(z)
    else:
        z = fs.global_factors(n, seed, fs.FrontSettings().grid_share, space)
    T_s = cfg["controller"]["sample_period"]
    log(f"{name}: {source}; {cfg['plant']['payloads']} kg, T = {T_s} s, dt = {cfg['sim']['dt']} s, "
        f"t_final = {cfg['sim']['t_final']} s, {cfg['sim']['integrator']}; {n} candidates (seed {seed})")  # fmt: skip
    result = {"name": name, "source": source, "config": cfg.as_dict(), "candidates": n, "seed": seed,
              "candidates_from": candidates_from,
              "grid_per_axis": grid_size(n, fs.FrontSettings().grid_share, len(space.params)), "factors": z, "rungs": []}  # fmt: skip
    plain_m = None
    for rung in rungs(cfg):
        c, warned = rung_config(cfg, rung)
        problem, _, p_rung = (plain0, None, p0) if rung["name"] == "plain" else _config.tuning_problems(c)
        steps = problem.options["n_steps"]
        m_per = _config.sample_steps(c) if T_s else None
        log(f"  {name} / {rung['name']}: dt = {rung['dt']:g} s, t_final = {rung['t_final']:g} s, {steps} steps"
            + (f", m = {m_per}" if m_per else "") + "".join(f"\n    warning: {w}" for w in warned))  # fmt: skip
        t = time.perf_counter()
        m, timing = evaluate(problem, fs.from_factors(p_rung, z), n, log)  # p_rung: the rung's precision
        entry = {**rung, "steps": steps, "steps_per_sample": m_per, "warnings": warned, "timing": timing,
                 "axes": {"rms_error": fs.axes(m)[0], "chattering_hf": fs.axes(m)[1]}, "diverged": m["diverged"]}  # fmt: skip
        if plain_m is None:
            plain_m = m
        else:
            entry["vs_plain"] = compare(plain_m, m)
            v = entry["vs_plain"]
            log(f"    rho rms {v['rms_error']['spearman']:.4f}  rho chat {v['chattering_hf']['spearman']:.4f}  "
                f"front kept {v['front']['plain_kept']}/{v['front']['plain_nondominated']}  "
                f"{time.perf_counter() - t:.1f} s")  # fmt: skip
        log(f"    {timing['ms_per_candidate']:.2f} ms per candidate warm (compile {timing['compile_s']:.1f} s)")
        result["rungs"].append(entry)
    base = result["rungs"][0]["timing"]["ms_per_candidate"]
    for r in result["rungs"]:
        r["timing"]["cost_vs_plain"] = r["timing"]["ms_per_candidate"] / base
        r["steps_vs_plain"] = r["steps"] / result["rungs"][0]["steps"]
    return result


# ---------------------------------------------------------------------------- report


def _f(x, fmt: str = ".3g") -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, fmt)


def _ranks_like_plain(v: dict) -> bool:
    rho = min(v["rms_error"]["spearman"], v["chattering_hf"]["spearman"])
    return bool(rho >= 0.99 and v["front"]["plain_kept"] == v["front"]["plain_nondominated"])


def markdown(results: list[dict], command: str, meta: dict) -> str:
    lines = [
        "# Fidelity ladder for the tuner (issue 22, item 2)",
        "",
        f"    {command}",
        "",
        f"Commit {meta['commit']}; {meta['devices']} CPU devices; load average (1 min) {meta['load'][0]} at the "
        f"start, {meta['load'][1]} at the end; {meta['wall_s']:.0f} s in all. Written by `tuning/fidelity.py` "
        "(its docstring defines every column).",
        "",
        (
            f"Candidates: the start and {results[0]['candidates'] - 1} points drawn (seed {results[0]['seed']}) from "
            f"`{results[0]['candidates_from']}`; "
            if results[0].get("candidates_from")
            else "Candidates: the front's global stage (`fosmc_jax.search.global_factors` with the front's grid share, seed "
            f"{results[0]['seed']}): for N = 256 the start, a 6^3 grid of factors common to the joints and 39 per-joint "
            "draws; "
        )
        + "the same N and each config's own horizon for every config (nothing reduced). Rank and relative-difference columns: over the candidates that diverged on neither problem "
        "(`compared`). Relative differences of the short-horizon rungs measure a different quantity "
        "(the metrics over the first tau + 0.5 s), not an integration error: only their ranks matter. "
        "Same control: of those, the candidates whose chattering_hf (the exact integral of the held control) "
        "agrees to 1e-9, i.e. the same control sequence up to rounding. Rel. diff on the plain front: the largest "
        "over the plain problem's non-dominated candidates; the config's parameters: candidate 0, the start "
        "(what `fosmc simulate` reports for the config). Diverged: candidates whose number of "
        "diverged rollouts agrees, and those with a diverged rollout on one problem only. Plain front kept: of the "
        "plain problem's non-dominated candidates (`fosmc_jax.search.nondominated` over every candidate), those "
        "non-dominated on the rung; rung front dominated on plain: the rung's non-dominated candidates dominated "
        "on the plain problem; epsilon: `fosmc_jax.search.epsilon` of the rung's non-dominated candidates, measured on the "
        "plain problem, against the plain set (1: nowhere worse). The rung `dt / 2 (finer)` is the plain problem's "
        "own discretization error and the floor of every comparison. The reference is the config's "
        "`[trajectory]` cycloid (the only reference a config sets; the TOML files keep the paper's, tau = 2 s), "
        "so the short horizon is tau + 0.5 s. "
        "Cost: warm ms per candidate (median chunk of 64 / 64), the median load average during that rung beside "
        "it (2 cores shared with other jobs: compare costs within a config, roughly).",
    ]
    for res in results:
        cfg = res["config"]
        lines += ["", f"## {res['name']}", "",
                  f"{res['source']}: payloads {cfg['plant']['payloads']} kg, T = {cfg['controller']['sample_period']} s, "
                  f"dt = {cfg['sim']['dt']} s, {cfg['sim']['integrator']}, t_final = {cfg['sim']['t_final']} s, "
                  f"cycloid tau = {cfg['trajectory']['duration']} s; {res['candidates']} candidates.", "",
                  "| rung | dt (s) | m | t_final (s) | steps | ms / cand. (load) | cost / plain | rho rms_error | "
                  "rho chattering_hf | compared | same control | rms_error rel. diff max / median | chattering_hf rel. diff max / "
                  "median | rel. diff on the plain front: rms / chat. max | the config's parameters: rel. diff rms / chat. | diverged: counts agree, plain-only, rung-only | plain front kept | rung front dominated "
                  "on plain | epsilon of rung picks |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
        for r in res["rungs"]:
            t = r["timing"]
            load = statistics.median(t["load"])
            head = (f"| {r['name']} | {r['dt']:g} | {r['steps_per_sample'] or '-'} | {r['t_final']:g} | {r['steps']:,} | "
                    f"{t['ms_per_candidate']:.2f} ({load:.1f}) | {t['cost_vs_plain']:.2f} |")  # fmt: skip
            if "vs_plain" not in r:
                div = int(np.sum(np.asarray(r["diverged"]) > 0))
                lines.append(head + f" 1 | 1 | {res['candidates'] - div} | - | 0 | 0 | 0 | 0 | {div} diverged | "
                             f"{int(fs.nondominated(r['axes']['rms_error'], r['axes']['chattering_hf']).sum())} points | - | 1 |")  # fmt: skip
                continue
            v = r["vs_plain"]
            e, c, d, fr = v["rms_error"], v["chattering_hf"], v["diverged"], v["front"]
            lines.append(head + f" {_f(e['spearman'], '.4f')} | {_f(c['spearman'], '.4f')} | {v['compared']} | {v['same_control']} | "
                         f"{_f(e['max_rel_diff'])} / {_f(e['median_rel_diff'])} | "
                         f"{_f(c['max_rel_diff'])} / {_f(c['median_rel_diff'])} | "
                         f"{_f(e['plain_front_max_rel_diff'])} / {_f(c['plain_front_max_rel_diff'])} | "
                         f"{_f(e['start_rel_diff'])} / {_f(c['start_rel_diff'])} | "
                         f"{d['counts_agree']}/{res['candidates']}, {d['plain_only']}, {d['rung_only']} | "
                         f"{fr['plain_kept']}/{fr['plain_nondominated']} | "
                         f"{fr['rung_dominated_on_plain']}/{fr['rung_nondominated']} | "
                         f"{_f(fr['epsilon_rung_picks_vs_plain'], '.4f')} |")  # fmt: skip
        good = [r["name"] for r in res["rungs"][1:] if _ranks_like_plain(r["vs_plain"])]
        lines += ["", "Rungs with Spearman's rho >= 0.99 on both axes and every plain non-dominated candidate kept: "
                  + (", ".join(f"`{g}`" for g in good) or "none") + "."]  # fmt: skip
        warned = [(r["name"], w) for r in res["rungs"] for w in r["warnings"]]
        if warned:
            lines += [""] + [f"- {name}: config warning: {w}" for name, w in warned]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", nargs="+", action="extend",
                    help=f"TOML paths or {', '.join(EXTRA)} (repeatable; default the realistic preset)")  # fmt: skip
    ap.add_argument("--n", type=int, default=256, help="candidates per config (default 256)")
    ap.add_argument("--seed", type=int, default=0, help="the global stage's seed (default 0, the front's)")
    ap.add_argument("--candidates-from", metavar="FILE",
                    help="the start and N - 1 points of a front.json or reference.json as the candidates")  # fmt: skip
    ap.add_argument("--out", default=str(ROOT / "tuning" / "results" / "fidelity"),
                    help="output stem: STEM.json and STEM.md (default tuning/results/fidelity)")  # fmt: skip
    args = ap.parse_args(argv)
    configs = args.config or [str(PRESET.relative_to(ROOT))]
    argv = sys.argv[1:] if argv is None else argv
    command = ".venv/bin/python tuning/fidelity.py" + ("" if not argv else " " + shlex.join(argv))
    t0, load0 = time.perf_counter(), load_avg()
    log = lambda s: print(f"[{time.perf_counter() - t0:6.1f} s] {s}", flush=True)
    results = [study(spec, args.n, args.seed, log, args.candidates_from) for spec in configs]
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True).stdout.strip() or "unknown"  # fmt: skip
    except OSError:
        commit = "unknown"
    meta = {"command": command, "commit": commit, "devices": len(jax.local_devices()),
            "load": [load0, load_avg()], "wall_s": time.perf_counter() - t0}  # fmt: skip
    out = Path(args.out)
    write_text(out.with_suffix(".json"), json.dumps(jsonable({"meta": meta, "configs": results}), indent=1))
    write_text(out.with_suffix(".md"), markdown(results, command, meta))
    log(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
