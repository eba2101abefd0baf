"""A numerical certificate of the hitting condition (20): s^T ds/dt / ||s|| < 0 away from s = 0.

Theorem 4.1 claims that the control (23) with gamma above the bounds (24)-(26) makes (20) hold
for every plant in the box. NOTES.md items 4-5 say the bounds cannot be taken on trust (norm
conventions, (1 + beta) where the usual argument needs (1 - beta)); this module checks (20)
itself, at sampled points, and reports the worst one.

Algebra. With Z = X - X_d, s = C Z - w (14) and w' = (CA + CBK) Z, (17) is
ds/dt = C Z' - C (A + BK) Z. Rows other than 3, 6, 9 of A, B are the same integrator chains in
the true and the nominal model, and X_d' = A X_d + B Omega (10) holds with the chains exactly,
so the chain parts cancel and only rows 3, 6, 9 are left:

    ds/dt = C_r ( a X + b U - theta_d''' - (A_r + B_bar K) Z ),     C_r = C[:, (3, 6, 9)],

with (a, b) the true rows 3, 6, 9 (a box vertex, or the arm's third_order_rows at X) and
U = Omega - (CB)^-1 rho f(s) [+ K Z] (23), rho = gamma_1 ||Z|| + gamma_2 ||X_d|| + gamma_3 ||Omega||.
Because w is a free integral state, the direction of s is independent of Z: both are sampled.

The box. For fixed (t, Z, s) the control does not depend on the plant, so s^T ds/dt is affine
in the entries of (a, b): its maximum over the box is at the vertex that sets each entry to the
bound that makes its term w_i X_j a_ij (resp. w_i U_j b_ij, w = C_r^T s) largest. The linear
certificate therefore covers *all* 2^m vertices (indeed the whole box) exactly, in closed form;
``vertices=N`` instead evaluates N explicit vertices (seeded sample, or all of them if fewer),
which the tests use to cross-check the closed form.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .._app.config import ConfigError, box_of, controller_of, reference_of
from .._controllers.fosmc import Controller, Derived, derive, safe_norm, switch
from .._design import paper as _paper
from .._design.gains import CONVENTIONS, summarize
from .._plants.arm import ARM_PARAMS, PAYLOAD_RANGE, Arm, third_order_rows
from .._plants.reference import desired_state, feedforward

# ---------------------------------------------------------------------------- array level


class Terms(NamedTuple):
    """What ds/dt needs at one (t, Z), independent of s and of the true plant."""

    X: Array  # (9,) true state X_d + Z
    rho: Array  # scalar, gamma_1 ||Z|| + gamma_2 ||X_d|| + gamma_3 ||Omega||
    U0: Array  # (3,) the control without its switching part: Omega [+ K Z]
    r: Array  # (3,) theta_d''' + (A_r + B_bar K) Z


def terms(ctrl: Controller, derived: Derived, derivatives: Array, Z: Array, law: str = "paper") -> Terms:
    """:class:`Terms` at reference ``derivatives`` (4, 3) (a reference's output at t) and
    tracking error ``Z`` (9,), with the controller's nominal model for Omega (10)."""
    X_d = desired_state(derivatives)
    Omega = feedforward(ctrl.a_rows, ctrl.b_rows, derivatives)
    rho = ctrl.gamma[0] * safe_norm(Z) + ctrl.gamma[1] * safe_norm(X_d) + ctrl.gamma[2] * safe_norm(Omega)
    U0 = Omega + derived.K @ Z if law == "equivalent" else Omega
    r = derivatives[3] + (ctrl.a_rows + ctrl.b_rows @ derived.K) @ Z
    return Terms(X_d + Z, rho, U0, r)


def control(ctrl: Controller, derived: Derived, tm: Terms, s: Array, switching: str = "sign") -> Array:
    """U (3,) of (23) at sliding variable ``s`` (3,), volts."""
    return tm.U0 - derived.CB_inv @ (tm.rho * switch(s, ctrl.delta, switching))


def hitting(
    ctrl: Controller,
    derivatives: Array,
    Z: Array,
    s: Array,
    a_true: Array,
    b_true: Array,
    switching: str = "sign",
    law: str = "paper",
) -> Array:
    """s^T ds/dt / ||s|| of (20) for the true rows ``a_true`` (3, 9), ``b_true`` (3, 3) (units of
    s per second). ``derivatives`` (4, 3) is the reference at t, ``Z`` (9,), ``s`` (3,) non-zero.
    (20) holds at this point where the value is negative."""
    derived = derive(ctrl)
    tm = terms(ctrl, derived, derivatives, Z, law)
    U = control(ctrl, derived, tm, s, switching)
    w = ctrl.C[:, list(_paper.ROWS)].T @ s
    return w @ (a_true @ tm.X + b_true @ U - tm.r) / jnp.linalg.norm(s)


def box_max_hitting(
    ctrl: Controller,
    derivatives: Array,
    Z: Array,
    s: Array,
    box: tuple[Array, Array, Array, Array],
    switching: str = "sign",
    law: str = "paper",
) -> tuple[Array, Array, Array]:
    """max over the whole box (A_lower, A_upper, B_lower, B_upper) of :func:`hitting`, exact
    (closed form: the function is affine in the box entries). Returns the value and the rows
    (3, 9), (3, 3) of a maximising vertex."""
    derived = derive(ctrl)
    tm = terms(ctrl, derived, derivatives, Z, law)
    U = control(ctrl, derived, tm, s, switching)
    w = ctrl.C[:, list(_paper.ROWS)].T @ s
    A_lo, A_hi, B_lo, B_hi = box
    ca, cb = jnp.outer(w, tm.X), jnp.outer(w, U)
    a = jnp.where(ca > 0, A_hi, A_lo)
    b = jnp.where(cb > 0, B_hi, B_lo)
    value = (jnp.sum(ca * a) + jnp.sum(cb * b) - w @ tm.r) / jnp.linalg.norm(s)
    return value, a, b


# ---------------------------------------------------------------------------- sampling


def s_directions(n_random: int, rng: np.random.Generator) -> np.ndarray:
    """Unit directions of s, (26 + n_random, 3): the 26 sign patterns in {-1, 0, 1}^3 \\ {0}
    (axes +-, the 12 edge diagonals, the 8 orthant diagonals), normalised, then random ones."""
    grid = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T
    grid = grid[np.any(grid != 0, axis=1)].astype(float)
    rand = rng.standard_normal((n_random, 3))
    out = np.concatenate([grid, rand])
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def z_samples(n_random: int, scales: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Tracking errors Z, (1 + 18 + n_random, 9): Z = 0, the 18 axis points +-scales_i e_i, and
    n_random points scales * r u, u uniform on the unit sphere of R^9, r uniform in [0, 1]."""
    axes = np.concatenate([np.diag(scales), -np.diag(scales)])
    u = rng.standard_normal((n_random, 9))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    rand = scales * rng.uniform(0.0, 1.0, (n_random, 1)) * u
    return np.concatenate([np.zeros((1, 9)), axes, rand])


def vertex_codes(m: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """All 2^m vertex codes if 2^m <= n, else n distinct ones drawn with ``rng`` (int64)."""
    if 2**m <= n:
        return np.arange(2**m, dtype=np.int64)
    codes = np.unique(rng.integers(0, 2**m, size=2 * n, dtype=np.int64))
    while codes.size < n:
        codes = np.unique(np.concatenate([codes, rng.integers(0, 2**m, size=n, dtype=np.int64)]))
    return rng.permutation(codes)[:n]


def vertices_from_codes(codes: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Box vertices (len(codes), *lower.shape): bit j of a code sets free entry j (the j-th entry,
    in C order, with lower < upper) to its upper bound."""
    free = np.flatnonzero((upper - lower).ravel() > 0)
    bits = (codes[:, None] >> np.arange(free.size)) & 1
    out = np.broadcast_to(lower.ravel(), (codes.size, lower.size)).copy()
    out[:, free] = np.where(bits == 1, upper.ravel()[free], lower.ravel()[free])
    return out.reshape((codes.size,) + lower.shape)


def _code_of(vertex: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> int:
    free = np.flatnonzero((upper - lower).ravel() > 0)
    v, hi = vertex.ravel()[free], upper.ravel()[free]
    return int(sum(1 << j for j in range(free.size) if v[j] == hi[j]))


# ---------------------------------------------------------------------------- certificate


class Certificate(NamedTuple):
    """Outcome of :func:`certify`.

    ``max_hitting``: the largest s^T ds/dt / ||s|| found (units of s per second); (20) holds at
    every point checked iff it is negative (``holds``). ``points_checked``: (t, Z, s, plant)
    points covered; for the linear plant with ``vertices = "all"`` each (t, Z, s) covers all
    2^m vertices exactly (``evaluations`` counts the closed-form maxima computed). ``where``:
    the worst point: t (s), Z (9,), s (3,) unit, and the vertex (its code and rows) or the
    payload (kg). ``vertices``: which plants were checked, in words.
    """

    max_hitting: float
    holds: bool
    points_checked: int
    evaluations: int
    where: dict[str, Any]
    vertices: str
    plant: str
    envelope: dict[str, Any]


_STATIC = ("switching", "law")


@functools.partial(jax.jit, static_argnames=_STATIC)
def _box_values(ctrl, derivs, Zs, S, box, switching, law):
    """box_max_hitting over the grid derivs (T, 4, 3) x Zs (nZ, 9) x S (nS, 3): (T, nZ, nS)."""
    one = lambda d, Z, s: box_max_hitting(ctrl, d, Z, s, box, switching, law)[0]
    return jax.lax.map(lambda d: jax.vmap(lambda Z: jax.vmap(lambda s: one(d, Z, s))(S))(Zs), derivs)


@functools.partial(jax.jit, static_argnames=_STATIC)
def _vertex_values(ctrl, derivs, Zs, S, Va, Vb, switching, law):
    """hitting at every vertex (Va (V, 3, 9), Vb (V, 3, 3)) x the grid: (V, T, nZ, nS)."""
    one = lambda d, Z, s, a, b: hitting(ctrl, d, Z, s, a, b, switching, law)
    per_v = lambda a, b: jax.lax.map(
        lambda d: jax.vmap(lambda Z: jax.vmap(lambda s: one(d, Z, s, a, b))(S))(Zs), derivs
    )
    return jax.lax.map(lambda ab: per_v(*ab), (Va, Vb))


@functools.partial(jax.jit, static_argnames=_STATIC)
def _arm_values(ctrl, derivs, Zs, S, params, payloads, switching, law):
    """hitting on the arm (rows third_order_rows at X_d + Z) per payload x the grid: (P, T, nZ, nS)."""

    def per_payload(mass):
        arm = Arm(params, mass)

        def at(d, Z):
            a, b = third_order_rows(arm, desired_state(d) + Z)
            return jax.vmap(lambda s: hitting(ctrl, d, Z, s, a, b, switching, law))(S)

        return jax.lax.map(lambda d: jax.vmap(lambda Z: at(d, Z))(Zs), derivs)

    return jax.lax.map(per_payload, payloads)


@jax.jit
def _argmax(v: Array) -> tuple[Array, Array]:
    k = jnp.argmax(v)
    return v.ravel()[k], k


def certify(
    cfg: dict,
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
    """Check the hitting condition (20) numerically for a resolved config (``_config.resolve``)
    of the paper's ideal loop (a digital loop's config is refused with a ``ConfigError``).

    Sampled points (defaults: ``n_times`` 81, ``n_z`` 200 on the linear plant, 21 and 30 on the
    arm, whose rows cost a model evaluation per point): ``n_times`` instants evenly over
    [0, sim.t_final]; tracking errors Z from
    :func:`z_samples` with ``n_z`` random ones inside the envelope |Z_i| <= scale of its state
    component (``z_scales`` = (theta rad, theta' rad/s, theta'' rad/s^2), same for each joint);
    s directions from :func:`s_directions` (26 sign patterns + ``n_s - 26`` random), times each
    norm in ``s_norms`` (default (1,) for ``sign``, where |s| does not matter; else
    (0.1, 1, 10, 100) x max(delta)). Plants: ``plant`` (default the config's plant.kind):
    ``linear``: the config's box around model.A_rows/B_rows, ``vertices = "all"`` (exact,
    closed form) or an int N (N explicit vertices, seeded sample); ``arm``: the arm of
    :mod:`fosmc_jax._plants.arm` at ``n_payloads`` payloads evenly over PAYLOAD_RANGE, its true rows
    ``third_order_rows`` at X = X_d + Z. ``switching`` defaults to ``sign`` (the theorem's law;
    pass the config's ``controller.switching`` to check what is simulated); ``law`` defaults to
    the config's. ``gamma`` (3,) overrides controller.gamma. Deterministic given ``seed``.
    Runs in float64.
    """
    if cfg["controller"]["kind"] != "fosmc":
        raise ConfigError(f"controller.kind: certify checks the FOSMC's hitting condition (20), not kind = "
                          f"'{cfg['controller']['kind']}'")  # fmt: skip
    if cfg["controller"]["sample_period"]:
        raise ConfigError(
            "controller.sample_period: certify checks the hitting condition (20) of the ideal, continuous-time "
            "loop; a digital loop (sample_period > 0: sampling, sensors, delay, saturation) cannot be certified "
            "this way (set sample_period = 0)"
        )
    plant = plant or cfg["plant"]["kind"]
    law = law or cfg["controller"]["law"]
    if plant not in ("linear", "arm"):
        raise ValueError(f"plant must be 'linear' or 'arm', got {plant!r}")
    if n_s < 26:
        raise ValueError(f"n_s must be at least 26 (the sign patterns), got {n_s}")
    n_times = n_times if n_times is not None else (81 if plant == "linear" else 21)
    n_z = n_z if n_z is not None else (200 if plant == "linear" else 30)
    rng = np.random.default_rng(seed)
    scales = np.tile(np.asarray(z_scales, dtype=np.float64), 3)
    with jax.enable_x64(True):
        ctrl, ref = controller_of(cfg, jnp.float64, gamma), reference_of(cfg, jnp.float64)
        if s_norms is None:
            s_norms = (1.0,) if switching == "sign" else tuple(float(np.max(ctrl.delta)) * k for k in (0.1, 1, 10, 100))
        times = np.linspace(0.0, cfg["sim"]["t_final"], n_times)
        Zs = z_samples(n_z, scales, rng)
        dirs = s_directions(n_s - 26, rng)
        S = np.concatenate([r * dirs for r in s_norms])
        envelope = {
            "times": f"{n_times} evenly over [0, {cfg['sim']['t_final']:g}] s",
            "Z": f"0, +-scale_i e_i and {n_z} uniform-radius points of the ellipsoid with semi-axes "
            f"{list(z_scales)} (theta rad, theta' rad/s, theta'' rad/s^2) per joint",
            "s": f"{len(dirs)} directions (26 sign patterns + {n_s - 26} random) x norms {list(s_norms)}",
            "switching": switching,
            "law": law,
            "gamma": np.asarray(ctrl.gamma).tolist(),
            "seed": seed,
        }
        derivs = jax.vmap(ref)(jnp.asarray(times))  # (T, 4, 3)
        Zj, Sj = jnp.asarray(Zs), jnp.asarray(S)
        n_pts = len(times) * len(Zs) * len(S)
        if plant == "linear":
            box = box_of(cfg)
            m = int(sum(np.count_nonzero(hi - lo > 0) for lo, hi in (box[:2], box[2:])))
            if vertices == "all":
                boxj = tuple(jnp.asarray(b) for b in box)
                values = _box_values(ctrl, derivs, Zj, Sj, boxj, switching, law)  # (T, nZ, nS)
                vmax, k = _argmax(values)
                it, iz, i_s = np.unravel_index(int(k), values.shape)
                _, a_v, b_v = box_max_hitting(ctrl, derivs[it], Zj[iz], Sj[i_s], boxj, switching, law)
                a_v, b_v = np.asarray(a_v), np.asarray(b_v)
                code = _code_of(
                    np.concatenate([a_v, b_v], 1),
                    np.concatenate(box[::2], 1),
                    np.concatenate(box[1::2], 1),
                )
                where = {"vertex_code": code, "A_rows": a_v.tolist(), "B_rows": b_v.tolist()}
                label = f"all 2^{m} vertices (exact closed-form maximum over the box)"
                points, evaluations = n_pts * 2**m, n_pts
            else:
                lo, hi = np.concatenate(box[::2], 1), np.concatenate(box[1::2], 1)
                codes = vertex_codes(m, int(vertices), rng)
                V = vertices_from_codes(codes, lo, hi)
                values = _vertex_values(ctrl, derivs, Zj, Sj, jnp.asarray(V[:, :, :9]), jnp.asarray(V[:, :, 9:]),
                                        switching, law)  # fmt: skip
                vmax, k = _argmax(values)
                iv, it, iz, i_s = np.unravel_index(int(k), values.shape)
                where = {
                    "vertex_code": int(codes[iv]),
                    "A_rows": V[iv, :, :9].tolist(),
                    "B_rows": V[iv, :, 9:].tolist(),
                }
                label = ("all" if codes.size == 2**m else f"sampled {codes.size} of 2^{m}") + " vertices (seeded)"
                points = evaluations = n_pts * codes.size
        else:
            payloads = np.linspace(*PAYLOAD_RANGE, n_payloads)
            params = jax.tree.map(lambda p: jnp.asarray(p, jnp.float64), ARM_PARAMS)
            values = _arm_values(ctrl, derivs, Zj, Sj, params, jnp.asarray(payloads), switching, law)  # (P, T, nZ, nS)
            vmax, k = _argmax(values)
            ip, it, iz, i_s = np.unravel_index(int(k), values.shape)
            where = {"payload": float(payloads[ip])}
            label = f"arm at {n_payloads} payloads evenly over {PAYLOAD_RANGE} kg"
            points = evaluations = n_pts * n_payloads
        vmax = float(vmax)
        where = {"t": float(times[it]), "Z": Zs[iz].tolist(), "s": S[i_s].tolist(), **where}
    return Certificate(vmax, bool(vmax < 0), int(points), int(evaluations), where, label, plant, envelope)


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


def gamma_verdicts(cfg: dict, eps: float = 0.01, **options) -> tuple[dict[str, float], list[BoundVerdict]]:
    """For each convention of (24)-(26) (``CONVENTIONS``), :func:`certify` at gamma = (1 +- eps)
    times the bound computed from the config's box (alpha, beta by vertex enumeration), the
    model and the poles. ``options`` go to :func:`certify`. Returns ({alpha, beta}, verdicts).

    "Sufficient in this example" = no violation found above the bound (a sampled check, not a
    proof); "necessary" = a violation found just below it.
    """
    box = box_of(cfg)
    d = summarize(
        cfg["model"]["A_rows"],
        cfg["model"]["B_rows"],
        box,
        cfg["controller"]["C"],
        cfg["controller"]["poles"],
    )
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


def critical_scale(cfg: dict, direction, lo: float = 0.0, hi: float = 64.0, iters: int = 12, **options) -> float:
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


def report(cfg: dict, eps: float = 0.01, verdicts: bool = True, **options) -> dict[str, Any]:
    """JSON-ready summary for ``fosmc certify``: :func:`certify` at the config's gamma (keys
    ``max_hitting``, ``holds``, ``points_checked``, ``evaluations``, ``where``, ``vertices``,
    ``plant``, ``envelope``) and, if ``verdicts``, ``gamma_bounds``: alpha, beta and one
    :class:`BoundVerdict` per convention (:func:`gamma_verdicts` with the same ``options``)."""
    out = certify(cfg, **options)._asdict()
    if verdicts:
        ab, vs = gamma_verdicts(cfg, eps, **options)
        out["gamma_bounds"] = {**ab, "eps": eps, "conventions": [v._asdict() for v in vs]}
    return out
