"""``fosmc front`` against pymoo's and optuna's NSGA-II at equal wall time, over seeds and populations.

Each run is ``tuning/reference_front.py build`` in a fresh process (the front: the CLI with
``--seed``; NSGA-II: :func:`fosmc_jax.search.nsga2` / ``optuna_nsga2`` through the package's
evaluator), its files in ``--runs`` (outside the repository), its front scored against the
config's committed reference front (tuning/results/reference/<config>/reference.json: epsilon in
log10 over the reference points with chattering_hf in 0.1-10 V and 0.5-10 V, hypervolume). The
matrix runs round-robin: seed 0 of every config and method, then seed 1 of every one, ..., so that
the shared machine's load drift reaches every method alike. Every child gets JAX's persistent
compilation cache in ``$FOSMC_JAX_CACHE``/xla at the CLI's 0.5 s threshold (``build`` of a peer
turns none on by itself), so that every method runs from the same warm caches; compilation counts
inside every method's budget.

    .venv/bin/python tuning/front_vs_peers.py --configs tuning/configs/realistic_arm.toml \\
        tuning/configs/unseen_arm.toml --methods front nsga2:64 nsga2:256 nsga2:512 nsga2:1024 \\
        optuna_nsga2:64 optuna_nsga2:256 --seeds 0 1 2 --budget 60 [--resume] [--report-only]

Writes tuning/results/front_vs_peers_<budget>s.{json,md} after every run (atomically; ``--resume``
skips the runs already there without an error), ``--findings FILE``: a markdown text kept in the
JSON and printed in the md. Per run: the process's wall time (launch to exit), ``build``'s (the
peers' budget starts inside it), the front CLI's own, evaluations, the 1/5/15-minute load at
start and end, the epsilons, the hypervolume and by how much its points beat the reference where
they do (the reference's epsilon against the run's points in 0.1-10 V; > 0: the reference is not
the union of everything measured). Progress lines go to stdout, prefixed by the time.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import re
import shlex
import subprocess
import sys
import time

import numpy as np

HERE = pathlib.Path(__file__).parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

import reference_front as rf  # noqa: E402
from reference_front import log  # noqa: E402

from fosmc_jax import search as fs  # noqa: E402
from fosmc_jax.io import jsonable, write_text  # noqa: E402

BAND = rf.BANDS[0]


def parse_method(spec: str) -> tuple[str, int | None]:
    """A method of --methods ("front", "nsga2:512") as (method, population or None)."""
    name, _, pop = spec.partition(":")
    return name, (int(pop) if pop else None) if name != "front" else None


def key(r: dict) -> tuple:
    return r["config"], r["method"], r["popsize"], r["seed"]


def one_run(config: str, method: str, pop: int | None, seed: int, budget: float, folder: pathlib.Path) -> dict:
    """One ``build`` in a fresh process, scored against the config's reference.json."""
    folder.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, str(HERE / "reference_front.py"), "build", "--config", config, "--method", method,
           "--budget", f"{budget:g}", "--seed", str(seed), *(["--popsize", str(pop)] if pop else []), "--out", str(folder)]  # fmt: skip
    env = rf.cache_env()
    load0, t0 = rf.load_text(), time.perf_counter()
    with open(folder / "build.log", "w") as out:
        rc = subprocess.run(cmd, env=env, stdout=out, stderr=subprocess.STDOUT).returncode
    run = {"config": config, "method": method, "popsize": pop, "seed": seed, "budget_s": budget, "rc": rc,
           "process_wall_s": time.perf_counter() - t0, "load_start_end": [load0, rf.load_text()],
           "command": " ".join(shlex.quote(a) for a in cmd).replace(f"{ROOT}/", ""), "folder": str(folder)}  # fmt: skip
    if rc:
        run["log_tail"] = (folder / "build.log").read_text()[-2000:]
        return run
    b = json.loads((folder / f"{method}.json").read_text())
    run.update(build_wall_s=b["wall_s"], evaluations=b["evaluations"], non_dominated=b["non_dominated"],
               diverged_candidates=b["diverged_candidates"], code=b["code"])  # fmt: skip
    if method == "front":  # the CLI's wall time from its process's start (its last lines), its stages' own
        cli = re.findall(r"points in ([0-9.]+) s \(wall time from the process", (folder / "build.log").read_text())
        run.update(cli_wall_s=float(cli[-1]), front_stages_wall_s=b["stages"]["wall_time_s"])
    reference = json.loads((ROOT / "tuning/results/reference" / rf.config_name(config) / "reference.json").read_text())
    e, c = rf.axes([p for p in b["points"] if p["diverged"] == 0])
    run.update(rf.score((e, c), reference))
    # where the run beats the reference: its epsilon against the run's points in the band
    band = (c >= BAND[0]) & (c <= BAND[1])
    ref = rf.axes(reference["points"])
    beyond = [fs.additive_epsilon(ref, (e[i : i + 1], c[i : i + 1])) for i in np.flatnonzero(band)]
    run["beats_reference_by"] = max(beyond, default=float("nan"))
    run["points_beyond_reference"] = int(np.sum(np.array(beyond) > 1e-9))
    return run


# ---------------------------------------------------------------------------- report


def fmt(x: float, spec: str = ".4f") -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, spec)


def rows_of(runs: list[dict], config: str) -> dict[tuple, list[dict]]:
    """The config's finished runs by (method, population), in the order first run."""
    out: dict[tuple, list[dict]] = {}
    for r in runs:
        if r["config"] == config and not r["rc"]:
            out.setdefault((r["method"], r["popsize"]), []).append(r)
    return out


def median(runs: list[dict], k: str) -> float:
    return float(np.median([r[k] for r in runs]))


def markdown(data: dict) -> str:
    b = data["budget_s"]
    lines = [f"# `fosmc front` against NSGA-II (pymoo, optuna) at {b:g} s", "",
             f"Made by `{data['command']}` (code {data['code']['commit'][:7]}, fosmc_jax diff "
             f"{data['code']['fosmc_jax_diff_sha1'] or 'none'}); every run a fresh process of `tuning/reference_front.py "
             "build` through the package's evaluator, round-robin over seeds, every method from the same warm "
             "persistent caches (native kernels and XLA programs; compilation inside every budget). Epsilon: additive, "
             "log10 of both axes, against the committed `tuning/results/reference/<config>/reference.json` (0.02 = "
             "4.7%); HV: hypervolume in (log10 V, log10 rad) to the reference's fixed point (the reference front's "
             "own in brackets). Wall: `build`'s (the front: the CLI's own, from its process's start) / the whole "
             "process's (launch to exit), medians. Load: 1-minute load average at the runs' starts and ends "
             "(range). Beats ref.: the largest log10 margin by which a run's point in 0.1-10 V lies beyond the "
             "reference front, over the seeds (points beyond it, summed).", ""]  # fmt: skip
    for config in data["configs"]:
        rows = rows_of(data["runs"], config)
        if not rows:
            continue
        ref_hv = next(iter(rows.values()))[0]["reference_hypervolume"]
        lines += [f"## {rf.config_name(config)}", "",
                  "| method | population | epsilon 0.1-10 V per seed | median | median 0.5-10 V | HV median "
                  f"({ref_hv:.3f}) | evaluations (median) | wall s | load (1-min) | beats ref. by (points) |",
                  "|---|---:|---|---:|---:|---:|---:|---:|---|---:|"]  # fmt: skip
        for (method, pop), rs in rows.items():
            rs = sorted(rs, key=lambda r: r["seed"])
            per_seed = ", ".join(f"{r['seed']}: {r['epsilon_0.1_10']:.4f}" for r in rs)
            wall = median(rs, "cli_wall_s" if method == "front" else "build_wall_s")
            loads = [float(x.split()[0]) for r in rs for x in r["load_start_end"]]
            lines.append(f"| {method} | {pop or '-'} | {per_seed} | {median(rs, 'epsilon_0.1_10'):.4f} | "
                         f"{median(rs, 'epsilon_0.5_10'):.4f} | {median(rs, 'hypervolume'):.3f} | "
                         f"{median(rs, 'evaluations'):.0f} | {wall:.1f} / {median(rs, 'process_wall_s'):.1f} | "
                         f"{min(loads):.2f}-{max(loads):.2f} | {fmt(max(r['beats_reference_by'] for r in rs))} "
                         f"({sum(r['points_beyond_reference'] for r in rs)}) |")  # fmt: skip
        peers = {k: median(rs, "epsilon_0.1_10") for k, rs in rows.items() if k[0] != "front" and len(rs)}
        lines.append("")
        if peers:
            best = min(peers, key=peers.get)
            line = f"Best NSGA-II: {best[0]} at population {best[1]}, median epsilon {peers[best]:.4f}"
            for impl in ("nsga2", "optuna_nsga2"):
                own = {k: v for k, v in peers.items() if k[0] == impl}
                if own and min(own, key=own.get) != best:
                    b2 = min(own, key=own.get)
                    line += f"; best {impl}: population {b2[1]}, {own[b2]:.4f}"
            lines.append(line + ".")
        if ("front", None) in rows and peers:
            f = median(rows["front", None], "epsilon_0.1_10")
            ahead = "ahead of" if f < peers[best] else "behind"
            lines.append(f"`fosmc front`'s median epsilon {f:.4f} is {ahead} it by {abs(f - peers[best]):.4f} "
                         f"(a factor {10 ** abs(f - peers[best]):.3f}).")  # fmt: skip
        lines.append("")
    failed = [r for r in data["runs"] if r["rc"]]
    if failed:
        lines += ["Failed runs: " + "; ".join(f"{rf.config_name(r['config'])} {r['method']} {r['popsize']} seed "
                                               f"{r['seed']} (rc {r['rc']})" for r in failed), ""]  # fmt: skip
    if data.get("findings"):
        lines += ["## Findings", "", data["findings"].strip(), ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--configs", nargs="+", default=["tuning/configs/realistic_arm.toml"])
    ap.add_argument("--methods", nargs="+", default=["front", "nsga2:64", "nsga2:256", "nsga2:512", "nsga2:1024"],
                    help="front, nsga2:<population>, optuna_nsga2:<population>")  # fmt: skip
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--budget", type=float, default=60.0, help="wall time per run, s")
    ap.add_argument("--runs", default="/tmp/front_vs_peers", help="the runs' files (default /tmp/front_vs_peers)")
    ap.add_argument("--out", help="the results' stem (default tuning/results/front_vs_peers_<budget>s)")
    ap.add_argument("--resume", action="store_true", help="skip the runs already in the JSON")
    ap.add_argument("--report-only", action="store_true", help="rewrite the md from the JSON")
    ap.add_argument("--findings", metavar="MD", help="a markdown text for the md's findings (kept in the JSON)")
    args = ap.parse_args(argv)
    stem = pathlib.Path(args.out or ROOT / "tuning" / "results" / f"front_vs_peers_{args.budget:g}s")
    path = stem.with_suffix(".json")
    command = " ".join(shlex.quote(a) for a in [".venv/bin/python", "tuning/front_vs_peers.py", *sys.argv[1:]])
    old = json.loads(path.read_text()) if (args.resume or args.report_only) and path.exists() else None
    if old is None and args.report_only:
        ap.error(f"--report-only: no {path}")
    methods = [parse_method(m) for m in args.methods]
    data = old or {"budget_s": args.budget, "command": command, "code": rf.code_state(), "runs": []}
    if not args.report_only:
        data.update(configs=list(dict.fromkeys(data.get("configs", []) + args.configs)), seeds=args.seeds)
    if args.findings:
        data["findings"] = pathlib.Path(args.findings).read_text()

    def save() -> None:
        write_text(path, json.dumps(jsonable(data), indent=1))
        write_text(stem.with_suffix(".md"), markdown(data))

    if args.report_only:
        return save()
    done = {key(r) for r in data["runs"] if not r["rc"]}
    todo = [(c, m, p, s) for s in args.seeds for c in args.configs for m, p in methods if (c, m, p, s) not in done]
    log(f"front_vs_peers: {len(todo)} runs of {args.budget:g} s ({len(done)} done), load {rf.load_text()}")
    for i, (config, method, pop, seed) in enumerate(todo):
        log(f"[{i + 1}/{len(todo)}] {rf.config_name(config)} {method} {pop or ''} seed {seed}: load {rf.load_text()}")
        folder = pathlib.Path(args.runs) / f"{args.budget:g}s" / rf.config_name(config) / f"{method}{pop or ''}_s{seed}"
        run = one_run(config, method, pop, seed, args.budget, folder)
        data["runs"] = [r for r in data["runs"] if key(r) != key(run)] + [run]
        save()
        if run["rc"]:
            log(f"  FAILED (rc {run['rc']}): {run['log_tail'][-300:]}")
        else:
            log(f"  epsilon {run['epsilon_0.1_10']:.4f} / {run['epsilon_0.5_10']:.4f}, HV {run['hypervolume']:.3f}, "
                f"{run['evaluations']} evaluations, wall {run.get('cli_wall_s', run['build_wall_s']):.1f} s "
                f"(process {run['process_wall_s']:.1f} s), beats ref. by {fmt(run['beats_reference_by'])}, "
                f"load {run['load_start_end']}")  # fmt: skip
    log(f"front_vs_peers: wrote {path} and {stem.with_suffix('.md')}")


if __name__ == "__main__":
    main()
