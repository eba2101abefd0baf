"""Which lever of ``fosmc front`` bought what, in seconds and in epsilon: one lever removed at a time.

The baseline is ``fosmc front --config C --budget 60 --search staged`` as a newcomer ran it before
NSGA-II became the default search (a fresh process,
empty compilation and kernel caches: :func:`budget_guide.one_run`); each variant removes one of
the levers of issue 22 (and two others) at the same budget, scored like the budget guide
(additive epsilon in log10 of both axes against the config's reference front over its points
with chattering_hf in 0.1-10 V and 0.5-10 V, hypervolume; ``tuning/reference_front.py``):

- ``no_train_dt``: no training surrogate at one integration step per controller sample: the
  config with ``[tune] train_dt = <[sim] dt>`` (a temporary TOML), i.e. ten plant steps per
  1 ms sample in training as in the plain problem (the library still counts this as a
  surrogate: its training problem's options differ from the plain one's by
  ``truncate_every``, so the plain re-evaluation and plain rounds still run);
- ``no_surrogate``: the same step and no surrogate at all (the pre-issue-22 behaviour; a
  monkeypatch of ``fosmc_jax._search.front._same_simulation`` to ignore ``truncate_every``, in the
  child process only);
- ``no_native``: the pure-JAX path (``vmap`` of ``simulate``'s ``lax.scan``) instead of the arm's
  compiled C++ kernel (``FOSMC_JAX_NATIVE=0``);
- ``warm``: the persistent caches of the same seed's baseline run reused (its
  ``FOSMC_JAX_CACHE``: the compiled kernel and XLA's programs): what they buy a returning user;
- ``fixed_cli``: fixed stage sizes, ``--candidates N --steps M`` with N, M what the same seed's
  baseline ran (global candidates, local rounds): the CLI's fixed-size mode, which also runs
  no CMA-ES and no plain rounds;
- ``fixed_all``: fixed sizes for every stage (global candidates, CMA-ES generations, local and
  plain rounds as the baseline ran them; ``cma`` and ``polish`` have no CLI flag: set in
  ``fosmc_jax._search.front.Settings`` by a wrapper of the CLI, in the child process only);
- ``no_cma``: no CMA-ES stage (``Settings.cma_share = 0``, same wrapper): its time goes to
  the local rounds (CMA-ES still gets whatever the global stage leaves of its own share);
- ``one_device``: the candidates not split over the cores (``JAX_NUM_CPU_DEVICES=1``; the
  kernel still uses XLA's intra-op thread pool).

    PYTHONPATH=. .venv/bin/python tuning/front_ablation.py --config tuning/configs/realistic_arm.toml \\
        --reference tuning/results/reference/realistic_arm/reference.json --seeds 0 1 2

Runs one process at a time, seeds outermost (every variant's seed 0 first); before each run it
waits (up to ``--wait`` s) for the 1-minute load average to fall to ``--max-load``, and runs
again once a run that started above it. Every run is appended to
tuning/results/front_ablation.json as it ends (``--resume`` skips the (variant, seed) pairs
already there); tuning/results/front_ablation.md is written from it.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import sys
import tempfile
import time

import numpy as np
import tomllib

HERE = pathlib.Path(__file__).parent
sys.path.insert(0, str(HERE))

import budget_guide  # noqa: E402
import reference_front  # noqa: E402

log = budget_guide.log

#: The child for the variants that change ``fosmc_jax._search.front`` in the process: argv[1] a JSON
#: object of Settings fields to set (``__same_simulation_ignores_truncation``: the patch of
#: ``no_surrogate``), the rest the CLI's arguments. Imports nothing the CLI does not import itself.
CHILD = """import json, sys
import fosmc_jax._app.cli as cli, fosmc_jax._search.front as front_module
o = json.loads(sys.argv[1])
if o.pop("__same_simulation_ignores_truncation", False):
    same = front_module._same_simulation
    drop = lambda p: p._replace(options={k: v for k, v in p.options.items() if k != "truncate_every"})
    front_module._same_simulation = lambda a, b: same(drop(a), drop(b))
base = front_module.Settings
front_module.Settings = lambda **kw: base(**{**kw, **o})
sys.exit(cli.main(sys.argv[2:]))"""

#: Variant: (lever removed, how).
VARIANTS = {
    "baseline": ("none", "`fosmc front --budget 60`, empty caches"),
    "warm": ("(c) none: adds the persistent caches to the (cold) baseline; a negative d is what they buy",
             "`FOSMC_JAX_CACHE` = the same seed's baseline's"),
    "no_train_dt": ("(a) one RK4 step per 1 ms sample in training", "config + `[tune] train_dt = 1e-4` (= `[sim] dt`)"),
    "no_surrogate": ("(a') training on `[sim]` itself, no surrogate", "as `no_train_dt`, and `_same_simulation` "
                     "ignores `truncate_every` (wrapper)"),
    "no_native": ("(b) the arm's C++ kernel -> pure-JAX scan", "`FOSMC_JAX_NATIVE=0`"),
    "fixed_cli": ("(d) time-driven stages -> `--candidates N --steps M`", "N, M: the same seed's baseline's global "
                  "candidates and local rounds (no CMA-ES, no plain rounds: the CLI's fixed mode)"),
    "fixed_all": ("(d') time-driven stages -> every stage's size fixed", "candidates, CMA-ES generations, local and "
                  "plain rounds: the same seed's baseline's (wrapper sets `Settings.cma`, `.polish`)"),
    "no_cma": ("(e) the CMA-ES stage", "`Settings.cma_share = 0` (wrapper)"),
    "one_device": ("(e') candidates split over the 2 cores", "`JAX_NUM_CPU_DEVICES=1`"),
}  # fmt: skip


def variant_config(config: str, folder: pathlib.Path) -> str:
    """The config with ``[tune] train_dt`` = its ``[sim] dt`` (a TOML in ``folder``)."""
    text = pathlib.Path(config).read_text()
    user = tomllib.loads(text)
    if "tune" in user:
        raise SystemExit(f"{config} has a [tune] table: add train_dt to it by hand")
    path = folder / f"{pathlib.Path(config).stem}_train_dt.toml"
    path.write_text(text + f"\n[tune]\ntrain_dt = {user['sim']['dt']!r}  # front_ablation.py: no_train_dt\n")
    return str(path)


def plan(variant: str, seed: int, config: str, base: pathlib.Path, runs: list[dict]) -> dict:
    """one_run's arguments of a variant (and its command as a reader would type it)."""
    done = [r for r in runs if r["variant"] == "baseline" and r["seed"] == seed]
    needs_baseline = variant in ("warm", "fixed_cli", "fixed_all")
    if needs_baseline and not done:
        raise SystemExit(f"{variant}, seed {seed}: run the baseline of seed {seed} first")
    b = done[-1] if done else None
    child = [sys.executable, "-c", CHILD]
    kw: dict = {"config": config, "cold": True}
    if variant == "baseline":
        kw["cache"] = tempfile.mkdtemp(prefix="fosmc_cold_", dir=base)
    elif variant == "warm":
        kw["cache"], kw["cold"] = b["cache"], False
    elif variant == "no_train_dt":
        kw["config"] = variant_config(config, base)
    elif variant == "no_surrogate":
        kw["config"] = variant_config(config, base)
        kw["cli"] = [*child, json.dumps({"__same_simulation_ignores_truncation": True})]
    elif variant == "no_native":
        kw["env_extra"] = {"FOSMC_JAX_NATIVE": "0"}
    elif variant == "fixed_cli":
        kw["extra"] = ("--candidates", str(b["stages"]["candidates"]), "--steps", str(b["stages"]["local_rounds"]))
    elif variant == "fixed_all":
        st = b["stages"]
        kw["extra"] = ("--candidates", str(st["candidates"]), "--steps", str(st["local_rounds"]))
        kw["cli"] = [*child, json.dumps({"cma": st["cma_generations"], "polish": st["plain_rounds"]})]
    elif variant == "no_cma":
        kw["cli"] = [*child, json.dumps({"cma_share": 0.0})]
    elif variant == "one_device":
        kw["env_extra"] = {"JAX_NUM_CPU_DEVICES": "1"}
    else:
        raise SystemExit(f"unknown variant {variant}")
    kw["extra"] = ("--search", "staged", *kw.get("extra", ()))  # its levers are the staged search's
    return kw


def wait_for_load(max_load: float, wait: float) -> None:
    """Wait until the 1-minute load average is at most ``max_load`` (at most ``wait`` s)."""
    t = time.perf_counter()
    while os.getloadavg()[0] > max_load and time.perf_counter() - t < wait:
        time.sleep(5)
    if time.perf_counter() - t > 1:
        log(f"  waited {time.perf_counter() - t:.0f} s for the load ({reference_front.load_text()})")


def one(variant: str, seed: int, args, base: pathlib.Path, runs: list[dict], reference: dict) -> dict:
    """One scored run of a variant (run again, once, when it started above ``--max-load``)."""
    for attempt in range(2):
        wait_for_load(args.max_load, args.wait)
        kw = plan(variant, seed, args.config, base, runs)
        out = base / (f"{variant}_s{seed}" + (f"_retry{attempt}" if attempt else ""))
        uptime = reference_front.load_text()
        log(f"{variant}, seed {seed}: {uptime}")
        r = budget_guide.one_run(budget=args.budget, seed=seed, out=out, **kw)
        if r["load_before"][0] <= args.max_load or attempt:
            break
        log(f"  started at load {r['load_before'][0]:.2f} > {args.max_load}: run again")
    r.update(variant=variant, uptime_before=uptime, uptime_after=reference_front.load_text(), out=str(out), retried=attempt,
             cache=kw.get("cache"), config=kw["config"], env=kw.get("env_extra", {}),
             wrapper=json.loads(kw["cli"][3]) if kw.get("cli") else None)  # fmt: skip
    text = (out / "cli.log").read_text()
    planned = re.search(r"costs ([\d.]+) s \(compilation ([\d.]+) s\): (\d+) s of search", text)
    r["chunk_s"], r["first_compile_s"], r["search_s"] = map(float, planned.groups()) if planned else (None,) * 3
    r["reach"] = budget_guide.reach(*r["front"])
    r["score"] = reference_front.score(r.pop("front"), reference)
    r["eps1"], r["eps2"] = r["score"]["epsilon_0.1_10"], r["score"]["epsilon_0.5_10"]
    r["hv"] = r["score"]["hypervolume"] / r["score"]["reference_hypervolume"]
    log(f"  wall {r['wall_s']:.1f} s, {r['evaluations']} + {r['plain_evaluations']} evaluations, "
        f"epsilon {r['eps1']:.3f} (0.1-10 V), {r['eps2']:.3f} (0.5-10 V), hypervolume {r['hv']:.4f}")  # fmt: skip
    return r


def markdown(data: dict, max_load: float = 3.5) -> str:
    runs = data["runs"]
    lines = ["# Which lever of `fosmc front` bought what (issue 22)", "",
             f"Generated by {' then '.join(f'`{c}`' for c in data.get('commands') or [data['command']])} (`tuning/front_ablation.py`), "
             f"{data['config']} at a "
             f"{data['budget']:g} s budget, one lever removed at a time. Each run is a fresh process with empty "
             "compilation and kernel caches (except `warm`), one at a time on this 2-core machine shared with other "
             "jobs; wall time from the process's start to its exit; epsilon: additive, in log10 of both axes, against "
             "the reference front over its points with chattering_hf in 0.1-10 V and 0.5-10 V (0.05 = 12%; lower is "
             "better); hypervolume as a share of the reference's. Median [range] over the seeds. d: the variant's "
             "median less the baseline's over the same seeds (epsilon: positive = the front got worse without the "
             f"lever, i.e. what the lever bought). *: a run that started above a 1-minute load of {max_load:g} after its "
             "rerun (the machine was shared).", "",
             "| variant | lever removed | seeds | wall (s) | search planned (s) | evaluations (training + plain) | "
             "points | "
             "epsilon 0.1-10 V | epsilon 0.5-10 V | hypervolume / reference's | d wall (s) | d epsilon 0.1-10 V | "
             "d epsilon 0.5-10 V | load (1 min) before-after |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    stat = lambda rs, k: (float(np.median([r[k] for r in rs])), min(r[k] for r in rs), max(r[k] for r in rs))
    fmt = lambda t, f: f"{t[0]:{f}}" + (f" [{t[1]:{f}}, {t[2]:{f}}]" if t[1] != t[2] else "")
    base = [r for r in runs if r["variant"] == "baseline"]
    for v, (lever, _) in VARIANTS.items():
        rs = [r for r in runs if r["variant"] == v]
        if not rs:
            continue
        ev = (f"{int(np.median([r['evaluations'] for r in rs])):,} + "
              f"{int(np.median([r['plain_evaluations'] for r in rs])):,}")  # fmt: skip
        load = f"{min(r['load_before'][0] for r in rs):.1f}-{max(r['load_after'][0] for r in rs):.1f}"
        delta = ["", "", ""]
        if base and v != "baseline":
            seeds = {r["seed"] for r in rs}  # the baseline over the variant's seeds
            b = [r for r in base if r["seed"] in seeds] or base
            delta = [f"{stat(rs, k)[0] - stat(b, k)[0]:+{f}}" for k, f in (("wall_s", ".1f"), ("eps1", ".3f"),
                                                                             ("eps2", ".3f"))]  # fmt: skip
        search = [r["search_s"] for r in rs if r["search_s"] is not None]
        search = f"{np.median(search):.0f}" if search else "-"
        seeds = ",".join(f"{r['seed']}{'*' if r['load_before'][0] > max_load else ''}" for r in rs)
        lines.append(f"| `{v}` | {lever} | {seeds} | {fmt(stat(rs, 'wall_s'), '.1f')} | "
                     f"{search} | {ev} | {int(np.median([r['points'] for r in rs]))} | {fmt(stat(rs, 'eps1'), '.3f')} | "
                     f"{fmt(stat(rs, 'eps2'), '.3f')} | {fmt(stat(rs, 'hv'), '.4f')} | {' | '.join(delta)} | "
                     f"{load} |")  # fmt: skip
    lines += ["", "Per run (stages: global candidates / CMA-ES generations / local rounds / plain rounds):", "",
              "| variant | seed | wall (s) | evaluations | stages | epsilon 0.1-10 V | epsilon 0.5-10 V | "
              "hypervolume / reference's | lowest chattering_hf (V) at rms_error <= 0.1 / 0.01 / 0.001 rad | "
              "uptime before |", "|---|---:|---:|---:|---|---:|---:|---:|---:|---|"]  # fmt: skip
    for r in sorted(runs, key=lambda r: (list(VARIANTS).index(r["variant"]), r["seed"])):
        st = r["stages"]
        stages = f"{st['candidates']} / {st['cma_generations']} / {st['local_rounds']} / {st['plain_rounds']}"
        reached = " / ".join(f"{r['reach'][f'{lim:g}']:.3g}" for lim in budget_guide.LEVELS)
        high = " (started above the load limit)" if r["load_before"][0] > max_load else ""
        lines.append(f"| `{r['variant']}` | {r['seed']}{high} | {r['wall_s']:.1f} | {r['evaluations']:,} + "
                     f"{r['plain_evaluations']:,} | {stages} | {r['eps1']:.3f} | {r['eps2']:.3f} | {r['hv']:.4f} | "
                     f"{reached} | {r['uptime_before'].strip()} |")  # fmt: skip
    lines += ["", "How each variant is run (every command from the repository root, `fosmc` = `.venv/bin/fosmc` or "
              "`python -m fosmc_jax`; `FOSMC_JAX_CACHE` = a new empty folder unless said otherwise; the "
              "wrapper is `python -c \"$CHILD\" '<JSON>'` with `CHILD` in `tuning/front_ablation.py`: it sets "
              "fields of `fosmc_jax._search.front.Settings` in the child process, where the CLI has no flag):", ""]  # fmt: skip
    for v, (_, how) in VARIANTS.items():
        rs = [r for r in runs if r["variant"] == v]
        if rs:
            r = rs[0]
            env = " ".join(f"{k}={x}" for k, x in r["env"].items())
            wrap = f" [wrapper `{json.dumps(r['wrapper'])}`]" if r["wrapper"] else ""
            lines.append(f"- `{v}`: {how}. Seed {r['seed']}: `{(env + ' ') if env else ''}{r['command']}`{wrap}")
    return "\n".join(lines) + "\n"


#: The md's hand-written part: everything from this line on is kept when the md is written again.
NOTES = "## Notes (by hand)"


def write_md(path: pathlib.Path, text: str) -> None:
    """Write the generated md, keeping the hand-written part of the one there (from :data:`NOTES`)."""
    old = path.read_text() if path.exists() else ""
    path.write_text(text + ("\n" + old[old.index(NOTES) :] if NOTES in old else ""))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--reference", required=True, help="reference.json of tuning/reference_front.py")
    ap.add_argument("--budget", type=float, default=60.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--max-load", type=float, default=3.5, help="1-minute load above which a run is repeated")
    ap.add_argument("--wait", type=float, default=120.0, help="seconds to wait for the load before a run")
    ap.add_argument("--resume", action="store_true", help="keep the runs of the json, skip those (variant, seed)")
    ap.add_argument("--keep", help="folder for the runs' fronts and caches (default: a temporary one)")
    ap.add_argument("--out", default=str(HERE / "results" / "front_ablation"), help="json/md path without suffix")
    ap.add_argument("--report", action="store_true", help="only write the md from the json")
    args = ap.parse_args(argv)
    if args.report:
        path = pathlib.Path(args.out)
        write_md(path.with_suffix(".md"), markdown(json.loads(path.with_suffix(".json").read_text()), args.max_load))
        return
    reference = json.loads(pathlib.Path(args.reference).read_text())
    out = pathlib.Path(args.out)
    base = pathlib.Path(args.keep or tempfile.mkdtemp(prefix="front_ablation_"))
    base.mkdir(parents=True, exist_ok=True)
    command = "python tuning/front_ablation.py " + " ".join(argv if argv is not None else sys.argv[1:])
    data = {
        "commands": [command],
        "config": args.config,
        "reference": args.reference,
        "budget": args.budget,
        "runs": [],
    }
    if args.resume and out.with_suffix(".json").exists():
        old = json.loads(out.with_suffix(".json").read_text())
        data["runs"], data["commands"] = old["runs"], [*old.get("commands", [old.get("command")]), command]
    for s in args.seeds:
        for v in args.variants:
            if any(r["variant"] == v and r["seed"] == s for r in data["runs"]):
                continue
            data["runs"].append(one(v, s, args, base, data["runs"], reference))
            out.with_suffix(".json").write_text(json.dumps(data, indent=1, default=float))
            write_md(out.with_suffix(".md"), markdown(data, args.max_load))
    log(f"wrote {out}.json and {out}.md")


if __name__ == "__main__":
    main()
