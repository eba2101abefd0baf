"""``fosmc bounds`` as a function: the design model's bounds and gains."""

from __future__ import annotations

from typing import Any

from .. import _problems as problems
from .._design import paper as _paper
from .shared import (
    ConfigInput,
    Log,
    _quiet,
    _with_x64,
    config_of,
)


@_with_x64
def run_bounds(config: ConfigInput = None, *, log: Log = _quiet) -> dict[str, Any]:
    """``fosmc bounds``: for the config's design model (``[model] from``, ``config.design_model``:
    the paper's rows and ``[plant.box]``, or the rows derived from ``[arm]``), alpha, beta (31)
    by exact vertex enumeration of its box, K placing the poles (16) (the K the simulated
    controller uses), eig(A + BK), CB, and the gamma lower bounds (24)-(26) in both
    conventions, beside the paper's printed numbers.

    Returns ``{"model": "paper" | "arm", "model_detail": where its rows come from, "alpha",
    "beta", "vertices_checked": {"A", "B"}, "K": (3, 9), "closed_loop_poles": [[re, im]] x 9,
    "CB": (3, 3), "gamma_min": {convention: (3,)}, "gamma", "paper_printed": {"alpha", "beta",
    "gamma_min"}}``; for ``kind = "arm"`` also ``"models"``: ``{"paper": ..., "arm": ...}``, the
    same quantities (alpha to gamma_min) for both models whichever is in use, ``"box"`` and
    ``"nominal_A_rows"``, ``"nominal_B_rows"``: the arm's box and nominal rows, and
    ``"arm_model"``: where they come from.
    """
    cfg = config_of(config)
    used = cfg.model.source
    sources = ("paper", "arm") if cfg.plant.kind == "arm" else (used,)
    designs, summaries = {}, {}
    for source in sources:
        designs[source] = problems.design_model(cfg, source)
        log(f"fosmc bounds: the {source} model ({designs[source].sampled}): alpha, beta by vertex enumeration ...")
        summaries[source] = problems.design_summary(cfg, source)

    def quantities(d) -> dict[str, Any]:
        return {
            "alpha": d.alpha.value,
            "beta": d.beta.value,
            "vertices_checked": {"A": d.alpha.vertices_checked, "B": d.beta.vertices_checked},
            "K": d.K,
            "closed_loop_poles": [[z.real, z.imag] for z in d.closed_loop_poles],
            "CB": d.CB,
            "gamma_min": d.gamma_min,
        }

    out = {
        "model": used,
        "model_detail": designs[used].sampled,
        **quantities(summaries[used]),
        "gamma": list(cfg.controller.gamma),
        "paper_printed": {
            "alpha": _paper.ALPHA_PRINTED,
            "beta": _paper.BETA_PRINTED,
            "gamma_min": _paper.GAMMA_MIN_PRINTED,
        },
    }
    if "arm" in designs:
        arm = designs["arm"]
        out["models"] = {source: quantities(d) for source, d in summaries.items()}
        out["box"] = dict(zip(problems.BOX_KEYS, arm.box))
        out["nominal_A_rows"], out["nominal_B_rows"] = arm.A_rows, arm.B_rows
        out["arm_model"] = arm.sampled
    return out
