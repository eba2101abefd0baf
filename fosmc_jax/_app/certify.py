"""``fosmc certify`` and its API: the hitting condition (20) checked numerically for a resolved
config (:mod:`fosmc_jax._certificate.hitting` does the numerics), and the verdicts on the gamma
bounds (24)-(26)."""

from __future__ import annotations

import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._certificate.hitting import (
    Certificate,
    argmax,
    arm_values,
    box_max_hitting,
    box_values,
    s_directions,
    vertex_values,
    z_samples,
)
from .._controllers import KINDS
from .._design.box import code_of, vertex_codes, vertices_from_codes
from .._design.gains import CONVENTIONS
from .._problems import (
    Config,
    ConfigError,
    arm_params_of,
    as_config,
    box_of,
    controller_of,
    design_summary,
    reference_of,
)
from .shared import ConfigInput, Log, _is_integer, _quiet, _with_x64, config_of


def certify(
    config: ConfigInput,
    *,
    gamma=None,
    plant: str | None = None,
    switching: str = "sign",
    law: str | None = None,
    n_times: int | None = None,
    n_z: int | None = None,
    z_scales=(0.05, 0.5, 5.0),
    n_s: int = 38,
    s_norms=None,
    vertices: str | int = "all",
    n_payloads: int = 11,
    seed: int = 0,
) -> Certificate:
    """Check the hitting condition (20) numerically for a config (a resolved
    :class:`fosmc_jax.config.Config`, or any form ``fosmc_jax.config.as_config`` takes) of the
    paper's ideal loop (a digital loop's config is refused with a ``ConfigError``).

    Sampled points (defaults: ``n_times`` 81, ``n_z`` 200 on the linear plant, 21 and 30 on the
    arm, whose rows cost a model evaluation per point): ``n_times`` instants evenly over
    [0, sim.t_final]; tracking errors Z from
    :func:`z_samples` with ``n_z`` random ones inside the envelope |Z_i| <= scale of its state
    component (``z_scales`` = (theta rad, theta' rad/s, theta'' rad/s^2), same for each joint);
    s directions from :func:`s_directions` (26 sign patterns + ``n_s - 26`` random), times each
    norm in ``s_norms`` (default (1,) for ``sign``, where |s| does not matter; else
    (0.1, 1, 10, 100) x max(delta)). Plants: ``plant`` (default the config's plant.kind):
    ``linear``: the box of the config's design model (``[plant.box]``, or the arm's with
    ``model.from = "arm"``), ``vertices = "all"`` (exact, closed form) or an int N (N explicit
    vertices, seeded sample); ``arm``: the config's ``[arm]``
    at ``n_payloads`` payloads evenly over its ``payload_range``, its true rows
    ``third_order_rows`` at X = X_d + Z. ``switching`` defaults to ``sign`` (the theorem's law;
    pass the config's ``controller.switching`` to check what is simulated); ``law`` defaults to
    the config's. The controller is the config's, on its design model's nominal rows
    (``[model] from``). ``gamma`` (3,) overrides controller.gamma. Deterministic given ``seed``.
    Runs in float64.
    """
    cfg = as_config(config)
    plant, law = _checked(cfg, plant or cfg.plant.kind, n_s), law or cfg.controller.law
    n_times = n_times if n_times is not None else (81 if plant == "linear" else 21)
    n_z = n_z if n_z is not None else (200 if plant == "linear" else 30)
    rng = np.random.default_rng(seed)
    scales = np.tile(np.asarray(z_scales, dtype=np.float64), 3)
    with jax.enable_x64(True):
        ctrl, ref = controller_of(cfg, jnp.float64, gamma), reference_of(cfg, jnp.float64)
        if s_norms is None:
            s_norms = (1.0,) if switching == "sign" else tuple(float(np.max(ctrl.delta)) * k for k in (0.1, 1, 10, 100))
        times = np.linspace(0.0, cfg.sim.t_final, n_times)
        Zs = z_samples(n_z, scales, rng)
        dirs = s_directions(n_s - 26, rng)
        S = np.concatenate([r * dirs for r in s_norms])
        envelope = {
            "times": f"{n_times} evenly over [0, {cfg.sim.t_final:g}] s",
            "Z": f"0, +-scale_i e_i and {n_z} uniform-radius points of the ellipsoid with semi-axes "
            f"{list(z_scales)} (theta rad, theta' rad/s, theta'' rad/s^2) per joint",
            "s": f"{len(dirs)} directions (26 sign patterns + {n_s - 26} random) x norms {list(s_norms)}",
            "switching": switching,
            "law": law,
            "gamma": np.asarray(ctrl.gamma).tolist(),
            "seed": seed,
        }
        derivs = jax.vmap(ref)(jnp.asarray(times))  # (T, 4, 3)
        grid = _Grid(ctrl, derivs, jnp.asarray(Zs), jnp.asarray(S), switching, law, len(times) * len(Zs) * len(S))
        if plant == "linear" and vertices == "all":
            found = _over_the_box(grid, box_of(cfg))
        elif plant == "linear":
            found = _over_vertices(grid, box_of(cfg), int(vertices), rng)
        else:
            found = _over_payloads(grid, cfg, n_payloads)
        vmax, (it, iz, i_s), where, label, points, evaluations = found
        vmax = float(vmax)
        where = {"t": float(times[it]), "Z": Zs[iz].tolist(), "s": S[i_s].tolist(), **where}
    return Certificate(vmax, bool(vmax < 0), int(points), int(evaluations), where, label, plant, envelope)


def _checked(cfg: Config, plant: str, n_s: int) -> str:
    """``plant``, once the config is one :func:`certify` checks (the FOSMC's ideal loop) and
    ``plant`` and ``n_s`` are in range."""
    if not KINDS[cfg.controller.kind].hitting_condition:
        raise ConfigError(f"controller.kind: certify checks the FOSMC's hitting condition (20), not kind = "
                          f"'{cfg.controller.kind}'")  # fmt: skip
    if cfg.controller.sample_period:
        raise ConfigError(
            "controller.sample_period: certify checks the hitting condition (20) of the ideal, continuous-time "
            "loop; a digital loop (sample_period > 0: sampling, sensors, delay, saturation) cannot be certified "
            "this way (set sample_period = 0)"
        )
    if plant not in ("linear", "arm"):
        raise ValueError(f"plant must be 'linear' or 'arm', got {plant!r}")
    if n_s < 26:
        raise ValueError(f"n_s must be at least 26 (the sign patterns), got {n_s}")
    return plant


class _Grid(NamedTuple):
    """The sampled points of :func:`certify`: the controller, the reference's derivatives at
    the instants (T, 4, 3), the errors Z (nZ, 9) and s values (nS, 3), the law, and the count
    of (instant, Z, s) points."""

    ctrl: Any
    derivs: Any
    Z: Any
    S: Any
    switching: str
    law: str
    n_points: int


def _box_size(box) -> int:
    """The number m of the box's rows that vary (2^m vertices)."""
    return int(sum(np.count_nonzero(hi - lo > 0) for lo, hi in (box[:2], box[2:])))


def _over_the_box(grid: _Grid, box):
    """The largest value over the whole box, exactly (closed form per point): (max, its
    (instant, Z, s) indices, its vertex, label, points covered, evaluations)."""
    m = _box_size(box)
    boxj = tuple(jnp.asarray(b) for b in box)
    values = box_values(grid.ctrl, grid.derivs, grid.Z, grid.S, boxj, grid.switching, grid.law)  # (T, nZ, nS)
    vmax, k = argmax(values)
    it, iz, i_s = np.unravel_index(int(k), values.shape)
    _, a_v, b_v = box_max_hitting(grid.ctrl, grid.derivs[it], grid.Z[iz], grid.S[i_s], boxj, grid.switching, grid.law)
    a_v, b_v = np.asarray(a_v), np.asarray(b_v)
    code = code_of(np.concatenate([a_v, b_v], 1), np.concatenate(box[::2], 1), np.concatenate(box[1::2], 1))
    where = {"vertex_code": code, "A_rows": a_v.tolist(), "B_rows": b_v.tolist()}
    label = f"all 2^{m} vertices (exact closed-form maximum over the box)"
    return vmax, (it, iz, i_s), where, label, grid.n_points * 2**m, grid.n_points


def _over_vertices(grid: _Grid, box, n_vertices: int, rng):
    """The largest value over ``n_vertices`` explicit vertices of the box (a seeded sample):
    as :func:`_over_the_box`'s."""
    m = _box_size(box)
    lo, hi = np.concatenate(box[::2], 1), np.concatenate(box[1::2], 1)
    codes = vertex_codes(m, n_vertices, rng)
    V = vertices_from_codes(codes, lo, hi)
    values = vertex_values(grid.ctrl, grid.derivs, grid.Z, grid.S, jnp.asarray(V[:, :, :9]), jnp.asarray(V[:, :, 9:]),
                            grid.switching, grid.law)  # fmt: skip
    vmax, k = argmax(values)
    iv, it, iz, i_s = np.unravel_index(int(k), values.shape)
    where = {"vertex_code": int(codes[iv]), "A_rows": V[iv, :, :9].tolist(), "B_rows": V[iv, :, 9:].tolist()}
    label = ("all" if codes.size == 2**m else f"sampled {codes.size} of 2^{m}") + " vertices (seeded)"
    return vmax, (it, iz, i_s), where, label, grid.n_points * codes.size, grid.n_points * codes.size


def _over_payloads(grid: _Grid, cfg: Config, n_payloads: int):
    """The largest value over the config's arm at ``n_payloads`` payloads evenly over its
    ``payload_range``: as :func:`_over_the_box`'s."""
    payload_range = tuple(cfg.arm.payload_range)
    payloads = np.linspace(*payload_range, n_payloads)
    params = arm_params_of(cfg, jnp.float64)
    values = arm_values(grid.ctrl, grid.derivs, grid.Z, grid.S, params, jnp.asarray(payloads), grid.switching,
                        grid.law)  # (P, T, nZ, nS)  # fmt: skip
    vmax, k = argmax(values)
    ip, it, iz, i_s = np.unravel_index(int(k), values.shape)
    where = {"payload": float(payloads[ip])}
    label = f"arm at {n_payloads} payloads evenly over {payload_range} kg"
    return vmax, (it, iz, i_s), where, label, grid.n_points * n_payloads, grid.n_points * n_payloads


# ---------------------------------------------------------------------------- gamma bounds


class BoundVerdict(NamedTuple):
    """Whether the gamma bound of one convention was sufficient / necessary in this example."""

    convention: str
    bound: list[float]  # (3,) lower bounds (24)-(26)
    max_hitting_above: float  # at gamma = (1 + eps) bound
    max_hitting_below: float  # at gamma = (1 - eps) bound
    sufficient: bool  # (20) held at every point checked with gamma = (1 + eps) bound
    necessary: bool  # (20) failed somewhere with gamma = (1 - eps) bound
    verdict: str  # "sufficient and necessary", "sufficient, not necessary", "necessary, not sufficient", "neither"


def gamma_verdicts(cfg: Config, eps: float = 0.01, **options) -> tuple[dict[str, float], list[BoundVerdict]]:
    """For each convention of (24)-(26) (``CONVENTIONS``), :func:`certify` at gamma = (1 +- eps)
    times the bound computed from the config's design model (``config.design_model``: its
    box, alpha and beta by vertex enumeration, and its nominal rows) and the poles. ``options``
    go to :func:`certify`. Returns ({alpha, beta}, verdicts).

    "Sufficient in this example" = no violation found above the bound (a sampled check, not a
    proof); "necessary" = a violation found just below it.
    """
    d = design_summary(cfg)
    out = []
    for c in CONVENTIONS:
        bound = np.asarray(d.gamma_min[c], dtype=np.float64)
        above = certify(cfg, gamma=(1 + eps) * bound, **options)
        below = certify(cfg, gamma=(1 - eps) * bound, **options)
        suff, nec = above.holds, not below.holds
        verdict = {
            (True, True): "sufficient and necessary",
            (True, False): "sufficient, not necessary",
            (False, True): "necessary, not sufficient",
            (False, False): "neither",
        }[(suff, nec)]  # fmt: skip
        out.append(BoundVerdict(c, bound.tolist(), above.max_hitting, below.max_hitting, suff, nec, verdict))
    return {"alpha": d.alpha.value, "beta": d.beta.value}, out


def critical_scale(cfg: Config, direction, lo: float = 0.0, hi: float = 64.0, iters: int = 12, **options) -> float:
    """Smallest lambda in [lo, hi] (bisection, ``iters`` steps) such that :func:`certify` holds
    with gamma = lambda * ``direction`` (3,); +inf if it fails at ``hi``. Assumes the check is
    monotone in lambda along the ray (it is for ``sign`` where larger gamma only adds a term
    that the sampled worst points oppose; the bisection does not verify this)."""
    direction = np.asarray(direction, dtype=np.float64)
    if not certify(cfg, gamma=hi * direction, **options).holds:
        return float("inf")
    for _ in range(iters):
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if certify(cfg, gamma=mid * direction, **options).holds else (mid, hi)
    return hi


def report(cfg: Config, eps: float = 0.01, verdicts: bool = True, **options) -> dict[str, Any]:
    """JSON-ready summary for ``fosmc certify``: :func:`certify` at the config's gamma (keys
    ``max_hitting``, ``holds``, ``points_checked``, ``evaluations``, ``where``, ``vertices``,
    ``plant``, ``envelope``) and, if ``verdicts``, ``gamma_bounds``: alpha, beta and one
    :class:`BoundVerdict` per convention (:func:`gamma_verdicts` with the same ``options``)."""
    out = certify(cfg, **options)._asdict()
    if verdicts:
        ab, vs = gamma_verdicts(cfg, eps, **options)
        out["gamma_bounds"] = {**ab, "eps": eps, "conventions": [v._asdict() for v in vs]}
    return out


@_with_x64
def run_certify(
    config: ConfigInput = None,
    *,
    vertices: int | str = "all",
    configured_switching: bool = False,
    seed: int = 0,
    log: Log = _quiet,
) -> dict[str, Any]:
    """``fosmc certify``: the hitting condition (20), s^T ds/dt < 0, checked numerically
    along the reference over sampled errors and sliding directions, over the whole box
    (``vertices = "all"``, exact) or ``vertices`` sampled vertices, or over the payload range
    for the arm; and the verdicts on the gamma bounds (24)-(26) of each convention.

    SGN switching unless ``configured_switching`` (then ``controller.switching``).
    Returns ``fosmc_jax._app.certify.report``'s dict (``max_hitting``, ``holds``,
    ``points_checked``, ``evaluations``, ``where``, ``vertices``, ``plant``, ``envelope``,
    ``gamma_bounds``): what ``--json`` prints.
    """
    if not (_is_integer(seed) and seed >= 0):
        raise ConfigError(f"--seed: expected a non-negative integer, got {seed}")
    cfg = config_of(config)
    switching = cfg.controller.switching if configured_switching else "sign"
    opts = {"switching": switching, "seed": seed}
    if vertices != "all":
        count = vertices if isinstance(vertices, int) and not isinstance(vertices, bool) else None
        if isinstance(vertices, str) and vertices.isdigit():
            count = int(vertices)
        if count is None or count < 1:
            raise ConfigError(f"--vertices: expected 'all' or a positive integer, got {vertices!r}")
        opts["vertices"] = count
    log(f"fosmc certify: {cfg.plant.kind} plant, {switching} switching ...")
    start = time.perf_counter()
    r = report(cfg, **opts)
    log(f"fosmc certify: done in {time.perf_counter() - start:.1f} s")
    return r
