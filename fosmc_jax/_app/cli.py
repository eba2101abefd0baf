"""The ``fosmc`` command line: parses arguments, calls the ``run_<command>`` functions of
:mod:`fosmc_jax._app.commands` (which do the work and return the data), prints, and maps
:class:`ConfigError` to ``fosmc: error: ...`` and exit status 2. No numerics here."""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import sys
import time
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path

import jax
import numpy as np

from .. import _problems as problems
from .._controllers.kind import load_entry_points
from .._design import paper as _paper
from .._design.gains import CONVENTIONS
from .._io import VERSIONS_KEY, atomic_write, jsonable, stamped_arrays
from .._simulator import sharding
from .._simulator.metrics import METRIC_NAMES, PERCENTILES, UNITS
from . import commands, distributed

_IMPORTED = time.perf_counter()  # process_start's fallback


def process_start() -> float:
    """This process's start as a ``time.perf_counter()`` value (from /proc on Linux; elsewhere
    the import of this module, after Python's start and the package's imports): the CLI's
    budgets count from it, as a user's stopwatch does."""
    try:
        ticks = int(open("/proc/self/stat").read().rsplit(")", 1)[1].split()[19])
        uptime = float(open("/proc/uptime").read().split()[0])
        age = uptime - ticks / os.sysconf("SC_CLK_TCK")
        if 0 <= age < time.perf_counter() - _IMPORTED + 600:  # a sane age (a container's /proc may lie)
            return time.perf_counter() - age
    except (OSError, ValueError, IndexError, AttributeError):
        pass
    return _IMPORTED


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------- simulate


def cmd_simulate(args) -> int:
    """Per-rollout metrics and the batch's summary; for a Monte-Carlo batch (a ``[sample]``
    table) the summary with percentiles, and ``--plot`` draws histograms instead of traces.
    ``--npz`` and ``--plot`` are checked (writable, a figure format) before the simulation.
    The rollouts are printed from their arrays as they are formatted (no Python object per
    rollout held: a batch run in chunks prints as much as memory holds)."""
    across = _processes(args)
    with distributed.agreeing(jax.process_count() > 1) as agree:  # a refusal here ends every process in one line
        sampled = commands.config_of(args.config).sample.count > 0
        if args.plot:
            from .plots import check_figure_path

            try:
                check_figure_path(args.plot)
            except ValueError as e:
                raise problems.ConfigError(f"--plot: {e}") from None
        for option, path in (("--npz", args.npz), ("--plot", args.plot)):
            if path and sharding.leads():  # process 0 alone writes
                commands.writable(path, option)
        agree(bytes(32))
    devices = None if distributed.Processes(**across).asked else args.devices  # per process: its own count
    r = commands.run_simulate(args.config, params=args.params, point=args.point, devices=devices,
                              keep_trace=bool(args.plot) and not sampled, records=False, draws=args.json,
                              chunk=args.chunk, checkpoint=args.checkpoint, resume=args.resume, log=_log,
                              **across)  # fmt: skip
    if not sharding.leads():  # process 0 alone prints and writes
        return 0
    cfg, summary, index = problems.as_config(r["config"]), r["summary"], r["arrays"]
    n = len(index["plant_index"])
    title = (f"{cfg.controller.kind}, {cfg.controller.switching} switching, "
             f"{cfg.sim.integrator} dt = {cfg.sim.dt} s")  # fmt: skip
    if args.plot and sampled:
        from .plots import plot_histograms

        plot_histograms(r["arrays"], ("rms_error", "chattering_hf"), UNITS, args.plot, title=title)
        _log(f"fosmc: wrote {args.plot}")
    elif args.plot:
        from .plots import plot_rollouts

        shown = min(n, 12)
        tr = r.pop("trace")
        pairs = zip(index["plant_index"][:shown], index["offset_index"][:shown])
        labels = [f"plant {p}, offset {o}" for p, o in pairs]
        plot_rollouts(np.asarray(tr.t[0]), tr.X[:shown], tr.X_d[:shown], tr.U[:shown], labels, args.plot, title=title)
        _log(f"fosmc: wrote {args.plot}")
    if args.npz:

        def write(tmp):
            with open(tmp, "wb") as f:  # a file object: np.savez would add ".npz" to a name
                np.savez(f, **stamped_arrays(r["arrays"]))

        atomic_write(args.npz, write)
        _log(f"fosmc: wrote {args.npz}")
    if args.json:
        for part in _simulate_json_parts(r):
            sys.stdout.write(part)
        sys.stdout.write("\n")
    else:
        if not (args.npz or sampled):
            _print_rollouts(commands.rollout_records(r["arrays"]))
        if n > 1 or args.npz:  # with --npz (or a sample) the summary is all that is printed
            print(f"batch of {n}: {summary['diverged_excluded']} diverged (excluded below)")
            for name in METRIC_NAMES:
                print(f"  {name:<19} mean {_fmt3(summary['mean'][name])}   max {_fmt3(summary['max'][name])}")
                if sampled:
                    print(" " * 21 + "   ".join(f"p{q} {_fmt3(summary[f'p{q}'][name])}" for q in PERCENTILES))
    return 0


def _simulate_json(r: dict) -> str:
    """``fosmc simulate --json`` from ``run_simulate(records=False)``, as one string
    (:func:`_simulate_json_parts`, joined)."""
    return "".join(_simulate_json_parts(r))


def _simulate_json_parts(r: dict, block: int = 10_000) -> Iterator[str]:
    """``fosmc simulate --json`` from ``run_simulate(records=False)``, in parts to write one
    after the other: its records (``rollout_records``), one per line, ``block`` rollouts per
    part (so that a batch of 10^7 never holds its text at once), written by json's C encoder
    from one ``tolist`` per array and block (records of NumPy rows through ``jsonable`` and an
    indented dump cost more than the simulation: BENCHMARKS.md, "Figures behind the code").
    Non-finite numbers become null, as ``jsonable`` makes them (the records hold only
    numbers and booleans, so the tokens cannot be in a string). The versions (``"fosmc_jax"``,
    from ``run_simulate``) come first, the rollouts next."""
    head = f' "{VERSIONS_KEY}": {json.dumps(r[VERSIONS_KEY])},\n' if VERSIONS_KEY in r else ""
    yield "{\n" + head + ' "rollouts": [\n  '
    arrays = r["arrays"]
    for start in range(0, len(arrays["diverged"]), block):
        records = commands.rollout_records({k: v[start : start + block].tolist() for k, v in arrays.items()})
        rows = ",\n  ".join(json.dumps(x) for x in records)
        if "NaN" in rows or "Infinity" in rows:
            rows = re.sub(r"-?Infinity|NaN", "null", rows)
        yield rows if start == 0 else ",\n  " + rows
    rest = json.dumps(jsonable({k: v for k, v in r.items() if k not in ("arrays", "trace", VERSIONS_KEY)}), indent=1)
    yield "\n ]," + rest[1:]


def _print_rollouts(rollouts: Iterable[dict]) -> None:
    head = f"{'rollout':>7} {'plant':>5} {'offset':>6} {'diverged':>8}  {'metric':<16} " + " ".join(
        f"{j:>11}" for j in ("joint 1", "joint 2", "joint 3")
    )
    print(head)
    for i, r in enumerate(rollouts):
        for k, name in enumerate(METRIC_NAMES):
            lead = (
                f"{i:>7} {r['plant_index']:>5} {r['offset_index']:>6} {str(r['diverged']):>8}" if k == 0 else " " * 29
            )
            vals = " ".join(f"{v:>11.4e}" for v in r["metrics"][name])
            print(f"{lead}  {name + ' (' + UNITS[name] + ')':<26}{vals}")


def _fmt3(v) -> str:
    return " ".join(f"{x:.4e}" for x in v)


# ---------------------------------------------------------------------------- bounds


def cmd_bounds(args) -> int:
    start = time.perf_counter()
    d = commands.run_bounds(args.config, log=_log)
    elapsed = time.perf_counter() - start
    if args.json:
        print(json.dumps(jsonable(d), indent=1))
        return 0
    gamma = d["gamma"]
    fmt = lambda v: "  ".join(f"{x:10.4f}" for x in np.ravel(v))
    hint = "; [model] from = 'arm' designs on the arm's" if "models" in d and d["model"] == "paper" else ""
    print(f"model: {d['model']} (K, CB and the bounds below: {d['model_detail']}{hint})")
    if "box" in d:
        a_rows, b_rows, box = d["nominal_A_rows"], d["nominal_B_rows"], [d["box"][k] for k in problems.BOX_KEYS]
        print(f"The arm's box ({d['arm_model']}) beside the paper's Appendix box")
        print("and nominal (29); rows 3, 6, 9 of A (columns 1-9) and B (columns 1-3):")
        print(f"  {'entry':<8}{'arm lower':>11}{'arm upper':>11}{'arm nominal':>12}   "
              f"{'paper lower':>11}{'paper upper':>12}{'paper (29)':>11}")  # fmt: skip
        paper_box = (_paper.A_LOWER, _paper.A_UPPER, _paper.B_LOWER, _paper.B_UPPER)
        for m, nom, pnom, (lo_, hi_), (plo, phi) in (
            ("A", a_rows, _paper.A_ROWS, box[:2], paper_box[:2]),
            ("B", b_rows, _paper.B_ROWS, box[2:], paper_box[2:]),
        ):
            for i in range(3):
                for j in range(nom.shape[1]):
                    arm_cols = f"{lo_[i, j]:11.3f}{hi_[i, j]:11.3f}{nom[i, j]:12.3f}"
                    paper_cols = f"{plo[i, j]:11.3f}{phi[i, j]:12.3f}{pnom[i, j]:11.3f}"
                    print(f"  {m}({3 * i + 3},{j + 1})".ljust(10) + arm_cols + "   " + paper_cols)
    checked = d["vertices_checked"]
    print(f"alpha = max ||B_bar^-1 dA_r||_2 over {checked['A']} box vertices = {d['alpha']:.4f}"
          f"   (paper (31): {_paper.ALPHA_PRINTED})")  # fmt: skip
    print(f"beta  = max ||B_bar^-1 dB_r||_2 over {checked['B']} box vertices = {d['beta']:.4f}"
          f"   (paper (31): {_paper.BETA_PRINTED})")  # fmt: skip
    print(f"({elapsed:.1f} s)\nK (3x9), placing the poles exactly (A + BK, (16)):")
    for row in d["K"]:
        print("  " + "  ".join(f"{x:9.4f}" for x in row))
    poles = [complex(re, im) for re, im in d["closed_loop_poles"]]
    print("eig(A + BK): " + ", ".join(f"{z.real:.4g}" + (f"{z.imag:+.3g}j" if z.imag else "") for z in poles))
    print("CB:")
    for row in d["CB"]:
        print("  " + fmt(row))
    s = np.linalg.svd(d["CB"], compute_uv=False)
    print(f"singular values of CB: {fmt(s)}")
    print("gamma lower bounds (24)-(26):")
    print(f"  {'spectral (all 2-norms)':<34}{fmt(d['gamma_min']['spectral'])}")
    print(f"  {'paper (||CB|| = sigma_min(CB))':<34}{fmt(d['gamma_min']['paper'])}")
    print(f"  {'printed in the paper, (35)':<34}{fmt(_paper.GAMMA_MIN_PRINTED)}")
    print(f"  {'gamma in use':<34}{fmt(gamma)}")
    for c in CONVENTIONS:
        ok = np.all(np.asarray(gamma) > d["gamma_min"][c])
        print(f"  gamma {'meets' if ok else 'does NOT meet'} the {c} bounds")
    if "models" in d:
        _print_both_models(d, fmt)
    return 0


def _print_both_models(d: dict, fmt) -> None:
    """An arm config's paper and arm models side by side, and the K of the one not in use."""
    models, other = d["models"], "arm" if d["model"] == "paper" else "paper"
    print(f"both design models (in use: {d['model']}):")
    print(f"  {'model':<34}{'paper':>10}{'':<26}{'arm':>10}")
    cells = {source: {"alpha": [m["alpha"]], "beta": [m["beta"]],
                      **{f"gamma lower bounds, {c}": m["gamma_min"][c] for c in CONVENTIONS}}
             for source, m in models.items()}  # fmt: skip
    for label in cells["paper"]:
        print(f"  {label:<34}{fmt(cells['paper'][label]):<36}{fmt(cells['arm'][label])}")
    print(f"K of the {other} model (3x9; not the controller's):")
    for row in models[other]["K"]:
        print("  " + "  ".join(f"{x:9.4f}" for x in row))


# ---------------------------------------------------------------------------- reproduce


def cmd_reproduce(args) -> int:
    start = time.perf_counter()
    r = commands.run_reproduce(args.out, plant=args.plant, t_final=args.t_final, dt=args.dt, integrator=args.integrator,
                               force=args.force, report=args.report, log=_log)  # fmt: skip
    print(r["files"]["metrics.md"])
    _log(f"fosmc reproduce: wrote {', '.join(list(r['files']) + r['figures'])} to {args.out}/ "
         f"in {time.perf_counter() - start:.1f} s (total wall time)")  # fmt: skip
    return 0


# ---------------------------------------------------------------------------- tune


def cmd_tune(args) -> int:
    """The objective's two metrics with their units, initial and final, then the chattering
    measure the objective does not use (total variation or ``chattering_hf``), labelled so."""
    r = commands.run_tune(args.config, steps=args.steps, out=args.out, resume=args.resume, force=args.force,
                          budget=args.budget, started=process_start(), log=_log, **_processes(args))  # fmt: skip
    if not sharding.leads():  # process 0 alone prints
        return 0
    optimised = (r["objective"]["error_metric"], r["objective"]["chattering_metric"])
    rows = [(name, commands.metric_label(name)) for name in optimised]
    rows += [(name, commands.metric_label(name) + ", not in the objective")
             for name in ("chattering_hf", "chattering") if name not in optimised]  # fmt: skip
    width = max(len(label) for _, label in rows)
    for name, label in rows:
        initial, final = (_fmt3(r[k]["metrics"][name]) for k in ("initial", "final"))
        print(f"{label:<{width}}  initial {initial}   final {final}")
    return 0


# ---------------------------------------------------------------------------- front


def cmd_front(args) -> int:
    from .._search.front import AXES

    start = process_start()
    result = commands.run_front(args.config, out=args.out, points=args.points, budget=args.budget,
                                candidates=args.candidates, steps=args.steps, seed=args.seed,
                                gradient_share=args.gradient_share, gradient_on=args.gradient_on,
                                plain_share=args.plain_share, search=args.search,
                                population=args.population,
                                generations=args.generations, compare=tuple(args.compare), force=args.force,
                                resume=args.resume, replay=args.replay, started=start, log=_log,
                                **_processes(args))  # fmt: skip
    if not sharding.leads():
        return 0
    _log(
        f"front: {len(result['points'])} points in {time.perf_counter() - start:.1f} s (wall time from the process's "
        "start)"
    )
    for i, pt in enumerate(result["points"]):
        e, c = (float(np.mean(pt["metrics"][k])) for k in AXES)
        print(f"point {i:3d}  {AXES[0]} {e:.4e} rad  {AXES[1]} {c:.4e} V  diverged {pt['diverged']}")
    return 0


def _processes(args) -> dict:
    """The options that join a command's process to the others (``run_*``'s keywords)."""
    return {"distributed": args.distributed, "coordinator": args.coordinator, "num_processes": args.num_processes,
            "process_id": args.process_id, "join_timeout": args.join_timeout}  # fmt: skip


def _add_processes(p: argparse.ArgumentParser) -> None:
    """The options of a command run as several processes (docs/performance.md)."""
    g = p.add_argument_group("across processes (jax.distributed; every process runs the same command)")
    g.add_argument("--distributed", action="store_true",
                   help="join the other processes of a SLURM or Open MPI job (jax.distributed.initialize)")  # fmt: skip
    g.add_argument("--coordinator", metavar="HOST:PORT", help="process 0's host and a free port on it")
    g.add_argument("--num-processes", type=int, metavar="N", help="with --coordinator: the number of processes")
    g.add_argument("--process-id", type=int, metavar="I", help="with --coordinator: this process's index, 0 to N-1")
    g.add_argument("--join-timeout", type=float, default=distributed.JOIN_TIMEOUT_S, metavar="S",
                   help=f"seconds for every process to join (default {distributed.JOIN_TIMEOUT_S:g})")  # fmt: skip


# ---------------------------------------------------------------------------- select


def cmd_select(args) -> int:
    from .._search.front import AXES
    from .._search.select import controller_toml, select

    try:
        r = select(args.front, max_error=args.max_error, max_chattering=args.max_chattering,
                   held_out=False if args.training_only else None)  # fmt: skip
        toml = controller_toml(r["params"])
    except ValueError as e:
        raise problems.ConfigError(str(e)) from None
    if args.json:
        print(json.dumps(jsonable(r), indent=1))
        return 0
    bounded, bound = (AXES[0], args.max_error) if args.max_error is not None else (AXES[1], args.max_chattering)
    other = AXES[1 - AXES.index(bounded)]
    print(f"point {r['index']}: the least mean {other} with mean {bounded} <= {bound:g} {UNITS[bounded]} "
          f"(judged on {r['judged_on']})")  # fmt: skip
    for k in AXES:
        held = (
            f"  (training {r['training_mean'][k]:.4e}, held-out {r['held_out_mean'][k]:.4e})"
            if "held_out_mean" in r
            else ""
        )
        print(f"  mean {k:<14} {r['mean'][k]:.4e} {UNITS[k]}{held}")
    print(f"# point {r['index']} of {args.front}, for the config's [controller] table:\n{toml}")
    return 0


# ---------------------------------------------------------------------------- certify


def cmd_certify(args) -> int:
    r = commands.run_certify(args.config, vertices=args.vertices, configured_switching=args.configured_switching,
                             seed=args.seed, log=_log)  # fmt: skip
    if args.json:
        print(json.dumps(jsonable(r), indent=1))
        return 0
    w = r["where"]
    print(f"hitting condition (20): max s^T s'/||s|| = {r['max_hitting']:.4g} -> "
          f"{'HOLDS' if r['holds'] else 'VIOLATED'} at all {r['points_checked']:.4g} points checked")  # fmt: skip
    print(f"  plants: {r['vertices']}; evaluations: {r['evaluations']}")
    for k, v in r["envelope"].items():
        print(f"  {k}: {v}")
    where = f", payload {w['payload']:g} kg" if "payload" in w else f", vertex code {w['vertex_code']}"
    print(f"  worst at t = {w['t']:.4g} s, s = {np.round(w['s'], 4).tolist()}, "
          f"||Z|| = {np.linalg.norm(w['Z']):.4g}{where}")  # fmt: skip
    g = r["gamma_bounds"]
    print(f"gamma bounds (24)-(26), alpha = {g['alpha']:.4f}, beta = {g['beta']:.4f}, "
          f"checked at (1 +- {g['eps']}) x bound:")  # fmt: skip
    for c in g["conventions"]:
        print(f"  {c['convention']:<9} bound {np.round(c['bound'], 3).tolist()}: {c['verdict']} in this example "
              f"(max at +eps {c['max_hitting_above']:.4g}, at -eps {c['max_hitting_below']:.4g})")  # fmt: skip
    return 0


# ---------------------------------------------------------------------------- export


def cmd_export(args) -> int:
    r = commands.run_export(args.config, out=args.out, params=args.params, point=args.point, precision=args.precision,
                            name=args.name, log=_log)  # fmt: skip
    print(f"{r['kind']} controller ({r['precision']}): {', '.join(map(str, r['paths']))}")
    if not r["check"].startswith("compiled cleanly"):
        _log(f"fosmc: warning: {r['check']}")
    return 0


# ---------------------------------------------------------------------------- identify


def cmd_identify(args) -> int:
    """Each entry's configured and identified value with its standard deviation and status, the
    directions the log does not identify, the fit's residuals; the files written."""
    r = commands.run_identify(args.config, data=args.data, params=args.params, out=args.out, payload=args.payload,
                              delay=args.delay, window=args.window, dt=args.dt, threshold=args.threshold,
                              iterations=args.iterations, bootstrap=args.bootstrap, force=args.force,
                              log=_log)  # fmt: skip
    if args.json:
        print(json.dumps(jsonable({k: v for k, v in r.items() if k != "config"}), indent=1))
        return 0
    print(f"{'entry':<10} {'configured':>12} {'identified':>12} {'+- std':>10} {'relative':>9}  status")
    for e in r["entries"]:
        std = "" if e["std"] is None else f"{e['std']:10.3g} {100 * e['relative_std']:8.2g}%"
        print(f"{e['name']:<10} {e['initial']:12.6g} {e['estimate']:12.6g} {std:>20}  {e['status']}")
    if r["groups"]:
        print(f"not identified by the log (relative standard deviation above {r['fit']['threshold']:g}); each fixed "
              "entry with the moves (of log p) that leave the log unchanged:")  # fmt: skip
        for g in r["groups"]:
            moves = ", ".join(f"{name} {w:+.3g}" for name, w in g["moves"].items())
            print(f"  {g['fixed']:<10} {moves}")
    fit = r["fit"]
    currents = "" if fit["rms_current"] is None else f", {_fmt3(fit['rms_current'])} A"
    print(f"fit: {fit['windows']} windows of {fit['window_s']:g} s, {fit['iterations']} iterations; residual RMS "
          f"{_fmt3(fit['rms_theta'])} rad{currents}")  # fmt: skip
    if r["config_check"] != "ok":
        _log(f"fosmc: warning: the identified arm is not a valid config: {r['config_check']}")
    if args.out:
        print(f"wrote {args.out}/identified.toml and {args.out}/identify.json")
    return 0


# ---------------------------------------------------------------------------- main


class _Parser(argparse.ArgumentParser):
    """argparse's parser with its errors in the form of the config's: one line ``fosmc: error:
    <option>: <what is wrong>`` on stderr and exit status 2, without the usage block."""

    def error(self, message: str):
        self.exit(2, f"fosmc: error: {_option_first(message)}\n")


#: argparse's error messages, rewritten to name the option first: (pattern, replacement).
_ARGPARSE_ERRORS = (
    (r"argument (\S+?)(?:/\S+)?: (.*)", r"\1: \2"),
    (r"the following arguments are required: (.*)", r"\1: required"),
    (r"unrecognized arguments: (.*)", r"\1: not an option of this command (fosmc <command> --help lists them)"),
    (r"one of the arguments (.*) is required", r"\1: one of them is required"),
    (r"ambiguous option: (\S+) could match (.*)", r"\1: ambiguous, could be \2"),
)


def _option_first(message: str) -> str:
    for pattern, replacement in _ARGPARSE_ERRORS:
        if re.fullmatch(pattern, message, flags=re.S):
            return re.sub(pattern, replacement, message, flags=re.S)
    return message


def parser() -> argparse.ArgumentParser:
    """The command line's parser: every command and option with its help. Its length is that
    table, one option after the other, as ``fosmc <command> --help`` lists them."""
    p = _Parser(prog="fosmc", description="FOSMC tracking controller simulator (JAX)")
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("simulate", help="simulate the closed loop; print metrics per rollout")
    s.add_argument("--config", help="TOML config (default: the paper's setup)")
    s.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    s.add_argument("--plot", metavar="PNG", help="write a figure of the rollouts")
    s.add_argument(
        "--npz",
        metavar="FILE",
        help="write every rollout's metrics as NumPy arrays (one (N, 3) array per metric, diverged, diverged_at, "
        "plant_index, offset_index, realization_index) and print only the batch summary",
    )
    s.add_argument(
        "--params",
        metavar="JSON",
        help="use the tuned parameters of the config's controller kind (delta, gamma, poles; k, phi; k1, k2) "
        "from a `fosmc tune` result.json or a `fosmc front` front.json",
    )
    s.add_argument("--point", type=int, help="with a front.json: the point to re-run (index)")
    s.add_argument(
        "--chunk",
        type=int,
        metavar="N",
        help="run the batch in chunks of at most N rollouts (default: as many as memory holds)",
    )
    s.add_argument(
        "--checkpoint",
        metavar="DIR",
        help="write each finished chunk (at most 65536 rollouts) to DIR, a new or empty folder",
    )
    s.add_argument(
        "--resume", action="store_true", help="with --checkpoint: continue the run in DIR from its last finished chunk"
    )
    s.add_argument(
        "--devices",
        type=int,
        help="split the batch over N devices (default: every core, or the count set in "
        "JAX_NUM_CPU_DEVICES / XLA_FLAGS; 1 turns sharding off)",
    )
    _add_processes(s)
    s.set_defaults(func=cmd_simulate)
    b = sub.add_parser("bounds", help="alpha, beta (31), K (16), gamma bounds (24)-(26)")
    b.add_argument("--config", help="TOML config (default: the paper's setup)")
    b.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    b.set_defaults(func=cmd_bounds)
    r = sub.add_parser("reproduce", help="the paper's Figs. 2-5, extra figures and metric tables")
    r.add_argument("--out", default="out/reproduction", help="output folder (default: out/reproduction)")
    r.add_argument("--plant", choices=("arm", "linear"), default="arm", help="plant for Figs. 2-5")
    r.add_argument("--force", action="store_true", help="overwrite a non-empty --out")
    r.add_argument("--report", metavar="MD", help="also update the generated blocks of this report")
    r.add_argument("--t-final", type=float, default=4.0, help="horizon (s), default 4")
    r.add_argument("--dt", type=float, default=1e-4, help="step (s), default 1e-4")
    r.add_argument("--integrator", choices=("euler", "rk4"), default="rk4")
    r.set_defaults(func=cmd_reproduce)
    f = sub.add_parser("front", help="Pareto front of tracking error against chattering (any controller kind)")
    f.add_argument("--config", help="TOML config (default: the paper's setup)")
    f.add_argument("--out", default="out/front", help="output folder (default: out/front)")
    f.add_argument("--points", type=int, help="parents per local round (default 8)")
    f.add_argument("--budget", type=float, default=300.0, help="wall time, s (default 300)")
    f.add_argument(
        "--candidates", type=int, help="global stage size: start, log grid, per-joint draws (default: from the budget)"
    )
    f.add_argument("--steps", type=int, help="local rounds around the non-dominated set (default: from the budget)")
    f.add_argument("--search", choices=("nsga2", "staged"),
                   help="the derivative-free search: pymoo's NSGA-II, or global stage, CMA-ES and local rounds "
                   "(default: staged with --candidates or --steps, else nsga2)")  # fmt: skip
    f.add_argument("--population", type=int, default=256, help="NSGA-II's population (default 256)")
    f.add_argument("--generations", type=int, help="NSGA-II's generations (default: from the budget)")
    f.add_argument("--seed", type=int, default=0, help="seed of the search's draws (default 0)")
    f.add_argument("--gradient-share", type=float, default=0.25, metavar="X",
                   help="share of the search time spent last on gradient steps refining the front's points "
                   "(with a budget; default 0.25; 0: none)")  # fmt: skip
    f.add_argument("--plain-share", type=float, default=0.25, metavar="X",
                   help="with a training surrogate, share of the search time the gradient steps leave that goes to "
                   "local rounds on the plain problem around the training front (with a budget; default 0.25; "
                   "0: none)")  # fmt: skip
    f.add_argument("--gradient-on", choices=("plain", "train"), default="train",
                   help="the problem the gradient steps descend (train: a training surrogate's cheaper gradient, "
                   "the points reached evaluated on the plain problem; without one the same; "
                   "default train)")  # fmt: skip
    f.add_argument(
        "--compare",
        action="append",
        default=[],
        metavar="JSON",
        help="a front.json or tune result.json to draw on the same axes (repeatable)",
    )
    f.add_argument("--force", action="store_true", help="overwrite a non-empty --out")
    f.add_argument("--resume", action="store_true", help="continue from --out's checkpoint")
    f.add_argument("--replay", metavar="JSON", help="redo the work a front.json records, bit for bit")
    _add_processes(f)
    f.set_defaults(func=cmd_front)
    e = sub.add_parser("select", help="the front point that best meets a bound on error or chattering; its TOML")
    e.add_argument("--front", required=True, metavar="JSON", help="a `fosmc front` front.json")
    bound = e.add_mutually_exclusive_group(required=True)
    bound.add_argument("--max-error", type=float, metavar="E",
                       help="the least mean chattering_hf among the points of mean rms_error <= E (rad)")  # fmt: skip
    bound.add_argument("--max-chattering", type=float, metavar="C",
                       help="the least mean rms_error among the points of mean chattering_hf <= C (V)")  # fmt: skip
    e.add_argument("--training-only", action="store_true",
                   help="judge the points on the training batch alone (default: on the larger of the training "
                   "and held-out means, where the front has held-out metrics)")  # fmt: skip
    e.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    e.set_defaults(func=cmd_select)
    t = sub.add_parser("tune", help="gradient-based tuning of the controller kind's parameters (optax)")
    t.add_argument("--config", help="TOML config with a [tune] table (default: the paper's setup)")
    t.add_argument("--steps", type=int, help="optimizer steps (overrides tune.steps)")
    t.add_argument("--budget", type=float, help="wall time, s, from the process's start (compilation included): "
                   "the global stage and as many gradient steps as fit (10 x tune.steps at most; --steps at most "
                   "where given)")  # fmt: skip
    t.add_argument("--out", default="out/tune", help="output folder (default: out/tune)")
    t.add_argument("--resume", action="store_true", help="continue from --out's checkpoint")
    t.add_argument("--force", action="store_true", help="overwrite a non-empty --out")
    _add_processes(t)
    t.set_defaults(func=cmd_tune)
    c = sub.add_parser("certify", help="check the hitting condition (20) numerically; gamma-bound verdicts")
    c.add_argument("--config", help="TOML config (default: the paper's setup)")
    c.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    c.add_argument("--vertices", default="all", help="'all' (exact over the box) or N sampled vertices")
    c.add_argument("--configured-switching", action="store_true", help="use controller.switching instead of SGN")
    c.add_argument("--seed", type=int, default=0, help="seed of the sampled points")
    c.set_defaults(func=cmd_certify)
    x = sub.add_parser("export", help="the digital loop's controller as dependency-free C99 (a header and a source)")
    x.add_argument("--config", help="TOML config with a digital loop (controller.sample_period > 0)")
    x.add_argument("--params", metavar="JSON",
                   help="the tuned parameters of a `fosmc tune` result.json or a `fosmc front` front.json")  # fmt: skip
    x.add_argument("--point", type=int, help="with a front.json (required there): the point to export (index)")
    x.add_argument("--out", required=True, metavar="DIR",
                   help="folder for NAME.h and NAME.c (created; files of those names replaced)")  # fmt: skip
    x.add_argument("--precision", choices=("float32", "float64"), default="float64",
                   help="the C real type (default float64)")  # fmt: skip
    x.add_argument("--name", default="fosmc", help="prefix of the files and of every C identifier (default fosmc)")
    x.set_defaults(func=cmd_export)
    i = sub.add_parser("identify", help="fit the arm's parameters to a log of an experiment (angles, voltages)")
    i.add_argument("--config", help="TOML config: the arm to start from, its encoder, integrator and delay")
    i.add_argument("--data", required=True, metavar="LOG",
                   help="the log: CSV (t, theta1-3, u1-3[, i1-3]) or NPZ (t, theta, u[, current])")  # fmt: skip
    i.add_argument("--params", required=True, metavar="NAMES",
                   help="comma-separated [arm] fields to fit, and payload (e.g. R,Kt,Kb,Jm,m3,payload)")  # fmt: skip
    i.add_argument("--out", metavar="DIR", help="folder for identified.toml and identify.json")
    i.add_argument("--payload", type=float, metavar="KG",
                   help="the experiment's payload, or the fit's start when payload is named (default: the config's, "
                   "if plant.payloads lists one)")  # fmt: skip
    i.add_argument("--delay", type=int, metavar="N",
                   help="samples from a logged voltage to the motor (default: controller.delay_samples)")  # fmt: skip
    i.add_argument("--window", type=float, default=0.2, metavar="S", help="shooting window, s (default 0.2)")
    i.add_argument("--dt", type=float, metavar="S",
                   help="longest integration step, s: the sample period cut in equal steps no longer (default: "
                   "the log's sample period)")  # fmt: skip
    i.add_argument("--threshold", type=float, default=0.05, metavar="X",
                   help="relative standard deviation above which the log does not identify (default 0.05)")  # fmt: skip
    i.add_argument("--iterations", type=int, default=50, metavar="N", help="LM steps per fit pass (default 50)")
    i.add_argument("--bootstrap", type=int, default=200, metavar="N",
                   help="window resamples (default 200; none below 5 windows)")  # fmt: skip
    i.add_argument("--json", action="store_true", help="print the report as JSON (without the config)")
    i.add_argument("--force", action="store_true", help="overwrite a non-empty --out")
    i.set_defaults(func=cmd_identify)
    return p


def _warn(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"fosmc: warning: {message}", file=sys.stderr)


#: Exit statuses of a run cut short, as a shell reports a process killed by the signal: 128 + SIGINT (2),
#: 128 + SIGPIPE (13) (numbers, not ``signal``'s names: Windows has no SIGPIPE).
INTERRUPTED, BROKEN_PIPE = 130, 141


def main(argv: list[str] | None = None) -> int:
    """The ``fosmc`` command: 0 when done; 2 and one line ``fosmc: error: <key or option>:
    <what is wrong>`` for a bad input, before the work; 130 on Ctrl-C (SIGINT), with one line
    saying how to resume ``tune`` and ``front`` from their checkpoint; 141 when the reader of
    the output went away (``| head``), quietly."""
    argv = sys.argv[1:] if argv is None else list(argv)
    started = time.time()
    args = parser().parse_args(argv)
    processes = distributed.Processes(*(getattr(args, k, None) for k in ("distributed", "coordinator",
                                                                          "num_processes", "process_id")),
                                      getattr(args, "join_timeout", distributed.JOIN_TIMEOUT_S))  # fmt: skip
    if processes.asked and not os.environ.get(distributed.CHILD):
        try:
            processes.checked()
        except problems.ConfigError as e:
            print(f"fosmc: error: {e}", file=sys.stderr)
            return 2
        return distributed.supervise(argv, processes)  # the work in a child: its faults in one line
    warnings.showwarning = _warn
    from .._simulator.cache import use_compilation_cache
    from .._simulator.sharding import _cores, show_all_cores, use_all_cores, use_host_devices  # before JAX starts

    if getattr(args, "devices", None) is None:
        # simulate, front (and tune's global stage) split their batches over every local device; a process
        # that joins others must not start JAX before it has
        show_all_cores() if processes.asked else use_all_cores()
    else:
        # each CPU device has its own threads: thousands abort the process (LLVM's pthread_create)
        if not 1 <= args.devices <= _cores():
            print(f"fosmc: error: --devices: expected an integer in [1, {_cores()}] (the cores this process may run "
                  f"on; more devices than cores run no faster), got {args.devices}", file=sys.stderr)  # fmt: skip
            return 2
        try:
            use_host_devices(args.devices)
        except RuntimeError as e:
            print(f"fosmc: error: --devices: {e}", file=sys.stderr)
            return 2
    jax.config.update("jax_enable_x64", True)  # float64 available; each run picks its precision
    use_compilation_cache()  # a second run loads its programs (FOSMC_JAX_COMPILATION_CACHE=0: off)
    try:
        load_entry_points()  # the controller kinds installed packages register (group fosmc_jax.kinds)
    except ValueError as e:
        print(f"fosmc: error: controller kinds: {e}", file=sys.stderr)
        return 2
    try:
        if processes.asked:  # first: before the command's own JAX operations (its config's checks)
            distributed.join(processes)
        code = args.func(args)
        sys.stdout.flush()  # a reader that went away shows here, not at the interpreter's exit
        return code
    except problems.ConfigError as e:
        print(f"fosmc: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        _silence_stdout()
        return BROKEN_PIPE
    except KeyboardInterrupt:
        _log(_interrupted(args, argv, started))
        return INTERRUPTED
    except Exception as e:
        if processes.asked and distributed.collective_failed(e):  # a peer died: the supervisor names it
            return distributed.after_collective_failed(e)
        raise


def _silence_stdout() -> None:
    """Point stdout at /dev/null, so that the interpreter's last flush of what the gone reader
    did not take raises nothing (Python's documented recipe for SIGPIPE)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # stdout is not a file (a test's capture)
        pass


def _interrupted(args, argv: list[str], started: float) -> str:
    """The one line of a run cut short by Ctrl-C: for ``tune`` and ``front``, whether its
    checkpoint (written atomically, so whole) holds work to resume from, and the command that
    does; ``started``: this process's start (``time.time()``), to tell this run's checkpoint
    from an earlier run's that ``--force`` was about to replace."""
    out = getattr(args, "out", None)
    if args.command == "simulate" and args.checkpoint and any(Path(args.checkpoint).glob("chunk_*.npz")):
        again = argv + ([] if args.resume else ["--resume"])
        return (f"fosmc: interrupted; {args.checkpoint} keeps the chunks done so far: resume with "
                f"`fosmc {shlex.join(again)}`")  # fmt: skip
    if args.command not in ("tune", "front") or out is None:
        return "fosmc: interrupted"
    checkpoint = Path(out) / "checkpoint.npz"
    if checkpoint.exists() and (args.resume or checkpoint.stat().st_mtime >= started):
        again = [a for a in argv if a != "--force"] + ([] if args.resume else ["--resume"])
        return (f"fosmc: interrupted; {checkpoint} keeps the work done so far: resume with "
                f"`fosmc {shlex.join(again)}`")  # fmt: skip
    return f"fosmc: interrupted before the first checkpoint in {out}: nothing to resume, run the command again"


if __name__ == "__main__":
    sys.exit(main())
