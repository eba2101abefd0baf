"""What a tuner pays per candidate on a config (default tuning/configs/realistic_arm.toml),
without and with the native kernel, one command:

    python benchmarks/tuner_cost.py                                 # chunks of 64, 3 warm chunks, 2 gradients
    python benchmarks/tuner_cost.py --chunk 16 --chunks 2 --out /tmp/tuner_cost.json
    python benchmarks/tuner_cost.py --t-final 0.1 --chunk 8 --chunks 1 --grads 1   # a short trial

- **front:** ``fosmc front``'s evaluator: the problem built as ``fosmc_jax.config.study`` builds
  it (``fosmc_jax.config.tuning_problems``; the search stages evaluate the training problem), candidates
  drawn as its global stage draws them (``global_factors`` with the front's ``grid_share``,
  ``from_factors``), evaluated by an ``Evaluator`` in chunks of ``--chunk`` (compiled
  once: vmap over the candidates, split over every local device). The first
  chunk compiles: its time less a warm chunk's is the compile time. Then ``--chunks`` warm
  chunks: the cost per candidate is their median / ``--chunk``.
- **tune:** one value-and-grad of ``fosmc tune``'s loss as ``fosmc_jax.run_tune``
  builds it and ``fosmc_jax.search.tune`` compiles it (``make_loss`` on the training problem,
  the objective's scales from ``evaluate`` at the config's parameters,
  ``value_and_grad`` per gradient mode; ``tune.mode = "auto"`` compiles both and
  keeps the faster): the first call less a warm one is the compile time, then the median
  of ``--grads`` warm calls.

Each measurement runs in a fresh process as the CLI sets one up (``use_all_cores()``: one CPU
device per core, float64 available; ``XLA_FLAGS`` and ``JAX_NUM_CPU_DEVICES`` removed from
its environment), twice: with ``FOSMC_JAX_NATIVE=0`` (no native kernel) and with it unset
(the native kernel where it is built), so one command gives before and after. The 1-minute
load average is recorded with every timing. Prints a table; ``--out`` writes everything as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "tuning" / "configs" / "realistic_arm.toml"
ENVS = (("FOSMC_JAX_NATIVE=0", "0"), ("FOSMC_JAX_NATIVE unset", None))


def load() -> float:
    return round(os.getloadavg()[0], 2)


def config(path: str, t_final: float | None) -> dict:
    """The resolved config (``t_final``: ``[sim] t_final`` replaced, for short trials)."""
    from fosmc_jax import config as _config

    cfg = _config.load(path)
    return _config.replace(cfg, sim={"t_final": t_final}) if t_final else cfg


def rollouts(problem) -> int:
    """Rollouts per candidate: plants x initial states (x noise realizations)."""
    import jax

    n = jax.tree.leaves(problem.plants)[0].shape[0] * problem.X0s.shape[0]
    return n * (1 if problem.keys is None else problem.keys.shape[0])


def front_cost(cfg: dict, chunk: int, chunks: int, seed: int = 0, which: str = "train") -> dict:
    """``fosmc front``'s chunk evaluation: compile time and warm cost per candidate, on the
    training problem its search stages evaluate (``which = "train"``; since issue 22 a digital
    loop's trains with one step per controller sample) or on the plain problem (``[sim]``, on
    which every result is re-evaluated)."""
    import jax

    from fosmc_jax import config as _config
    from fosmc_jax import search as fs

    plain, train, p0 = _config.tuning_problems(cfg)
    train = plain if which == "plain" else train
    evaluate = fs.Evaluator(train)  # compiled by the first chunk
    space = fs.space_of(p0)
    params = fs.from_factors(p0, fs.global_factors(chunk * (chunks + 1), seed, fs.FrontSettings().grid_share, space))
    times, loads = [], []
    for i in range(chunks + 1):
        part = jax.tree.map(lambda x, i=i: x[i * chunk : (i + 1) * chunk], params)
        t0 = time.perf_counter()
        m = evaluate(part, chunk, log=lambda _: None)
        times.append(time.perf_counter() - t0)
        loads.append(load())
        print(f"  front: chunk {i + 1}/{chunks + 1} of {chunk}: {times[-1]:.2f} s{' (compiles)' if i == 0 else ''}  "
              f"load {loads[-1]}", flush=True)  # fmt: skip
    warm = statistics.median(times[1:])
    n = rollouts(train)
    return {"problem": which, "dt": float(train.dt), "chunk": chunk, "chunks": chunks,
            "devices": jax.local_device_count(), "rollouts_per_candidate": n,
            "n_steps": train.options["n_steps"], "integrator": train.options["integrator"],
            "precision": str(train.dt.dtype), "first_chunk_s": times[0], "compile_s": times[0] - warm,
            "chunk_s": warm, "chunk_s_all": times[1:], "ms_per_candidate": 1e3 * warm / chunk,
            "rollout_steps_per_s": chunk * n * train.options["n_steps"] / warm, "loads": loads,
            "diverged_last_chunk": int(m["diverged"].sum())}  # fmt: skip


def tune_cost(cfg: dict, grads: int) -> dict:
    """One value-and-grad of ``fosmc tune``'s loss per gradient mode the config's
    ``tune.mode`` lets it try: compile time and warm cost."""
    import jax

    from fosmc_jax import config as _config
    from fosmc_jax import search as fs

    tcfg = cfg["tune"]
    plain, problem, p0 = _config.tuning_problems(cfg)
    floor = None
    if tcfg["keep_gamma_bound"]:  # as run_tune: alpha, beta of the design model the controller is built on
        d = _config.design_summary(cfg)
        floor = fs.GammaFloor(d.alpha.value, d.beta.value, tcfg["gamma_bound_convention"])
    t0 = time.perf_counter()
    obj = fs.objective_of(tcfg, fs.evaluate(problem, p0)["metrics"])  # the objective's scales, as run_tune
    scales_s = time.perf_counter() - t0
    u0 = fs.to_internal(p0, plain.base, floor)
    loss = fs.make_loss(problem, obj, floor)
    out = {"n_steps": problem.options["n_steps"], "rollouts": rollouts(problem), "devices": jax.local_device_count(),
           "checkpoint_every": problem.options.get("checkpoint_every"), "mode": tcfg["mode"],
           "objective_scales_s": scales_s, "modes": {}}  # fmt: skip
    for mode in ("reverse", "forward") if tcfg["mode"] == "auto" else (tcfg["mode"],):
        f = fs.value_and_grad(loss, mode)
        t0 = time.perf_counter()
        jax.block_until_ready(f(u0))
        first = time.perf_counter() - t0
        times, loads = [], []
        for _ in range(grads):
            t0 = time.perf_counter()
            jax.block_until_ready(f(u0))
            times.append(time.perf_counter() - t0)
            loads.append(load())
        warm = statistics.median(times)
        out["modes"][mode] = {"first_call_s": first, "compile_s": first - warm, "value_and_grad_s": warm,
                              "all_s": times, "loads": loads}  # fmt: skip
        print(f"  tune: value-and-grad ({mode}): {warm:.3f} s (compile {first - warm:.1f} s)  load {loads}", flush=True)
    out["picked"] = min(out["modes"], key=lambda k: out["modes"][k]["value_and_grad_s"])
    return out


def child(args) -> None:
    """One measurement in this (fresh) process, set up as the CLI sets itself up."""
    from fosmc_jax import use_all_cores

    use_all_cores()
    import jax

    jax.config.update("jax_enable_x64", True)
    cfg = config(args.config, args.t_final)
    t0 = time.perf_counter()
    if args.child == "front":
        result = front_cost(cfg, args.chunk, args.chunks, which=args.problem)
    else:
        result = tune_cost(cfg, args.grads)
    result.update(wall_s=time.perf_counter() - t0, native_env=os.environ.get("FOSMC_JAX_NATIVE"), jax=jax.__version__)
    Path(args.child_out).write_text(json.dumps(result))


def measure(what: str, native: str | None, args, tmp: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES", "FOSMC_JAX_NATIVE")}
    if native is not None:
        env["FOSMC_JAX_NATIVE"] = native
    out = Path(tmp) / f"{what}-{native}.json"
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--child",
        what,
        "--child-out",
        str(out),
        "--config",
        str(args.config),
        "--chunk",
        str(args.chunk),
        "--chunks",
        str(args.chunks),
        "--grads",
        str(args.grads),
        "--problem",
        args.problem,
    ]
    if args.t_final:
        cmd += ["--t-final", str(args.t_final)]
    print(f"{what}, FOSMC_JAX_NATIVE={native if native is not None else '(unset)'}: load {load()}", flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, check=True)
    return dict(json.loads(out.read_text()), process_s=time.perf_counter() - t0)


def table(info: dict) -> str:
    res = info["results"]
    labels = [label for label, _ in ENVS]
    rows = []
    if "front" in info["what"]:
        f = res[labels[0]]["front"]
        rows.append((f"front: ms per candidate ({f['problem']} problem, chunks of {f['chunk']}, {f['devices']} "
                     f"devices, {f['rollouts_per_candidate']} rollouts x {f['n_steps']} steps of {f['dt']:g} s)",
                     [res[k]["front"]["ms_per_candidate"] for k in labels], "{:.1f}"))  # fmt: skip
        rows.append(("front: compile s", [res[k]["front"]["compile_s"] for k in labels], "{:.1f}"))
        rows.append(("front: load (per chunk)", [f"{min(res[k]['front']['loads'])}-{max(res[k]['front']['loads'])}"
                                                 for k in labels], "{}"))  # fmt: skip
    if "tune" in info["what"]:
        t = res[labels[0]]["tune"]
        for mode in t["modes"]:
            rows.append((f"tune: value-and-grad s ({mode}, {t['rollouts']} rollouts x {t['n_steps']} steps, "
                         f"checkpoint every {t['checkpoint_every']})",
                         [res[k]["tune"]["modes"][mode]["value_and_grad_s"] for k in labels], "{:.3f}"))  # fmt: skip
            rows.append((f"tune: compile s ({mode})", [res[k]["tune"]["modes"][mode]["compile_s"] for k in labels],
                         "{:.1f}"))  # fmt: skip
            rows.append((f"tune: load ({mode})", [f"{min(res[k]['tune']['modes'][mode]['loads'])}-"
                         f"{max(res[k]['tune']['modes'][mode]['loads'])}" for k in labels], "{}"))  # fmt: skip
        rows.append(("tune: mode kept (auto: the faster)", [res[k]["tune"]["picked"] for k in labels], "{}"))
    lines = [f"| measurement | {' | '.join(labels)} | ratio (=0 / unset) |", "|---|---|---|---|"]
    for name, values, fmt in rows:
        ratio = f"{values[0] / values[1]:.2f}x" if all(isinstance(v, float) for v in values) and values[1] else ""
        lines.append(f"| {name} | {' | '.join(fmt.format(v) for v in values)} | {ratio} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(CONFIG), help="TOML config (default: tuning/configs/realistic_arm.toml)")
    ap.add_argument("--chunk", type=int, default=64, help="candidates per chunk (default 64)")
    ap.add_argument("--chunks", type=int, default=3, help="warm chunks timed after the compiling one (default 3)")
    ap.add_argument("--grads", type=int, default=2, help="warm value-and-grad calls timed per mode (default 2)")
    ap.add_argument("--what", default="front,tune", help="front, tune or both (default front,tune)")
    ap.add_argument("--t-final", type=float, help="replace [sim] t_final (a short trial)")
    ap.add_argument(
        "--problem",
        choices=("train", "plain"),
        default="train",
        help="the front's problem timed: its training problem (default) or the plain one ([sim])",
    )
    ap.add_argument("--out", help="write the results as JSON")
    ap.add_argument("--child", choices=("front", "tune"), help=argparse.SUPPRESS)
    ap.add_argument("--child-out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return child(args)
    what = tuple(w for w in args.what.split(",") if w)
    uptime = lambda: subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    info = {"command": "python benchmarks/tuner_cost.py " + " ".join(sys.argv[1:] if argv is None else argv),
            "config": str(args.config), "t_final": args.t_final, "what": what, "cores": os.cpu_count(),
            "uptime_start": uptime(), "results": {}}  # fmt: skip
    print(f"start: {info['uptime_start']}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for w in what:  # the two environments back to back per measurement
            for label, native in ENVS:
                info["results"].setdefault(label, {})[w] = measure(w, native, args, tmp)
    info["uptime_end"] = uptime()
    info["table"] = table(info)
    print(f"end: {info['uptime_end']}\n\n{info['table']}")
    if args.out:
        Path(args.out).write_text(json.dumps(info, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
