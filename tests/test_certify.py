"""The hitting-condition certificate (20): against an independent NumPy computation with the
full 9x9 model, the closed-form box maximum against vertex enumeration, signs on obvious cases,
counts and determinism."""

import jax.numpy as jnp
import numpy as np
import pytest

from fosmc_jax import _problems as _config
from fosmc_jax._app.certify import certify, report
from fosmc_jax._certificate.hitting import (
    box_max_hitting,
    hitting,
    s_directions,
    z_samples,
)
from fosmc_jax._controllers.fosmc import FOSMCParams
from fosmc_jax._design import paper as _paper
from fosmc_jax._design.box import vertex_codes, vertices_from_codes
from fosmc_jax._design.gains import gain_from_poles
from fosmc_jax._plants.reference import Cycloid

SMALL = dict(n_times=5, n_z=6, n_s=28)


def paper_controller(gamma=_paper.GAMMA, delta=_paper.DELTA_SETS[0]):
    f = lambda x: jnp.asarray(np.asarray(x, dtype=np.float64))
    ctrl = FOSMCParams(f(_paper.C), f(_paper.POLES), f(gamma), f(delta), f(_paper.A_ROWS), f(_paper.B_ROWS))
    ref = Cycloid(f(_paper.THETA_START), f(_paper.THETA_END), f(_paper.TAU))
    return ctrl, ref


def numpy_hitting(t, Z, s, a_true, b_true, gamma, delta, switching, law):
    """s^T s' / ||s|| from (17) with the full 9x9 matrices, independently of fosmc_jax's algebra
    (only K comes from the library)."""
    A, B = _paper.full_A(_paper.A_ROWS), _paper.full_B(_paper.B_ROWS)
    At, Bt = _paper.full_A(a_true), _paper.full_B(b_true)
    K = np.asarray(gain_from_poles(jnp.asarray(_paper.A_ROWS), jnp.asarray(_paper.B_ROWS), jnp.asarray(_paper.POLES)))
    C = _paper.C
    # reference (30) and its derivatives, by hand
    d = _paper.THETA_END - _paper.THETA_START
    tau = _paper.TAU
    w = 2 * np.pi / tau
    inside = 0 <= t < tau
    th = _paper.THETA_START + d / (2 * np.pi) * (w * t - np.sin(w * t)) if inside else _paper.THETA_END
    d1 = d / tau * (1 - np.cos(w * t)) if inside else 0 * d
    d2 = d * w / tau * np.sin(w * t) if inside else 0 * d
    d3 = d * w**2 / tau * np.cos(w * t) if inside else 0 * d
    X_d = np.stack([th, d1, d2], axis=1).reshape(9)
    Xd_dot = np.stack([d1, d2, d3], axis=1).reshape(9)
    Omega = np.linalg.solve(B[[2, 5, 8]], Xd_dot[[2, 5, 8]] - (A @ X_d)[[2, 5, 8]])
    assert np.allclose(A @ X_d + B @ Omega, Xd_dot)  # (10)
    X = X_d + Z
    rho = gamma[0] * np.linalg.norm(Z) + gamma[1] * np.linalg.norm(X_d) + gamma[2] * np.linalg.norm(Omega)
    f = np.sign(s) if switching == "sign" else s / (np.abs(s) + delta)
    U = Omega - np.linalg.solve(C @ B, rho * f) + (K @ Z if law == "equivalent" else 0)
    Zdot = At @ X + Bt @ U - Xd_dot
    sdot = C @ Zdot - C @ (A + B @ K) @ Z
    return s @ sdot / np.linalg.norm(s)


def random_vertex(rng):
    a = np.where(rng.random((3, 9)) < 0.5, _paper.A_LOWER, _paper.A_UPPER)
    b = np.where(rng.random((3, 3)) < 0.5, _paper.B_LOWER, _paper.B_UPPER)
    return a, b


@pytest.mark.parametrize("switching,law", [("sign", "paper"), ("ratio", "paper"), ("sign", "equivalent")])
def test_hitting_matches_numpy(switching, law):
    rng = np.random.default_rng(1)
    ctrl, ref = paper_controller()
    for _ in range(8):
        t = rng.uniform(0, 4)
        Z = rng.normal(size=9) * np.tile([0.05, 0.5, 5.0], 3)
        s = rng.normal(size=3) * 50
        a, b = random_vertex(rng)
        got = hitting(
            ctrl,
            ref(jnp.asarray(t)),
            jnp.asarray(Z),
            jnp.asarray(s),
            jnp.asarray(a),
            jnp.asarray(b),
            switching,
            law,
        )
        want = numpy_hitting(t, Z, s, a, b, _paper.GAMMA, _paper.DELTA_SETS[0], switching, law)
        np.testing.assert_allclose(float(got), want, rtol=1e-9, atol=1e-8 * (1 + abs(want)))


def test_box_max_equals_vertex_enumeration_on_a_small_box():
    """Four free entries: the closed form equals the max over the 16 vertices, and its vertex."""
    rng = np.random.default_rng(2)
    ctrl, ref = paper_controller()
    A_lo, A_hi = _paper.A_ROWS.copy(), _paper.A_ROWS.copy()
    B_lo, B_hi = _paper.B_ROWS.copy(), _paper.B_ROWS.copy()
    A_lo[0, 1], A_hi[0, 1] = -102.79, 60.63
    A_lo[1, 3], A_hi[1, 3] = -129.62, -95.39
    B_lo[0, 0], B_hi[0, 0] = 15.54, 26.28
    B_lo[2, 1], B_hi[2, 1] = -46.0, -43.34
    box = tuple(jnp.asarray(x) for x in (A_lo, A_hi, B_lo, B_hi))
    lo, hi = np.concatenate([A_lo, B_lo], 1), np.concatenate([A_hi, B_hi], 1)
    V = vertices_from_codes(np.arange(16), lo, hi)
    for _ in range(5):
        d = ref(jnp.asarray(rng.uniform(0, 4)))
        Z, s = jnp.asarray(rng.normal(size=9) * 0.2), jnp.asarray(rng.normal(size=3))
        value, a, b = box_max_hitting(ctrl, d, Z, s, box)
        each = [float(hitting(ctrl, d, Z, s, jnp.asarray(v[:, :9]), jnp.asarray(v[:, 9:]))) for v in V]
        np.testing.assert_allclose(float(value), max(each), rtol=1e-10)
        np.testing.assert_allclose(float(hitting(ctrl, d, Z, s, a, b)), max(each), rtol=1e-10)


def test_box_max_bounds_every_vertex_of_the_paper_box():
    rng = np.random.default_rng(3)
    ctrl, ref = paper_controller()
    box = tuple(jnp.asarray(x) for x in (_paper.A_LOWER, _paper.A_UPPER, _paper.B_LOWER, _paper.B_UPPER))
    d = ref(jnp.asarray(0.7))
    Z, s = jnp.asarray(rng.normal(size=9) * 0.1), jnp.asarray(rng.normal(size=3))
    top = float(box_max_hitting(ctrl, d, Z, s, box)[0])
    for _ in range(50):
        a, b = random_vertex(rng)
        assert float(hitting(ctrl, d, Z, s, jnp.asarray(a), jnp.asarray(b))) <= top + 1e-9


def test_sign_of_the_margin_on_obvious_cases():
    cfg = _config.resolve({})
    huge = certify(cfg, gamma=[1e6, 1e6, 1e6], **SMALL)
    assert huge.holds and huge.max_hitting < 0
    # gamma = 0: U = Omega only; with dA, dB != 0 some (t, Z, s) has s^T s' > 0
    zero = certify(cfg, gamma=[0.0, 0.0, 0.0], **SMALL)
    assert not zero.holds and zero.max_hitting > 0
    # gamma = 0 on the exact nominal plant (a degenerate box) with Z = 0 only: s' = 0 exactly
    nominal = {"plant": {"box": {"A_lower": _paper.A_ROWS.tolist(), "A_upper": _paper.A_ROWS.tolist(),
                                 "B_lower": _paper.B_ROWS.tolist(), "B_upper": _paper.B_ROWS.tolist()}}}  # fmt: skip
    flat = certify(
        _config.resolve(nominal),
        gamma=[0.0, 0.0, 0.0],
        n_times=5,
        n_z=0,
        z_scales=(0, 0, 0),
        n_s=26,
    )
    assert abs(flat.max_hitting) < 1e-9 and not flat.holds


@pytest.mark.slow  # 3 s: the default tier keeps to 4 minutes on 2 cores
def test_points_checked_counts():
    cfg = _config.resolve({})
    c = certify(cfg, **SMALL)
    n = 5 * (1 + 18 + 6) * 28
    assert c.evaluations == n and c.points_checked == n * 2**32 and c.vertices.startswith("all 2^32")
    v = certify(cfg, vertices=7, **SMALL)
    assert v.points_checked == v.evaluations == n * 7 and v.vertices.startswith("sampled 7 of 2^32")
    assert v.max_hitting <= c.max_hitting + 1e-9  # a sample of vertices never beats the exact max
    r = certify(cfg, switching="ratio", n_times=2, n_z=1, n_s=27)
    assert r.evaluations == 2 * 20 * 27 * 4  # four default s norms for ratio


@pytest.mark.slow  # compiles the arm's certificate over the payload range (~7 s)
def test_arm_counts_and_where():
    cfg = _config.resolve({})
    c = certify(cfg, plant="arm", n_times=2, n_z=0, n_s=26, n_payloads=2)
    assert c.points_checked == 2 * 19 * 26 * 2 and c.where["payload"] in (0.0, 10.0)
    assert np.isfinite(c.max_hitting)


def test_deterministic_given_seed():
    cfg = _config.resolve({})
    a = certify(cfg, vertices=5, seed=4, **SMALL)
    b = certify(cfg, vertices=5, seed=4, **SMALL)
    c = certify(cfg, vertices=5, seed=5, **SMALL)
    assert a == b
    assert a.where != c.where or a.max_hitting != c.max_hitting


def test_samplers():
    rng = np.random.default_rng(0)
    d = s_directions(4, rng)
    assert d.shape == (30, 3) and np.allclose(np.linalg.norm(d, axis=1), 1)
    assert len({tuple(np.sign(x)) for x in d[:26]}) == 26
    z = z_samples(10, np.tile([0.1, 1, 10], 3), rng)
    assert z.shape == (29, 9) and np.all(z[0] == 0) and np.all(np.abs(z) <= np.tile([0.1, 1, 10], 3) + 1e-12)
    codes = vertex_codes(32, 100, rng)
    assert codes.size == len(set(codes.tolist())) == 100
    assert np.array_equal(vertex_codes(3, 100, rng), np.arange(8))


@pytest.mark.slow  # 5 s: the default tier keeps to 4 minutes on 2 cores
def test_report_and_gamma_verdicts():
    import json

    cfg = _config.resolve({})
    d = json.loads(json.dumps(report(cfg, n_times=3, n_z=2, n_s=26)))
    assert {"max_hitting", "holds", "points_checked", "where", "vertices", "gamma_bounds"} <= set(d)
    assert isinstance(d["holds"], bool) and isinstance(d["points_checked"], int)
    gb = d["gamma_bounds"]
    assert gb["beta"] == pytest.approx(0.62, abs=0.01)
    assert [c["convention"] for c in gb["conventions"]] == ["spectral", "paper"]
    for v in gb["conventions"]:
        assert v["sufficient"] == (v["max_hitting_above"] < 0)
        assert v["necessary"] == (v["max_hitting_below"] >= 0)
