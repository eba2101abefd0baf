"""The ``fosmc`` command line. No numerics here: it reads configs, calls the library, prints."""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings

import jax
import numpy as np

from . import _config, _paper
from ._design import CONVENTIONS, summarize
from ._io import jsonable, write_text
from ._metrics import METRIC_NAMES, UNITS, batch_summary
from ._simulator import simulate_batch


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------- simulate


def cmd_simulate(args) -> int:
    cfg = _config.load(args.config)
    if args.params:
        cfg = _config.with_params(cfg, args.params, args.point)
    elif args.point is not None:
        raise _config.ConfigError("--point: needs --params FRONT.json")
    n = _config.n_steps(cfg)
    if args.plot and not cfg["sim"]["save_every"]:
        m = _config.sample_steps(cfg)
        cfg["sim"]["save_every"] = max(1, n // 4000 // m) * m
    problem = _config.build(cfg)
    n_plants = jax.tree.leaves(problem.plants)[0].shape[0]
    n_offsets, n_real = problem.X0s.shape[0], 1 if problem.keys is None else problem.keys.shape[0]
    n_rollouts = n_plants * n_offsets * n_real
    _log(f"fosmc: {n_rollouts} rollout(s) x {n} steps ({cfg['sim']['integrator']}, "
         f"dt = {cfg['sim']['dt']} s, {cfg['sim']['precision']}): compiling and running ...")  # fmt: skip
    start = time.perf_counter()
    if args.devices > 1:
        from ._sharding import simulate_sharded

        result = simulate_sharded(*problem.args, devices=args.devices, keys=problem.keys, **problem.options)
    else:
        result = simulate_batch(*problem.args, keys=problem.keys, **problem.options)
    result = jax.block_until_ready(result)
    _log(f"fosmc: done in {time.perf_counter() - start:.2f} s (compilation included)")

    metrics = {name: np.asarray(getattr(result.metrics, name)) for name in METRIC_NAMES}
    rollouts = []
    for r in range(n_rollouts):
        rollouts.append({
            "plant_index": r // (n_offsets * n_real),
            "offset_index": r // n_real % n_offsets,
            "realization_index": r % n_real,
            "metrics": {name: metrics[name][r] for name in METRIC_NAMES},
            "diverged": bool(result.diverged[r]),
            "diverged_at": float(result.diverged_at[r]),
        })  # fmt: skip
    if args.plot:
        from ._plots import plot_rollouts

        shown = min(n_rollouts, 12)
        tr = result.trace
        labels = [f"plant {x['plant_index']}, offset {x['offset_index']}" for x in rollouts[:shown]]
        plot_rollouts(np.asarray(tr.t[0]), tr.X[:shown], tr.X_d[:shown], tr.U[:shown], labels, args.plot,
                      title=f"{cfg['controller']['kind']}, {cfg['controller']['switching']} switching, "
                            f"{cfg['sim']['integrator']} dt = {cfg['sim']['dt']} s")  # fmt: skip
        _log(f"fosmc: wrote {args.plot}")
    summary = batch_summary(result.metrics, result.diverged)
    if args.json:
        print(json.dumps(jsonable({"rollouts": rollouts, "summary": summary, "config": cfg}), indent=1))
    else:
        _print_rollouts(rollouts)
        if n_rollouts > 1:
            print(f"batch of {n_rollouts}: {summary['diverged_excluded']} diverged (excluded below)")
            for name in METRIC_NAMES:
                print(f"  {name:<19} mean {_fmt3(summary['mean'][name])}   max {_fmt3(summary['max'][name])}")
    return 0


def _print_rollouts(rollouts: list[dict]) -> None:
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


# ---------------------------------------------------------------------------- bounds


def cmd_bounds(args) -> int:
    cfg = _config.load(args.config)
    start = time.perf_counter()
    arm = cfg["plant"]["kind"] == "arm"
    if arm:
        from ._arm import ARM_PARAMS, arm_box, envelope_samples

        lo, hi = min(cfg["plant"]["payloads"]), max(cfg["plant"]["payloads"])
        _log(f"fosmc bounds: sampling the arm's rows along the reference, payloads {lo:g}..{hi:g} kg ...")
        with jax.enable_x64(True):
            abox = arm_box(ARM_PARAMS, np.linspace(lo, hi, 11), envelope_samples())
        a_rows, b_rows, box = abox.A_nominal, abox.B_nominal, abox[:4]
    else:
        box = _config.box_of(cfg)
        a_rows, b_rows = cfg["model"]["A_rows"], cfg["model"]["B_rows"]
    d = summarize(a_rows, b_rows, box, cfg["controller"]["C"], cfg["controller"]["poles"])
    elapsed = time.perf_counter() - start
    out = {
        "alpha": d.alpha.value,
        "beta": d.beta.value,
        "vertices_checked": {"A": d.alpha.vertices_checked, "B": d.beta.vertices_checked},
        "K": d.K,
        "closed_loop_poles": [[z.real, z.imag] for z in d.closed_loop_poles],
        "CB": d.CB,
        "gamma_min": d.gamma_min,
        "gamma": cfg["controller"]["gamma"],
        "paper_printed": {
            "alpha": _paper.ALPHA_PRINTED,
            "beta": _paper.BETA_PRINTED,
            "gamma_min": _paper.GAMMA_MIN_PRINTED,
        },
    }
    if arm:
        out["box"] = dict(zip(_config.BOX_KEYS, box))
        out["nominal_A_rows"], out["nominal_B_rows"] = a_rows, b_rows
    if args.json:
        print(json.dumps(jsonable(out), indent=1))
        return 0
    fmt = lambda v: "  ".join(f"{x:10.4f}" for x in np.ravel(v))
    if arm:
        print("The arm's box (sampled along the reference x payloads) beside the paper's Appendix box")
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
    print(f"alpha = max ||B_bar^-1 dA_r||_2 over {d.alpha.vertices_checked} box vertices = {d.alpha.value:.4f}"
          f"   (paper (31): {_paper.ALPHA_PRINTED})")  # fmt: skip
    print(f"beta  = max ||B_bar^-1 dB_r||_2 over {d.beta.vertices_checked} box vertices = {d.beta.value:.4f}"
          f"   (paper (31): {_paper.BETA_PRINTED})")  # fmt: skip
    print(f"({elapsed:.1f} s)\nK (3x9), placing the poles exactly (A + BK, (16)):")
    for row in d.K:
        print("  " + "  ".join(f"{x:9.4f}" for x in row))
    print(
        "eig(A + BK): "
        + ", ".join(f"{z.real:.4g}" + (f"{z.imag:+.3g}j" if z.imag else "") for z in d.closed_loop_poles)
    )
    print("CB:")
    for row in d.CB:
        print("  " + fmt(row))
    s = np.linalg.svd(d.CB, compute_uv=False)
    print(f"singular values of CB: {fmt(s)}")
    print("gamma lower bounds (24)-(26):")
    print(f"  {'spectral (all 2-norms)':<34}{fmt(d.gamma_min['spectral'])}")
    print(f"  {'paper (||CB|| = sigma_min(CB))':<34}{fmt(d.gamma_min['paper'])}")
    print(f"  {'printed in the paper, (35)':<34}{fmt(_paper.GAMMA_MIN_PRINTED)}")
    print(f"  {'gamma in use':<34}{fmt(cfg['controller']['gamma'])}")
    for c in CONVENTIONS:
        ok = np.all(np.asarray(cfg["controller"]["gamma"]) > d.gamma_min[c])
        print(f"  gamma {'meets' if ok else 'does NOT meet'} the {c} bounds")
    return 0


# ---------------------------------------------------------------------------- reproduce


def cmd_reproduce(args) -> int:
    from pathlib import Path

    from . import _reproduce as R

    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.force:
        raise _config.ConfigError(f"--out: {out} exists and is not empty (use --force to overwrite)")
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    settings = R.Settings(t_final=args.t_final, dt=args.dt, integrator=args.integrator)
    _log(f"fosmc reproduce: {args.plant} plant, {settings.integrator}, dt = {settings.dt} s, "
         f"{settings.t_final} s; compiling and running the cases ...")  # fmt: skip
    cases = R.run_cases(args.plant, settings, log=_log)
    rows = R.metric_rows(cases)
    _log(f"fosmc reproduce: the shortened check table ({R.SHORT.t_final} s) ...")
    short = R.metric_rows(R.run_cases(args.plant, R.SHORT, log=_log))
    files = {"metrics.csv": R.to_csv(rows), "metrics.md": R.to_markdown(rows), "design.md": R.design_facts(),
             "metrics_short.csv": R.to_csv(short)}  # fmt: skip
    for name, text in files.items():
        write_text(out / name, text)
    _log("fosmc reproduce: drawing figures ...")
    figures = R.write_figures(cases, out, args.plant)
    if args.plant == "arm":
        _log(f"fosmc reproduce: the realistic loop ({R.REALISTIC_PRESET.name}) beside the ideal one ...")
        realistic = R.run_realistic_cases(args.t_final, log=_log)
        sweeps = R.tradeoff_sweeps(args.t_final, log=_log)
        rows = R.metric_rows(realistic, R.METRIC_NAMES)
        files.update({"realistic.md": R.to_markdown(rows, R.METRIC_NAMES), "tradeoff.md": R.sweep_markdown(sweeps)})
        for name in ("realistic.md", "tradeoff.md"):
            write_text(out / name, files[name])
        figures += R.write_realistic_figures(cases + realistic, sweeps, out)
    if args.report:
        report = Path(args.report)
        text = report.read_text()
        text = R.replace_block(text, "metrics", files["metrics.md"])
        text = R.replace_block(text, "design", files["design.md"])
        for name in ("realistic", "tradeoff"):
            if f"{name}.md" in files:
                text = R.replace_block(text, name, files[f"{name}.md"])
        write_text(report, text)
        _log(f"fosmc reproduce: updated {report}")
    print(files["metrics.md"])
    _log(f"fosmc reproduce: wrote {', '.join(list(files) + figures)} to {out}/ "
         f"in {time.perf_counter() - start:.1f} s (total wall time)")  # fmt: skip
    return 0


# ---------------------------------------------------------------------------- tune


def cmd_tune(args) -> int:
    from pathlib import Path

    from . import _tuning as T
    from ._plots import plot_tuning

    cfg = _config.load(args.config)
    tcfg = cfg["tune"]
    if args.steps is not None:
        if args.steps < 1:
            raise _config.ConfigError(f"--steps: expected a positive integer, got {args.steps}")
        tcfg["steps"] = args.steps
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not (args.force or args.resume):
        raise _config.ConfigError(f"--out: {out} exists and is not empty (use --resume or --force)")
    plain, problem, p0 = _config.tuning_problems(cfg)
    out.mkdir(parents=True, exist_ok=True)
    floor = None
    if tcfg["keep_gamma_bound"]:
        box = _config.box_of(cfg)
        d = summarize(cfg["model"]["A_rows"], cfg["model"]["B_rows"], box, cfg["controller"]["C"],
                      cfg["controller"]["poles"])  # fmt: skip
        floor = T.GammaFloor(d.alpha.value, d.beta.value, tcfg["gamma_bound_convention"])
    n_rollouts = _rollouts(problem)
    _log(f"tune: {n_rollouts} rollouts x {problem.options['n_steps']} steps (dt = {float(problem.dt)} s) per "
         f"training evaluation; free parameters: {', '.join(tcfg['params'])}")  # fmt: skip
    m = T.evaluate(problem, p0)["metrics"]  # the objective's scales, on the training simulation
    initial = T.evaluate(plain, p0)
    obj = T.objective_of(tcfg, m)
    start_params = p0
    resuming = args.resume and (out / "checkpoint.npz").exists()
    if tcfg["global_candidates"] and floor is None and not resuming:
        from ._front import global_stage

        start_params, score = global_stage(problem, obj, p0, tcfg["global_candidates"], free=tuple(tcfg["params"]),
                                           log=_log)  # fmt: skip
        _log(f"tune: global stage: the best of {tcfg['global_candidates']} candidates scores {score:.4f} "
             "(the config's parameters score about 0 with the log scale)")  # fmt: skip
    try:
        u0 = T.to_internal(start_params, plain.base, floor)
    except ValueError as e:
        raise _config.ConfigError(str(e)) from None
    settings = T.Settings(tcfg["steps"], tcfg["learning_rate"], tcfg["schedule"], tcfg["clip"], tcfg["mode"],
                          tuple(tcfg["params"]), tcfg["checkpoint_every"])  # fmt: skip
    start = time.perf_counter()
    u, history = T.run(T.make_loss(problem, obj, floor), u0, settings, checkpoint=out / "checkpoint.npz",
                       resume=args.resume, log=_log)  # fmt: skip
    final_params = T.to_physical(u, plain.base, floor)
    final = T.evaluate(plain, final_params)
    as_dict = lambda p: {k: np.asarray(v).tolist() for k, v in p._asdict().items()}
    result = {
        "initial": {"params": as_dict(p0), **initial},
        "start": {
            "params": as_dict(start_params),
            "global_candidates": 0 if start_params is p0 else tcfg["global_candidates"],
        },  # fmt: skip
        "final": {"params": as_dict(final_params), **final},
        "objective": obj._asdict(),
        "history": {k: v for k, v in history.items() if k != "params"},
        "config": cfg,
    }
    write_text(out / "result.json", json.dumps(jsonable(result), indent=1))
    params_history = [as_dict(T.to_physical(T.Tunable(*map(jax.numpy.asarray, p)), plain.base, floor))
                      for p in history["params"]]  # fmt: skip
    plot_tuning(history, params_history, out / "tuning.png")
    _log(f"tune: wrote {out}/result.json and {out}/tuning.png in {time.perf_counter() - start:.1f} s")
    for name in ("rms_error", "chattering"):
        print(f"{name:<12} initial {_fmt3(initial['metrics'][name])}   final {_fmt3(final['metrics'][name])}")
    return 0


def _fmt3(v) -> str:
    return " ".join(f"{x:.4e}" for x in v)


def _rollouts(problem) -> int:
    """Rollouts in a problem's batch: plants x offsets x noise realizations."""
    keys = 1 if problem.keys is None else problem.keys.shape[0]
    return jax.tree.leaves(problem.plants)[0].shape[0] * problem.X0s.shape[0] * keys


# ---------------------------------------------------------------------------- front


def cmd_front(args) -> int:
    from pathlib import Path

    from . import _front as F

    cfg = _config.load(args.config)
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not (args.force or args.resume):
        raise _config.ConfigError(f"--out: {out} exists and is not empty (use --resume or --force)")
    for name, value in (("--points", args.points), ("--candidates", args.candidates), ("--steps", args.steps)):
        if value is not None and value < (1 if name == "--points" else 0):
            raise _config.ConfigError(f"{name}: expected a {'positive' if name == '--points' else 'non-negative'} "
                                      f"integer, got {value}")  # fmt: skip
    if not args.budget > 0:
        raise _config.ConfigError(f"--budget: expected a positive number of seconds, got {args.budget}")
    for path in args.compare:
        try:
            json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            raise _config.ConfigError(f"--compare: cannot read {path}: {e}") from None
    out.mkdir(parents=True, exist_ok=True)
    settings = F.Settings(points=args.points or 8, budget=args.budget, candidates=args.candidates or 0,
                          steps=args.steps or 0)  # fmt: skip
    start = time.perf_counter()
    result = F.study(cfg, settings, out=out, resume=args.resume, compare=tuple(args.compare), log=_log)
    _log(f"front: {len(result['points'])} points in {time.perf_counter() - start:.1f} s (wall time)")
    for i, pt in enumerate(result["points"]):
        e, c = (float(np.mean(pt["metrics"][k])) for k in F.AXES)
        print(f"point {i:3d}  {F.AXES[0]} {e:.4e} rad  {F.AXES[1]} {c:.4e} V  diverged {pt['diverged']}")
    return 0


# ---------------------------------------------------------------------------- certify


def cmd_certify(args) -> int:
    from . import _certify

    cfg = _config.load(args.config)
    switching = cfg["controller"]["switching"] if args.configured_switching else "sign"
    opts = {"switching": switching, "seed": args.seed}
    if args.vertices != "all":
        if not args.vertices.isdigit() or int(args.vertices) < 1:
            raise _config.ConfigError(f"--vertices: expected 'all' or a positive integer, got {args.vertices!r}")
        opts["vertices"] = int(args.vertices)
    _log(f"fosmc certify: {cfg['plant']['kind']} plant, {switching} switching ...")
    start = time.perf_counter()
    r = _certify.report(cfg, **opts)
    _log(f"fosmc certify: done in {time.perf_counter() - start:.1f} s")
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


# ---------------------------------------------------------------------------- main


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fosmc", description="FOSMC tracking controller simulator (JAX)")
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("simulate", help="simulate the closed loop; print metrics per rollout")
    s.add_argument("--config", help="TOML config (default: the paper's setup)")
    s.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    s.add_argument("--plot", metavar="PNG", help="write a figure of the rollouts")
    s.add_argument(
        "--params",
        metavar="JSON",
        help="use delta, gamma, poles from a `fosmc tune` result.json or a `fosmc front` front.json",
    )
    s.add_argument("--point", type=int, help="with a front.json: the point to re-run (index)")
    s.add_argument("--devices", type=int, default=1, help="split the batch over N devices (on CPU: N host devices)")
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
    f = sub.add_parser("front", help="Pareto front of tracking error against chattering")
    f.add_argument("--config", help="TOML config (default: the paper's setup)")
    f.add_argument("--out", default="out/front", help="output folder (default: out/front)")
    f.add_argument("--points", type=int, help="refinement starts (default 8)")
    f.add_argument("--budget", type=float, default=300.0, help="wall time, s (default 300)")
    f.add_argument("--candidates", type=int, help="global stage size (default: from the budget)")
    f.add_argument("--steps", type=int, help="refinement steps (default: from the budget)")
    f.add_argument(
        "--compare",
        action="append",
        default=[],
        metavar="JSON",
        help="a front.json or tune result.json to draw on the same axes (repeatable)",
    )
    f.add_argument("--force", action="store_true", help="overwrite a non-empty --out")
    f.add_argument("--resume", action="store_true", help="continue from --out's checkpoint")
    f.set_defaults(func=cmd_front)
    t = sub.add_parser("tune", help="gradient-based tuning of delta, gamma and the poles (optax)")
    t.add_argument("--config", help="TOML config with a [tune] table (default: the paper's setup)")
    t.add_argument("--steps", type=int, help="optimizer steps (overrides tune.steps)")
    t.add_argument("--out", default="out/tune", help="output folder (default: out/tune)")
    t.add_argument("--resume", action="store_true", help="continue from --out's checkpoint")
    t.add_argument("--force", action="store_true", help="overwrite a non-empty --out")
    t.set_defaults(func=cmd_tune)
    c = sub.add_parser("certify", help="check the hitting condition (20) numerically; gamma-bound verdicts")
    c.add_argument("--config", help="TOML config (default: the paper's setup)")
    c.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    c.add_argument("--vertices", default="all", help="'all' (exact over the box) or N sampled vertices")
    c.add_argument("--configured-switching", action="store_true", help="use controller.switching instead of SGN")
    c.add_argument("--seed", type=int, default=0, help="seed of the sampled points")
    c.set_defaults(func=cmd_certify)
    return p


def _warn(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"fosmc: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    warnings.showwarning = _warn
    if getattr(args, "devices", 1) > 1:
        from ._sharding import use_host_devices

        try:
            use_host_devices(args.devices)  # before the first JAX operation
        except RuntimeError as e:
            print(f"fosmc: error: --devices: {e}", file=sys.stderr)
            return 2
    elif getattr(args, "devices", 1) < 1:
        print(f"fosmc: error: --devices: expected a positive integer, got {args.devices}", file=sys.stderr)
        return 2
    jax.config.update("jax_enable_x64", True)  # float64 available; each run picks its precision
    try:
        return args.func(args)
    except _config.ConfigError as e:
        print(f"fosmc: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
