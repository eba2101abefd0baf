"""Does ``fosmc select`` judged on the held-out batch pick points that hold on arms neither batch saw?

For a ``fosmc front`` front.json of a config with sampled arms (``[arm.uncertainty]``), at each
chattering bound C (``--bounds``): the point ``fosmc_jax.search.select(front, max_chattering=C)``
picks judged on the training batch alone (``held_out=False``, the choice before) and on the larger
of its training and held-out means (the default); each pick is evaluated on two batches that
neither the search nor the held-out check saw:

    third    fresh arms (``[arm.uncertainty] seed`` + 2) at payloads 2, 4, 6 and 8 kg
    corners  every corner of the uncertainty box (``sampling = "vertices"``) at the training payloads

Per pick: its mean rms_error on training, held-out, third batch and corners (rad), and on the third
batch and the corners the worst rollout's rms_error (mean over joints) over its training mean and
the rollouts above twice it. Writes ``tuning/results/<stem>.md`` and ``.json``.

    .venv/bin/python tuning/select_held_out.py --front tuning/results/select_held_out_realistic_robust/front.json

(that front: ``.venv/bin/fosmc front --config tuning/configs/realistic_arm_robust.toml --budget 300
--seed 0 --out DIR``).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import fosmc_jax as fj  # noqa: E402
from fosmc_jax.io import write_text  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from held_out_split import per_rollout  # noqa: E402

BOUNDS = (0.3, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 3.0)  # V, mean chattering_hf
THIRD_PAYLOADS = [2.0, 4.0, 6.0, 8.0]  # kg: neither training's 0, 10 nor the held-out 1, 3, ..., 9


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--front", required=True, help="a fosmc front front.json with held-out metrics")
    ap.add_argument("--bounds", nargs="+", type=float, default=list(BOUNDS), help="max_chattering bounds, V")
    ap.add_argument("--chunk", type=int, default=16)
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--stem", default="select_held_out_realistic_robust")
    args = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    front = json.loads(pathlib.Path(args.front).read_text())
    cfg = fj.config.resolve(front["config"])
    if not cfg.arm.uncertainty.samples:
        raise SystemExit(f"select_held_out: {args.front}'s config samples no arms ([arm.uncertainty])")
    picks = []
    for c in args.bounds:
        for held in (False, True):
            try:
                r = fj.search.select(front, max_chattering=c, held_out=held)
            except ValueError as e:
                print(f"select_held_out: {c:g} V, held_out={held}: {e}", flush=True)
                continue
            picks.append({"bound": c, "judged_on": r["judged_on"], "index": r["index"]})
    idx = sorted({p["index"] for p in picks})
    pts = [front["points"][i] for i in idx]
    params = {k: np.asarray([p["params"][k] for p in pts], float) for k in pts[0]["params"]}
    mean = lambda p, key: float(np.mean([np.nan if x is None else x for x in p[key]["rms_error"]]))
    train = {i: mean(p, "metrics") for i, p in zip(idx, pts)}
    held = {i: mean(p, "held_out") for i, p in zip(idx, pts)}
    seed = cfg.arm.uncertainty.seed
    replace = fj.config.replace
    batches = {"third": replace(cfg, plant={"payloads": THIRD_PAYLOADS}, arm={"uncertainty": {"seed": seed + 2}}),
               "corners": replace(cfg, arm={"uncertainty": {"sampling": "vertices", "samples": 0}})}  # fmt: skip
    evals = {}
    for name, bcfg in batches.items():
        problem = fj.config.build(bcfg)
        res = per_rollout(problem, params, args.chunk, f"{name} ({problem.rollouts} rollouts)")
        rms = np.where(res["diverged"], np.nan, res["rms_error"].mean(2))  # (points, rollouts)
        ratio = rms / np.asarray([train[i] for i in idx])[:, None]
        evals[name] = {i: {"mean": float(np.nanmean(rms[n])), "worst_ratio": float(np.nanmax(ratio[n])),
                           "above_2x": int(np.sum(ratio[n] > 2)), "diverged": int(res["diverged"][n].sum()),
                           "rollouts": int(problem.rollouts)} for n, i in enumerate(idx)}  # fmt: skip
    rows = []
    for p in picks:
        i, t, c = p["index"], evals["third"][p["index"]], evals["corners"][p["index"]]
        pt = front["points"][i]
        p.update(chattering_hf=float(np.mean(pt["metrics"]["chattering_hf"])), training=train[i], held_out=held[i],
                 third=t, corners=c)  # fmt: skip
        rows.append(f"| {p['bound']:g} | {p['judged_on']} | {i} | {p['chattering_hf']:.3f} | {train[i]:.3g} | "
                    f"{held[i]:.3g} | {t['mean']:.3g} | {t['worst_ratio']:.3g} | {t['above_2x']}/{t['rollouts']} | "
                    f"{c['mean']:.3g} | {c['worst_ratio']:.3g} | {c['above_2x']}/{c['rollouts']} |")  # fmt: skip
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=HERE)
    command = " ".join([".venv/bin/python tuning/select_held_out.py", *(argv if argv is not None else sys.argv[1:])])
    text = "\n".join([
        "# `fosmc select` judged on training alone and on training and held-out",
        "",
        f"`{command}` at {commit.stdout.strip()} (load average {load0:.1f} at the start, "
        f"{os.getloadavg()[0]:.1f} at the end). The front: {args.front} ({len(front['points'])} points, config "
        f"payloads {list(cfg.plant.payloads)}, {cfg.arm.uncertainty.samples} sampled arms, held-out batch "
        f"{front.get('held_out_batch')}). Per chattering bound (V, mean chattering_hf): the point each judgement "
        "picks and its mean rms_error (rad) on training, on the held-out batch and on two batches neither saw: "
        f"the third (arm seed {seed + 2}, payloads {THIRD_PAYLOADS} kg) and every corner of the uncertainty box at "
        "the training payloads; worst: the worst rollout's rms_error (mean over joints) over the point's training "
        "mean; > 2x: rollouts above twice it.",
        "",
        "| bound, V | judged on | point | chattering_hf, V | training | held-out | third | third worst | "
        "third > 2x | corners | corners worst | corners > 2x |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
    ])  # fmt: skip
    out = pathlib.Path(args.out)
    write_text(out / f"{args.stem}.md", text)
    write_text(out / f"{args.stem}.json", json.dumps({"command": command, "picks": picks}, indent=1))
    print(text)


if __name__ == "__main__":
    main()
