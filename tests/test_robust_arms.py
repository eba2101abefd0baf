"""Robust tuning over sampled arms (issue 25, item 4): the worst-case objective forms run over
the sampled-arm axis of the batch, and tuning reports the held-out arms it did not see."""

import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import _problems as _config
from fosmc_jax._search import tune as tuner

# 3 sampled arms (torque constants +-50%: clearly different arms) x 2 payloads, 0.1 s of Euler
# (the arm's vmap path compiles in less than half RK4's time; the integrator is not what is tested)
ARMS = {
    "plant": {"kind": "arm", "payloads": [0.0, 5.0]},
    "arm": {"uncertainty": {"Kt": 0.5, "F": 0.3, "samples": 3, "seed": 4}},
    "sim": {"t_final": 0.1, "dt": 1e-3, "integrator": "euler"},
}


@pytest.mark.slow  # 7 s: the default tier keeps to 4 minutes on 2 cores
def test_worst_case_forms_run_over_the_sampled_arms():
    """The tuner's loss equals mean(J) + w x (max or CVaR of J) with J per rollout of the whole
    batch, sampled arms included (recomputed here in NumPy from the plain simulation)."""
    cfg = _config.resolve({**ARMS, "tune": {"worst_weight": 2.0, "cvar_alpha": 0.5}})
    plain, _, p0 = _config.tuning_problems(cfg)
    assert plain.rollouts == 6
    r = plain.simulate(p0, split=True, fast=False)
    E = np.asarray(r.metrics.rms_error).mean(-1)
    C = np.asarray(r.metrics.chattering_hf).mean(-1)
    assert not np.asarray(r.diverged).any()
    obj = tuner.objective_of(cfg["tune"], {"rms_error": E.mean(), "chattering_hf": C.mean()})
    # the weighted form on the log scale
    J = obj.weight_error * np.log(E / E.mean()) + obj.weight_chattering * np.log(C / C.mean())
    # the arms differ: the worst rollout is not the same for every arm's payloads
    assert np.ptp(J.reshape(3, 2).mean(1)) > 1e-3
    u0 = tuner.to_internal(p0, plain.base, None)
    for form, worst in (("max", J.max()), ("cvar", np.sort(J)[::-1][:3].mean())):  # (1 - 0.5) x 6 = 3 worst
        loss, _ = tuner.make_loss(plain, obj._replace(worst_case=form), None)(u0)
        np.testing.assert_allclose(float(loss), J.mean() + 2.0 * worst, rtol=1e-4, atol=1e-5, err_msg=form)


@pytest.mark.slow  # a tune of one step: the gradient's compilation, ~20 s
def test_tune_reports_its_final_parameters_on_fresh_arms():
    result = fj.run_tune(ARMS, steps=1)
    held, batch = result["held_out"], result["held_out_batch"]
    assert batch["arm_samples"] == 3 and batch["arm_seed"] == 5  # fresh arms: the next seed
    assert held["rollouts"] == 3 * len(batch["payloads"]) and held["diverged"] == 0
    assert not set(batch["payloads"]) & {0.0, 5.0}
    # the same parameters on the training batch and on the held-out one: close, not equal
    train, test = (np.mean(x["metrics"]["rms_error"]) for x in (result["final"], held))
    assert train != test and 0.2 < test / train < 5
