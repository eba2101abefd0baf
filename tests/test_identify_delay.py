"""``fosmc identify`` checks its delay, and a log of an experiment comes from a simulation (issue
34, item 7): the delay check's verdict, the log writer read back exactly, the simulated log's
delay, encoder and currents, and in the slow tier a wrong delay warned and the right one not."""

import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax._firmware import identify as identification

LOOP = {"plant": {"kind": "arm", "payloads": [2.0]}, "controller": {"sample_period": 1e-3, "delay_samples": 1},
        "sensors": {"encoder_counts": [2621440, 2621440, 2621440]}, "sim": {"t_final": 0.3, "dt": 2.5e-4}}  # fmt: skip


def test_the_delay_check_names_another_delay_only_when_it_fits_clearly_better():
    assert identification.delay_warning({0: 100.0, 1: 200.0, 2: 300.0}, 1).startswith(
        "--delay 1: the log fits --delay 0 better"
    )
    assert "fit again with --delay 0" in identification.delay_warning({0: 100.0, 1: 200.0}, 1)
    assert identification.delay_warning({0: 100.0, 1: 80.0, 2: 300.0}, 1) is None  # the configured one is best
    assert identification.delay_warning({0: 97.0, 1: 100.0}, 1) is None  # within the margin (5%): noise, not a verdict
    assert identification.delay_warning({0: 94.0, 1: 100.0}, 1) is not None


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
@pytest.mark.parametrize("currents", [False, True])
def test_a_written_log_reads_back_exactly(tmp_path, suffix, currents):
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.9e-3, 1.1e-3, 50))
    log = identification.Log(t, rng.standard_normal((50, 3)), 24 * rng.standard_normal((50, 3)),
                rng.standard_normal((50, 3)) if currents else None)  # fmt: skip
    identification.write_log(log, tmp_path / f"log{suffix}")
    back = identification.read_log(tmp_path / f"log{suffix}")
    for a, b in zip(log, back):
        assert (a is None and b is None) or np.array_equal(a, b)
    assert [p.name for p in tmp_path.iterdir()] == [f"log{suffix}"]  # nothing else left (atomic write)


@pytest.mark.parametrize(
    "change, key",
    [({"plant": {"kind": "linear"}}, "plant.kind"), ({"controller": {"sample_period": 0.0, "delay_samples": 0},
                                                      "sensors": {"encoder_counts": [0, 0, 0]}},
                                                     "controller.sample_period")],
)  # fmt: skip
def test_a_log_needs_an_arm_in_a_digital_loop(change, key):
    cfg = {k: {**LOOP.get(k, {}), **change.get(k, {})} for k in {*LOOP, *change}}
    with pytest.raises(fj.ConfigError, match=f"^{key}: "):
        fj.identification_log(cfg)


@pytest.mark.slow  # a 0.3 s closed loop of the arm, compiled (~10-20 s)
def test_a_simulated_log_has_the_loops_samples_encoder_delay_and_currents(tmp_path):
    written = fj.identification_log(LOOP, tmp_path / "log.csv", currents=True)  # the config's delay: 1
    acting = fj.identification_log(LOOP, delay=0)
    assert np.array_equal(identification.read_log(tmp_path / "log.csv").u, written.u)
    np.testing.assert_allclose(np.diff(written.t), 1e-3, rtol=1e-9)
    assert written.t.size == 301 and written.current.shape == (301, 3) and acting.current is None
    q = 2 * np.pi / 2621440
    np.testing.assert_allclose(written.theta / q, np.round(written.theta / q), atol=1e-6)  # encoder counts
    assert np.array_equal(written.u[:-1], acting.u[1:])  # written one sample before it acts
    assert np.array_equal(written.theta, acting.theta) and np.abs(written.u).max() <= 24.0
    # the currents follow the state by the motor's equation: L i' = u - R i - Kb theta', held u
    assert np.abs(written.current).max() > 0.01


@pytest.mark.slow  # two fits of a closed-loop log (~1-2 min on 2 cores)
def test_a_wrong_delay_is_warned_and_the_right_one_is_not():
    """A closed loop of the arm with Kt 20% off on joint 1, logged as the voltages act (delay
    0), fitted for Kt and the payload with --delay 1 (the config's) and 0: the first warns and
    names delay 0; the second does not warn (its own delay costs least)."""
    kt = np.asarray(fj.ARM_PARAMS.Kt) * [1.2, 1, 1]
    cfg = {**LOOP, "sim": {"t_final": 1.0, "dt": 2.5e-4}, "arm": {"Kt": kt.tolist()}}
    log = fj.identification_log(cfg, delay=0)
    settings = identification.Settings(window=200, bootstrap=0, resolution=(2 * np.pi / 2621440,) * 3)
    wrong = identification.identify(fj.ARM_PARAMS, 2.0, log, ["Kt", "payload"], settings._replace(delay=1))
    right = identification.identify(fj.ARM_PARAMS, 2.0, log, ["Kt", "payload"], settings._replace(delay=0))
    costs = {int(d): c for d, c in wrong["log"]["delay_costs"].items()}
    assert set(costs) == {0, 1, 2, 3} and min(costs, key=costs.get) == 0
    assert [w for w in wrong["warnings"] if w.startswith("--delay 1: the log fits --delay 0 better")]
    assert not [w for w in right["warnings"] if w.startswith("--delay")]
    truth = [*kt, 2.0]
    np.testing.assert_allclose([e["estimate"] for e in right["entries"]], truth, rtol=0.01)
