"""Did a front run's search visit the reference's basin where it falls short, and what did it
find there? For the reference points in a band of chattering_hf, the nearest candidate the run
evaluated (its ``checkpoint.npz``: every training candidate's log10 factors ``z`` and metrics)
in the max norm over the factors, and the training metrics of the candidates within a radius:

    .venv/bin/fosmc front --config tuning/configs/realistic_arm.toml --seed 1 --out /tmp/front_s1
    .venv/bin/python tuning/basin_probe.py --config realistic_arm --run /tmp/front_s1 --band 0.3 0.45

The reference points' factors are their parameters over the config's (``fosmc_jax.search.to_factors``);
the axes are the front's (mean ``rms_error`` E, mean ``chattering_hf`` C). Prints the factors' medians
(reference and the run's front in the band), the distances, the nearest candidates' metrics, and the
E quantiles of the candidates within ``--radius`` of the reference point nearest to the history.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from reference_front import params_of  # noqa: E402

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]


def factors(p0, points: list[dict]) -> np.ndarray:
    """The log10 factors (n, 9) of front points over the start p0."""
    return fs.to_factors(p0, params_of(points, p0))


def in_band(points: list[dict], lo: float, hi: float) -> list[dict]:
    return [p for p in points if lo <= np.mean(p["metrics"]["chattering_hf"]) <= hi]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True, help="a name in tuning/configs (its reference too)")
    ap.add_argument("--run", required=True, help="a fosmc front --out folder (front.json, checkpoint.npz)")
    ap.add_argument("--band", nargs=2, type=float, required=True, metavar=("LO", "HI"), help="chattering_hf, V")
    ap.add_argument("--radius", type=float, default=0.3, help="log10, max over the factors (default 0.3)")
    args = ap.parse_args()
    _, _, p0 = _config.tuning_problems(_config.load(ROOT / "tuning" / "configs" / f"{args.config}.toml"))
    reference = json.loads((ROOT / "tuning/results/reference" / args.config / "reference.json").read_text())
    run = pathlib.Path(args.run)
    ref = in_band(reference["points"], *args.band)
    own = in_band(json.loads((run / "front.json").read_text())["points"], *args.band)
    zr, zf = factors(p0, ref), factors(p0, own)
    np.set_printoptions(precision=2, suppress=True, linewidth=150)
    print(f"{len(ref)} reference points and {len(own)} of the run's front in {args.band[0]}-{args.band[1]} V")
    print("factors (delta 1-3, gamma 1-3, poles 1-3), median: reference", np.median(zr, 0))
    print("                                                  the run's", np.median(zf, 0))
    ck = np.load(run / "checkpoint.npz")
    z = ck["z"]
    e, c = fs.axes({k[2:]: ck[k] for k in ck.files if k.startswith("m.")})
    dist = np.array([np.abs(z - r).max(1) for r in zr])  # (reference points, candidates)
    nearest = dist.argmin(1)
    d = dist[np.arange(len(zr)), nearest]
    print(f"{len(z)} candidates evaluated; distance to the nearest, per reference point: median {np.median(d):.3f}, "
          f"{d.min():.3f}-{d.max():.3f}")  # fmt: skip
    ref_e = [np.mean(p["metrics"]["rms_error"]) for p in ref]
    ref_c = [np.mean(p["metrics"]["chattering_hf"]) for p in ref]
    for i in np.argsort(d)[:3]:
        j = nearest[i]
        print(f"reference E {ref_e[i]:.3g} rad C {ref_c[i]:.3g} V at {zr[i]}\n"
              f"  nearest ({d[i]:.3f}): E {e[j]:.3g} rad C {c[j]:.3g} V at {z[j]}")  # fmt: skip
    i = int(np.argmin(d))
    near = dist[i] < args.radius
    q = np.nanquantile(e[near], [0.1, 0.5, 0.9])
    print(f"{int(near.sum())} candidates within {args.radius} of that reference point: E quantiles 10/50/90% "
          f"{q[0]:.3g} / {q[1]:.3g} / {q[2]:.3g} rad")  # fmt: skip
    band = (c >= args.band[0]) & (c <= args.band[1])
    print(f"best E in the band: the run's candidates {np.nanmin(np.where(band, e, np.nan)):.3g} rad (training), "
          f"its front {min(np.mean(p['metrics']['rms_error']) for p in own):.3g}, the reference {min(ref_e):.3g}")  # fmt: skip


if __name__ == "__main__":
    main()
