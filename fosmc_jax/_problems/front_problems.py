"""What ``fosmc front``'s study evaluates, built once from a resolved config as one value: the
training and plain problems it searches on, the held-out batch every front point is checked on
(:func:`held_out_config`: what training did not see, which ``fosmc tune`` checks too), and the
paper's FOSMC on the config's batch beside them (the references)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

from .._simulator.problem import Problem
from .build import plain_problem, tuning_problems
from .resolve import as_config, replace
from .tables import Config

#: The references, by label: the switching of the paper's FOSMC run with Table 1's sets
#: (``None``: the config's own switching) and with SGN.
REFERENCES = {"Table 1": None, "SGN": "sign"}


def held_out_config(config: Config | dict) -> Config:
    """The config's batch with what training did not see: arm payloads between and beside the
    training ones (at 0.1, 0.3, ..., 0.9 of ``arm.payload_range``: 1, 3, 5, 7, 9 kg on the
    paper's arm, unless trained on; a front point tuned on 0 and 10 kg alone can lose a joint in
    between, tuning/README.md), fresh box samples (linear ``sample`` / ``vertices``), fresh
    sampled arms (``[arm.uncertainty]``), fresh ``[sample]`` draws and noise seeds."""
    cfg = as_config(config)
    plant = cfg.plant
    changes: dict[str, Any] = {"sample": {"seed": cfg.sample.seed + 1}, "sensors": {"seed": cfg.sensors.seed + 1}}
    if plant.kind == "arm":
        lo, hi = cfg.arm.payload_range
        fresh = [p for p in (lo + (hi - lo) * f for f in (0.1, 0.3, 0.5, 0.7, 0.9)) if p not in plant.payloads]
        changes["plant"] = {"payloads": fresh or [(plant.payloads[0] + (lo + hi) / 2) / 2]}
        changes["arm"] = {"uncertainty": {"seed": cfg.arm.uncertainty.seed + 1}}
    elif plant.uncertainty in ("sample", "vertices"):
        changes["plant"] = {"seed": plant.seed + 1}
    return replace(cfg, **changes)


def held_out_batch(held: Config) -> dict[str, Any]:
    """What :func:`held_out_config`'s batch ``held`` draws, for a result file: the plant's kind,
    payloads and box seed, the seeds of its sampled arms and ``[sample]`` draws."""
    unc = held.arm.uncertainty
    return {"kind": held.plant.kind, "payloads": list(held.plant.payloads), "seed": held.plant.seed,
            "arm_samples": unc.samples if held.plant.kind == "arm" else 0,
            "arm_seed": unc.seed, "sample_seed": held.sample.seed}  # fmt: skip


class FrontProblems(NamedTuple):
    """A config's problems for ``fosmc front`` (and what describes them in front.json)."""

    config: Config  # the resolved config
    plain: Problem  # [sim]'s problem: every front point is evaluated on it
    train: Problem  # the one the search trains on (fosmc_jax._problems.build.tuning_problems)
    p0: Any  # the config's values of its kind's parameters
    held_out: Problem  # the plain problem of held_out_config: what training did not see
    held_out_batch: dict[str, Any]  # what that batch draws, for front.json
    references: dict[str, Problem | None]  # REFERENCES' labels: the paper's FOSMC (None: ``plain`` is it)


def front_problems(config: str | Path | dict | Config) -> FrontProblems:
    """The :class:`FrontProblems` of a config: each config resolved and each problem built once."""
    cfg = as_config(config)
    plain, train, p0 = tuning_problems(cfg)
    held = held_out_config(cfg)
    references = {}
    for label, switching in REFERENCES.items():
        reference = replace(cfg, controller={"switching": switching or cfg.controller.switching, "kind": "fosmc"})
        own = switching is None and reference == cfg  # the config's own controller: the plain problem is it
        references[label] = None if own else plain_problem(reference)
    return FrontProblems(cfg, plain, train, p0, plain_problem(held), held_out_batch(held), references)
