"""Every command's outputs on fixed inputs, fingerprinted: the check that a restructure changed
no number (run it on the tree before and the tree after, then compare the two folders).

    # one tree (a checkout, e.g. `git worktree add /tmp/before <commit>`): its package, this venv
    .venv/bin/python benchmarks/command_outputs.py run --tree /tmp/before --out /tmp/outputs_before
    .venv/bin/python benchmarks/command_outputs.py run --tree . --out /tmp/outputs_after
    .venv/bin/python benchmarks/command_outputs.py compare /tmp/outputs_before /tmp/outputs_after

The commands (every one with fixed sizes, so nothing depends on the clock): ``simulate --json``
on the paper's setup, tuning/configs/example.toml, realistic_arm.toml and the small_arm preset;
``bounds --json`` on the paper's setup and realistic_arm; ``certify --json`` on the paper's
setup and arm_ideal_set2; ``tune --steps 3`` on arm_set2; ``front --candidates 64 --steps 2`` on
example.toml and ``select`` on its front; ``export`` of realistic_arm; ``identify`` (R, Kt) on
the synthetic log of realistic_arm (:func:`fosmc_jax.identification_log` of this checkout's
package, whichever tree runs; no bootstrap);
``reproduce`` (the paper's figures and tables). Each command runs ``python -m fosmc_jax`` in a
fresh process with the tree first on ``PYTHONPATH``. ``manifest.json`` holds a SHA-256 per
output (the output folder's name replaced in every file): of the bytes for figures and C files,
of the JSON without its volatile fields (versions, wall times, loads, paths: :data:`VOLATILE`).
``compare`` recomputes them from the two folders, prints every output whose fingerprint differs
and, for JSON, the first differing paths; it exits 1 where any differs.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: JSON keys whose values are the run's circumstances, not its numbers.
VOLATILE = re.compile(r"(^fosmc_jax$|version|seconds|wall|elapsed|time_s|^time$|load|date|commit|^out$|path|command)")
CONFIGS = "tuning/configs"
LOG = "identify_log.csv"

#: (name, command line after ``fosmc``, the file its stdout goes to or None); ``{out}`` is the
#: output folder.
COMMANDS = [
    ("simulate_paper", ["simulate", "--json"], "simulate_paper.json"),
    ("simulate_example", ["simulate", "--config", f"{CONFIGS}/example.toml", "--json"], "simulate_example.json"),
    ("simulate_realistic", ["simulate", "--config", f"{CONFIGS}/realistic_arm.toml", "--json"],
     "simulate_realistic.json"),
    ("simulate_small_arm", ["simulate", "--config", "small_arm", "--json"], "simulate_small_arm.json"),
    ("bounds_paper", ["bounds", "--json"], "bounds_paper.json"),
    ("bounds_realistic", ["bounds", "--config", f"{CONFIGS}/realistic_arm.toml", "--json"], "bounds_realistic.json"),
    ("certify_paper", ["certify", "--json"], "certify_paper.json"),
    ("certify_ideal_set2", ["certify", "--config", f"{CONFIGS}/arm_ideal_set2.toml", "--json"],
     "certify_ideal_set2.json"),
    ("tune", ["tune", "--config", f"{CONFIGS}/arm_set2.toml", "--steps", "3", "--out", "{out}/tune"], None),
    ("front", ["front", "--config", f"{CONFIGS}/example.toml", "--candidates", "64", "--steps", "2", "--out",
               "{out}/front"], None),
    ("select", ["select", "--front", "{out}/front/front.json", "--max-error", "1e-3", "--json"], "select.json"),
    ("export", ["export", "--config", f"{CONFIGS}/realistic_arm.toml", "--out", "{out}/export"], None),
    ("identify", ["identify", "--config", f"{CONFIGS}/realistic_arm.toml", "--data", "{out}/" + LOG, "--params",
                  "R,Kt", "--payload", "0", "--bootstrap", "0", "--out", "{out}/identify", "--json"],
     "identify.json"),
    ("reproduce", ["reproduce", "--out", "{out}/reproduce"], None),
]  # fmt: skip


def _stable(x):
    """JSON ``x`` without its :data:`VOLATILE` keys."""
    if isinstance(x, dict):
        return {k: _stable(v) for k, v in x.items() if not VOLATILE.search(str(k))}
    if isinstance(x, list):
        return [_stable(v) for v in x]
    return x


def fingerprint(path: Path, out: Path) -> str:
    """SHA-256 of an output of the run in ``out``, its folder's name replaced (identify writes it)."""
    data = path.read_bytes().replace(str(out).encode(), b"{out}")
    if path.suffix == ".json":
        try:
            data = json.dumps(_stable(json.loads(data)), sort_keys=True).encode()
        except json.JSONDecodeError:
            pass
    return hashlib.sha256(data).hexdigest()


def run(tree: Path, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": str(tree), "MPLBACKEND": "Agg"}
    log_script = (f"import jax; jax.config.update('jax_enable_x64', True); import fosmc_jax; "
                  f"fosmc_jax.identification_log('{CONFIGS}/realistic_arm.toml', "
                  f"{str(out / LOG)!r})")  # fmt: skip
    # identify's log from this checkout's package whatever the tree: the same input for both trees
    subprocess.run([sys.executable, "-c", log_script], cwd=ROOT, env={**env, "PYTHONPATH": str(ROOT)}, check=True)
    times = {}
    for name, argv, stdout in COMMANDS:
        argv = [a.replace("{out}", str(out)) for a in argv]
        t0 = time.perf_counter()
        print(f"[{time.strftime('%H:%M:%S')}] {name}: fosmc {' '.join(argv)}", flush=True)
        r = subprocess.run([sys.executable, "-m", "fosmc_jax", *argv], cwd=tree, env=env, capture_output=True)
        if r.returncode != 0:
            sys.exit(f"{name} failed ({r.returncode}): {r.stderr.decode()[-2000:]}")
        if stdout:
            (out / stdout).write_bytes(r.stdout)
        times[name] = round(time.perf_counter() - t0, 1)
    manifest = fingerprints(out)
    (out / "manifest.json").write_text(json.dumps({"tree": str(tree), "files": manifest, "seconds": times}, indent=1))
    print(f"{len(manifest)} outputs fingerprinted in {out / 'manifest.json'} ({sum(times.values()):.0f} s)")


def fingerprints(out: Path) -> dict[str, str]:
    files = sorted(p for p in out.rglob("*") if p.is_file() and p.name not in ("manifest.json", "checkpoint.npz"))
    return {str(p.relative_to(out)): fingerprint(p, out) for p in files}


def _first_differences(a, b, where="", limit=5) -> list[str]:
    if type(a) is not type(b):
        return [f"{where or '/'}: {type(a).__name__} against {type(b).__name__}"]
    if isinstance(a, dict):
        found = [f"{where}/{k}: only in one" for k in sorted(set(a) ^ set(b))]
        for k in sorted(set(a) & set(b)):
            found += _first_differences(a[k], b[k], f"{where}/{k}", limit)
        return found[:limit]
    if isinstance(a, list):
        if len(a) != len(b):
            return [f"{where}: {len(a)} against {len(b)} entries"]
        found = []
        for i, (x, y) in enumerate(zip(a, b)):
            found += _first_differences(x, y, f"{where}[{i}]", limit)
            if len(found) >= limit:
                break
        return found[:limit]
    return [] if a == b else [f"{where}: {a!r} against {b!r}"]


def compare(a: Path, b: Path) -> int:
    fa, fb = fingerprints(a), fingerprints(b)  # again, from the files: the current normalization
    differ = sorted(k for k in set(fa) | set(fb) if fa.get(k) != fb.get(k))
    for k in differ:
        print(f"differs: {k}" + ("" if k in fa and k in fb else " (only in one)"))
        if k.endswith(".json") and k in fa and k in fb:
            try:
                ja, jb = (_stable(json.loads((d / k).read_text().replace(str(d), "{out}"))) for d in (a, b))
            except json.JSONDecodeError:
                continue
            for line in _first_differences(ja, jb):
                print(f"    {line}")
    print(f"{len(set(fa) | set(fb)) - len(differ)} of {len(set(fa) | set(fb))} outputs identical")
    return 1 if differ else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    r = sub.add_parser("run", help="run every command of a tree; fingerprint its outputs")
    r.add_argument("--tree", default=str(ROOT), help="the checkout whose package runs (default: this one)")
    r.add_argument("--out", required=True, help="a new or empty folder")
    c = sub.add_parser("compare", help="compare two run folders")
    c.add_argument("a")
    c.add_argument("b")
    args = ap.parse_args()
    if args.what == "run":
        run(Path(args.tree).resolve(), Path(args.out).resolve())
        return 0
    return compare(Path(args.a).resolve(), Path(args.b).resolve())


if __name__ == "__main__":
    sys.exit(main())
