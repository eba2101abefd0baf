"""``fosmc front --gradient-share`` against the front without gradient steps and against pymoo's
NSGA-II, at equal wall time, over seeds.

Each run is a fresh process: ``fosmc front --gradient-share G`` (the CLI; the share 0: the front
without gradient steps), and ``tuning/reference_front.py build`` for NSGA-II (``--method nsga2 --popsize P``: :func:`fosmc_jax.search.nsga2` through
the package's evaluator), every one with the same budget, JAX's persistent compilation cache in
``$FOSMC_JAX_CACHE``/xla (warm caches for every method alike; compilation inside every budget),
round-robin over seeds (seed 0 of every config and variant, then seed 1, ...) so that the shared
machine's load drift reaches every variant alike. Each front is scored against the config's
reference (``tuning/results/reference/<config>/reference.json``: the epsilon in log10 over the
reference points with chattering_hf in 0.1-10 V and 0.5-10 V, the hypervolume).

    .venv/bin/python tuning/front_gradient.py --configs realistic_arm unseen_arm --shares 0 0.25 0.4 \\
        --peers nsga2:64 --seeds 0 1 2 --budget 105 --runs /tmp/front_gradient --out tuning/results/front_gradient
    .venv/bin/python tuning/front_gradient.py --report-only --out tuning/results/front_gradient

``--boxes narrow kind`` runs every variant in another box (:data:`BOXES`; the run's process
re-registers the FOSMC kind with it, ``fosmc_jax.search.register``: white-box, the registry's kinds
are not public) and in the kinds' own:

    .venv/bin/python tuning/front_gradient.py --shares 0.25 --peers nsga2:64 nsga2:256 --boxes narrow kind \
        --budget 60 --runs /tmp/front_box --out tuning/results/front_box_60s

(``front_box_60s`` was run as ``--boxes kind wide`` when the kind's box was the narrow one.)

``--nsga2-shares 0 0.25`` adds the front on NSGA-II (``fosmc front --search nsga2 --gradient-share G``;
``--shares`` is the staged search's); ``--train-shares 0.25`` the same with the gradient steps on
the training surrogate (``--gradient-on train``):

    .venv/bin/python tuning/front_gradient.py --shares 0.25 --nsga2-shares 0 0.25 --peers nsga2:256 \
        --budget 60 --runs /tmp/front_nsga2_60 --out tuning/results/front_nsga2_60s

``--plain-shares 0`` adds each ``--nsga2-shares`` variant with that share of plain rounds
(``--plain-share``; with a training surrogate the rest of the search goes to NSGA-II):

    .venv/bin/python tuning/front_gradient.py --shares --nsga2-shares 0.25 --plain-shares 0 --peers \
        --budget 300 --runs /tmp/plain_share --out tuning/results/front_300s_plain_share

``--unions 2`` also scores the union of every two seeds' fronts of each config and variant (two
runs of 150 s against one of 300 s: whether restarts would pay):

    .venv/bin/python tuning/front_gradient.py --configs realistic_arm --shares --nsga2-shares 0.25 --peers \
        --seeds 10 11 12 13 14 15 --budget 150 --unions 2 --runs /tmp/islands --out tuning/results/front_150s_unions

A run whose files are already in ``--runs`` is scored, not run again (a killed study resumes);
``--score-only`` re-scores the runs in ``--runs`` (against a rebuilt reference) and stops at a
missing one instead of running it.
Writes OUT.json (per run: config, variant, seed, scores, wall time, load) and OUT.md (the median
per config and variant); ``--findings FILE``: a markdown text the report keeps.
"""

from __future__ import annotations

import argparse
import itertools
import json
import pathlib
import subprocess
import sys
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
import reference_front  # noqa: E402

from fosmc_jax.io import jsonable, write_text  # noqa: E402

log = reference_front.log


#: Other boxes of log factors than the kinds' own (``--boxes``): a run in one re-registers the FOSMC
#: kind with it in its own process (:func:`_in_box`), the way a user's script would.
BOXES = {
    "wide": {"delta": (-3.0, 3.0), "gamma": (-2.5, 1.0), "poles": (0.0, 3.0)},  # the kind's since d9f7323
    "narrow": {"delta": (-3.0, 1.5), "gamma": (-0.5, 0.5), "poles": (0.0, 2.0)},  # the kind's before
    # the wide box's faces the rebuilt references lie on or past (gamma's lower on joint 1, delta's
    # upper on unseen_arm): a third of their points; docs/tuning.md "The box"
    "wider": {"delta": (-3.0, 4.5), "gamma": (-4.5, 1.0), "poles": (0.0, 3.0)},
}


def _in_box(box: str, argv: list[str]) -> int:
    """Run ``argv`` (``fosmc ...`` or ``reference_front.py ...``) in this process with the FOSMC
    kind's box replaced by ``BOXES[box]``."""
    import runpy

    import fosmc_jax.search as fs
    from fosmc_jax._controllers import KINDS

    kind = KINDS["fosmc"]
    params = tuple(p._replace(box=BOXES[box][p.name]) for p in kind.space.params)
    fs.register(kind._replace(space=kind.space._replace(params=params)))
    if argv[0] == "fosmc":
        sys.argv = ["fosmc", *argv[1:]]
        try:
            runpy.run_module("fosmc_jax", run_name="__main__")
        except SystemExit as e:
            return int(e.code or 0)
        return 0
    reference_front.main(argv[1:])
    return 0


def _variant_files(runs: pathlib.Path, config: str, variant: str, seed: int) -> tuple[pathlib.Path, pathlib.Path]:
    """A run's folder and the file scored in it: ``g<G>`` the CLI's front.json, ``front`` and
    ``nsga2:<P>`` a ``build`` method json."""
    folder = runs / config / f"{variant.replace(':', '')}_s{seed}"
    return folder, folder / ("nsga2.json" if variant.startswith("nsga2") else "front.json")


def _points(path: str | pathlib.Path) -> list[dict]:
    """A run's front points with no diverged rollout."""
    return [p for p in next(iter(reference_front.points_of(path).values())) if not p["diverged"]]


def unions(rows: list[dict], k: int) -> list[dict]:
    """The scores of the union of the fronts of every ``k`` seeds of one config and variant (what
    k independent runs reach together: the islands question, k runs of budget / k against one
    run of the budget)."""
    out = []
    for config, variant in dict.fromkeys((r["config"], r["variant"]) for r in rows):
        mine = sorted((r for r in rows if (r["config"], r["variant"]) == (config, variant)), key=lambda r: r["seed"])
        reference = json.loads((reference_front.OUT / config / "reference.json").read_text())
        for combo in itertools.combinations(mine, k):
            pts = [p for r in combo for p in _points(r["file"])]
            scores = reference_front.score(reference_front.axes(pts), reference)
            out.append({"config": config, "variant": variant, "seeds": [r["seed"] for r in combo], **scores})
    return out


def run(config: str, variant: str, seed: int, budget: float, runs: pathlib.Path, score_only: bool = False) -> dict:
    folder, result = _variant_files(runs, config, variant, seed)
    path = f"tuning/configs/{config}.toml"
    wall = None
    if not result.exists() and score_only:
        raise SystemExit(f"front_gradient: --score-only: no run {result} (leave out its variant or seed)")
    if not result.exists():
        folder.mkdir(parents=True, exist_ok=True)
        name, _, box = variant.partition("@")
        if name.startswith(("g", "ng", "tg")) or name == "front":  # "front": the CLI without gradient steps
            share, _, plain = ("0" if name == "front" else name.lstrip("nt")[1:]).partition("p")
            search = ["--search", "nsga2" if name.startswith(("ng", "tg")) else "staged"]
            on = ["--gradient-on", "train"] if name.startswith("tg") else []
            cmd = [str(ROOT / ".venv/bin/fosmc"), "front", "--config", path, "--budget", f"{budget:g}", "--seed",
                   str(seed), "--gradient-share", share, *search, *on, *(["--plain-share", plain] if plain else []),
                   "--out", str(folder), "--force"]  # fmt: skip
        else:
            method, _, pop = name.partition(":")
            cmd = [sys.executable, str(HERE / "reference_front.py"), "build", "--config", path, "--method", method,
                   "--budget", f"{budget:g}", "--seed", str(seed), "--out", str(folder),
                   *(["--popsize", pop] if pop else [])]  # fmt: skip
        if box:  # the same command, run by this script in the box
            inner = ["fosmc", *cmd[1:]] if cmd[1] == "front" else ["reference_front.py", *cmd[2:]]
            cmd = [sys.executable, __file__, "--in-box", box, "--", *inner]
        env = reference_front.cache_env()
        load0, t0 = reference_front.load_text(), time.perf_counter()
        with open(folder / "run.log", "w") as out:
            subprocess.run(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT, check=True)
        wall = time.perf_counter() - t0
        (folder / "run.json").write_text(json.dumps({"load_start_end": [load0, reference_front.load_text()],
                                                     "wall_s": wall, "command": cmd}))  # fmt: skip
    meta = json.loads((folder / "run.json").read_text()) if (folder / "run.json").exists() else {}
    reference = json.loads((reference_front.OUT / config / "reference.json").read_text())
    pts = _points(result)
    scores = reference_front.score(reference_front.axes(pts), reference)
    data = json.loads(result.read_text())
    stages = data.get("stages", {})
    return {"config": config, "variant": variant, "seed": seed, "budget_s": budget, "file": str(result),
            "points": len(pts), "gradient_steps": stages.get("gradient_steps"), "from_gradient": stages.get("from_gradient"),
            "evaluations": stages.get("evaluations", data.get("evaluations")),  # a front's: on its training problem
            "wall_s": meta.get("wall_s", data.get("wall_s")), "load_start_end": meta.get("load_start_end", data.get("load_start_end")),
            **scores}  # fmt: skip


def report(data: dict, out: pathlib.Path) -> None:
    rows = data["runs"]
    lines = ["# The front with gradient steps, at equal wall time", "",
             f"Generated by `tuning/front_gradient.py` from `{out.with_suffix('.json').name}` (`--report-only` regenerates it). "
             f"Command: `{data['command']}`; code {data['code']['commit'][:10]}. Epsilon: additive, log10, against the config's "
             "reference front over its points with chattering_hf in the band; lower is better; reached at: the chattering_hf of "
             "the reference point where the 0.1-10 V epsilon is reached, per seed. HV: hypervolume in log10 "
             "(higher is better; the reference's own in the header).", ""]  # fmt: skip
    for config in dict.fromkeys(r["config"] for r in rows):
        mine = [r for r in rows if r["config"] == config]
        lines += [f"## {config} (reference HV {mine[0]['reference_hypervolume']:.3f})", "",
                  "| variant | epsilon 0.1-10 V per seed | median | reached at (V) | epsilon 0.5-10 V median | median gap | HV median | gradient steps | points from gradient steps | evaluations | wall s | load (1-min, start) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for variant in dict.fromkeys(r["variant"] for r in mine):
            rs = sorted((r for r in mine if r["variant"] == variant), key=lambda r: r["seed"])
            med = lambda k, rs=rs: float(np.median([r[k] for r in rs]))
            steps = ", ".join(str(r["gradient_steps"]) for r in rs) if rs[0]["gradient_steps"] is not None else "-"
            grad = ", ".join(str(r["from_gradient"]) for r in rs) if rs[0]["from_gradient"] is not None else "-"
            base, _, box = variant.partition("@")
            if base == "front":
                name = "front (no gradient steps)"
            elif base.startswith("g"):
                name = f"front --gradient-share {base[1:]}"
            elif base.startswith("ng"):
                share, _, plain = base[2:].partition("p")
                name = f"front --search nsga2 --gradient-share {share}" + (f" --plain-share {plain}" if plain else "")
            elif base.startswith("tg"):
                name = f"front --search nsga2 --gradient-share {base[2:]} --gradient-on train"
            else:
                name = f"pymoo NSGA-II, population {base.split(':')[1]}"
            name += f", box {box} ({', '.join(f'{k} 10^{list(v)}' for k, v in BOXES[box].items())})" if box else ""
            eps = ", ".join(f"{r['epsilon_0.1_10']:.4f}" for r in rs)
            at = ", ".join(f"{r['epsilon_at'][0]:.2f}" if r.get("epsilon_at") else "-" for r in rs)
            walls = ", ".join(f"{r['wall_s']:.0f}" for r in rs if r["wall_s"])
            evals = ", ".join(str(r.get("evaluations") or "-") for r in rs)
            loads = ", ".join(str(r["load_start_end"][0]).split()[0] for r in rs if r["load_start_end"])
            gap = f"{med('median_gap'):.4f}" if all("median_gap" in r for r in rs) else "-"
            lines.append(f"| {name} | {eps} | **{med('epsilon_0.1_10'):.4f}** | {at} | {med('epsilon_0.5_10'):.4f} | "
                         f"{gap} | {med('hypervolume'):.3f} | {steps} | {grad} | {evals} | {walls} | {loads} |")  # fmt: skip
        lines.append("")
        us = [u for u in data.get("unions", []) if u["config"] == config]
        if us:
            lines += [f"Unions of {len(us[0]['seeds'])} seeds' fronts (`--unions`):", "",
                      "| variant | seeds | epsilon 0.1-10 V | reached at (V) | median gap | HV |", "|---|---|---|---|---|---|"]  # fmt: skip
            for u in us:
                at = f"{u['epsilon_at'][0]:.2f}" if u.get("epsilon_at") else "-"
                lines.append(f"| {u['variant']} | {', '.join(map(str, u['seeds']))} | {u['epsilon_0.1_10']:.4f} | {at} | "
                             f"{u.get('median_gap', float('nan')):.4f} | {u['hypervolume']:.3f} |")  # fmt: skip
            for variant in dict.fromkeys(u["variant"] for u in us):
                eps = [u["epsilon_0.1_10"] for u in us if u["variant"] == variant]
                lines.append(f"| {variant}: median of {len(eps)} unions | | **{np.median(eps):.4f}** | | | |")
            lines.append("")
    if data.get("findings"):
        lines += ["## Findings", "", data["findings"]]
    write_text(out.with_suffix(".md"), "\n".join(lines) + "\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", nargs="+", default=["realistic_arm", "unseen_arm"])
    ap.add_argument("--shares", nargs="*", type=float, default=[0.0, 0.25, 0.4], help="0: the front without them")
    ap.add_argument("--nsga2-shares", nargs="*", type=float, default=[],
                    help="also the front on NSGA-II (--search nsga2) with these gradient shares")  # fmt: skip
    ap.add_argument("--train-shares", nargs="*", type=float, default=[],
                    help="also the front on NSGA-II with gradient steps on the training surrogate (--gradient-on train)")  # fmt: skip
    ap.add_argument("--plain-shares", nargs="*", type=float, default=[],
                    help="also the --nsga2-shares variants with these plain rounds' shares (--plain-share)")  # fmt: skip
    ap.add_argument("--peers", nargs="*", default=["nsga2:64"], help="NSGA-II populations as nsga2:P")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--budget", type=float, default=105.0)
    ap.add_argument("--runs", default="/tmp/front_gradient", help="folder of the runs' files (outside the repository)")
    ap.add_argument("--out", default=str(HERE / "results" / "front_gradient"))
    ap.add_argument("--findings")
    ap.add_argument(
        "--unions",
        type=int,
        default=0,
        metavar="K",
        help="also score the union of every K seeds' fronts of each config and variant",
    )
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--score-only", action="store_true", help="score the runs in --runs; run none")
    ap.add_argument(
        "--boxes",
        nargs="+",
        default=["kind"],
        choices=["kind", *BOXES],
        help="the boxes each variant runs in (kind: the kinds' own)",
    )
    ap.add_argument("--in-box", choices=list(BOXES), help=argparse.SUPPRESS)  # a run's own process (run)
    ap.add_argument("argv", nargs="*", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.in_box:
        return _in_box(args.in_box, args.argv)
    out = pathlib.Path(args.out).resolve()
    if args.report_only:
        data = json.loads(out.with_suffix(".json").read_text())
    else:
        variants = [("front" if g == 0 else f"g{g:g}") for g in args.shares] + [f"ng{g:g}" for g in args.nsga2_shares]
        variants += [f"ng{g:g}p{p:g}" for g in args.nsga2_shares for p in args.plain_shares]
        variants += [f"tg{g:g}" for g in args.train_shares]
        variants += list(args.peers)
        variants = [v + ("" if box == "kind" else f"@{box}") for v in variants for box in args.boxes]
        rows = []
        for seed in args.seeds:
            for config in args.configs:
                for variant in variants:
                    log(f"{config} {variant} seed {seed}: load {reference_front.load_text()}")
                    rows.append(run(config, variant, seed, args.budget, pathlib.Path(args.runs), args.score_only))
                    log(f"  epsilon {rows[-1]['epsilon_0.1_10']:.4f} / {rows[-1]['epsilon_0.5_10']:.4f}, "
                        f"HV {rows[-1]['hypervolume']:.3f}")  # fmt: skip
        command = " ".join([".venv/bin/python", "tuning/front_gradient.py", *sys.argv[1:]])
        data = {"command": command, "code": reference_front.code_state(), "runs": rows}
        if args.unions:
            data["unions"] = unions(rows, args.unions)
    if args.findings:
        data["findings"] = pathlib.Path(args.findings).read_text()
    write_text(out.with_suffix(".json"), json.dumps(jsonable(data), indent=1))
    report(data, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
