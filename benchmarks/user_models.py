"""A user's law and a user's plant on the generated kernel against the built-in FOSMC on the
built-in arm (issue 32, "your model at kernel speed"), one command:

    python benchmarks/user_models.py                       # 1,024 rollouts x 1,000 RK4 float64 steps
    python benchmarks/user_models.py --rollouts 256 --steps 200 --rounds 2   # a short trial
    python benchmarks/user_models.py --out benchmarks/results/issue32/user_models.json

Everything through the public API (``fj.simulate_batch``, the default path): the arm of Table 1
(``fj.arm_sweep``, payloads in [0, 10] kg) from offsets around the cycloid's start, dt = 1e-4 s.
The models, each defined here as a user would, outside the package:
- ``fosmc``: the built-in FOSMC (Table 1 set 1) on the built-in arm (the baseline);
- ``tanh_pd``: a user's law, feedforward (10) + pole placement + a tanh limit at 24 V;
- ``pi_tanh``: the same with an integral of the angle error (a state of its own);
- ``user_arm``: the package's arm re-declared as a user class (delegating to ``fj.Arm``'s
  methods: the kernel must not need to know the class) under the built-in FOSMC;
- ``lagged_arm``: a user's plant with a state of its own, the arm driven through a first-order
  actuator lag (12 state rows), under the built-in FOSMC.
Per model: the forward (``simulate_batch``, jitted) and the value and gradient of
mean(rms_error) + 1e-3 mean(chattering) in the law's parameters, compiled first (timed apart,
with the generated model's cold build: ``--cache``, default a fresh folder), then ``--rounds``
interleaved rounds of ``--round-s`` s each. Printed: each forward as a ratio to the baseline's
(the issue: a user's law within 2x, the re-declared arm within 1.2x) and each value and gradient
as a ratio to its own forward (within 5x); the 1-minute load with every round.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import statistics
import tempfile
import time
import warnings
from pathlib import Path


def models(fj, jax, jnp, np):
    """(name, plants, controller-of-parameters, parameters) for every model."""
    from fosmc_jax import paper

    @functools.partial(jax.tree_util.register_dataclass, data_fields=["K", "a_rows", "b_rows"], meta_fields=[])
    @dataclasses.dataclass(frozen=True)
    class TanhPD:
        K: jax.Array
        a_rows: jax.Array
        b_rows: jax.Array

        def init(self, X0, r0, key=None):
            return ()

        def update(self, state, Y, r, t):
            U = fj.feedforward(self.a_rows, self.b_rows, r) + self.K @ (Y - fj.desired_state(r))
            return 24.0 * jnp.tanh(U / 24.0), state

    @functools.partial(jax.tree_util.register_dataclass, data_fields=["K", "Ki", "a_rows", "b_rows", "dt"],
                       meta_fields=[])  # fmt: skip
    @dataclasses.dataclass(frozen=True)
    class PITanh:
        K: jax.Array
        Ki: jax.Array
        a_rows: jax.Array
        b_rows: jax.Array
        dt: jax.Array

        def init(self, X0, r0, key=None):
            return jnp.zeros(3, X0.dtype)

        def update(self, z, Y, r, t):
            e = Y - fj.desired_state(r)
            z = z + self.dt * e[0::3]
            U = fj.feedforward(self.a_rows, self.b_rows, r) + 24.0 * jnp.tanh((self.K @ e + self.Ki * z) / 24.0)
            return U, z

    @functools.partial(jax.tree_util.register_dataclass, data_fields=["params", "payload"], meta_fields=[])
    @dataclasses.dataclass(frozen=True)
    class UserArm:
        """The package's arm as a user's class: every method delegates to fj.Arm's."""

        params: object
        payload: jax.Array
        time_varying = True

        def _arm(self):
            return fj.Arm(self.params, self.payload)

        def init(self, X0):
            return self._arm().init(X0)

        def observe(self, state, t):
            return self._arm().observe(state, t)

        def derivative(self, state, U, t):
            return self._arm().derivative(state, U, t)

        def derivative_observed(self, state, X, U, t):
            return self._arm().derivative_observed(state, X, U, t)

    @functools.partial(jax.tree_util.register_dataclass, data_fields=["arm", "tau"], meta_fields=[])
    @dataclasses.dataclass(frozen=True)
    class LaggedArm:
        """The arm behind a first-order actuator lag of time constant tau (s): 3 more states."""

        arm: object
        tau: jax.Array
        time_varying = True

        def init(self, X0):
            return self.arm.init(X0), jnp.zeros(3, X0.dtype)

        def observe(self, state, t):
            return self.arm.observe(state[0], t)

        def derivative(self, state, U, t):
            x, v = state
            return self.arm.derivative(x, v, t), (U - v) / self.tau

    c = lambda x: jnp.asarray(x, jnp.float64)
    fosmc = fj.FOSMCParams(c(paper.C), c(paper.POLES), c(paper.GAMMA), c(paper.DELTA_SETS[0]), c(paper.A_ROWS),
                           c(paper.B_ROWS))  # fmt: skip
    K = c(-np.kron(np.eye(3), [[400.0, 40.0, 1.0]]))
    return fosmc, TanhPD, PITanh, UserArm, LaggedArm, K


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rollouts", type=int, default=1024, help="payloads x offsets (a square number)")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--round-s", type=float, default=0.5)
    ap.add_argument("--cache", help="the kernel cache folder (default: a fresh temporary one: cold builds)")
    ap.add_argument("--out", help="write the rows as JSON")
    args = ap.parse_args(argv)
    tmp = tempfile.TemporaryDirectory(prefix="fosmc-user-models-")
    os.environ["FOSMC_JAX_CACHE"] = args.cache or tmp.name

    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import fosmc_jax as fj
    from fosmc_jax import paper

    fosmc, TanhPD, PITanh, UserArm, LaggedArm, K = models(fj, jax, jnp, np)
    side = int(round(args.rollouts**0.5))
    arms = fj.arm_sweep(jnp.linspace(0.0, 10.0, side))
    ref = fj.Cycloid(*(jnp.asarray(x, jnp.float64) for x in (paper.THETA_START, paper.THETA_END, paper.TAU)))
    X0 = np.asarray(fj.desired_state(ref(0.0)))
    X0s = jnp.asarray(X0 + np.random.default_rng(1).uniform(-0.05, 0.05, (side, 9)))
    dt = 1e-4
    a, b = fosmc.a_rows, fosmc.b_rows
    cases = {  # name: (plants, controller of theta, theta)
        "fosmc": (arms, lambda p: fj.FOSMC(p), fosmc),
        "tanh_pd": (arms, lambda k: TanhPD(k, a, b), K),
        "pi_tanh": (arms, lambda ki: PITanh(K, ki, a, b, jnp.asarray(dt)), jnp.full(3, -100.0)),
        "user_arm": (UserArm(arms.params, arms.payload), lambda p: fj.FOSMC(p), fosmc),
        "lagged_arm": (LaggedArm(arms, jnp.full(side, 2e-3)), lambda p: fj.FOSMC(p), fosmc),
    }
    opts = dict(n_steps=args.steps, integrator="rk4")
    runs = {}
    print(f"{side * side} rollouts x {args.steps} RK4 float64 steps; start: load {os.getloadavg()[0]:.2f}", flush=True)
    for name, (plants, make, theta) in cases.items():

        def loss(theta, plants=plants, make=make):
            m = fj.simulate_batch(plants, make(theta), ref, X0s, dt, **opts).metrics
            return jnp.mean(m.rms_error) + 1e-3 * jnp.mean(m.chattering)

        for kind, fn in (("forward", loss), ("value_and_grad", jax.value_and_grad(loss))):
            t0 = time.perf_counter()
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                compiled = jax.jit(fn).lower(theta).compile()
                with_warnings = [str(w.message) for w in caught if "generated kernel" in str(w.message)]
            jax.block_until_ready(compiled(theta))
            runs[name, kind] = dict(call=compiled, arg=theta, compile_s=time.perf_counter() - t0, times=[],
                                    vmap_path=with_warnings)  # fmt: skip
            print(f"  {name} {kind}: compiled (with the kernel's build) in {runs[name, kind]['compile_s']:.1f} s"
                  + (f"; ON THE VMAP PATH: {with_warnings[0]}" if with_warnings else ""), flush=True)  # fmt: skip
    loads = []
    for _ in range(args.rounds):
        for r in runs.values():
            t0, calls = time.perf_counter(), 0
            while time.perf_counter() - t0 < args.round_s or calls == 0:
                jax.block_until_ready(r["call"](r["arg"]))
                calls += 1
            r["times"].append((time.perf_counter() - t0) / calls)
        loads.append(os.getloadavg()[0])
    rows = []
    base = runs["fosmc", "forward"]["times"]
    for name in cases:
        f, g = runs[name, "forward"], runs[name, "value_and_grad"]
        row = dict(model=name, forward_s=statistics.median(f["times"]), value_and_grad_s=statistics.median(g["times"]),
                   forward_over_fosmc=statistics.median([x / y for x, y in zip(f["times"], base)]),
                   grad_over_forward=statistics.median([x / y for x, y in zip(g["times"], f["times"])]),
                   forward_compile_s=f["compile_s"], grad_compile_s=g["compile_s"],
                   vmap_path=f["vmap_path"] + g["vmap_path"])  # fmt: skip
        rows.append(row)
        print(f"{name:10s} forward {1e3 * row['forward_s']:8.1f} ms = {row['forward_over_fosmc']:.2f}x the built-in "
              f"FOSMC on the built-in arm; value and gradient {1e3 * row['value_and_grad_s']:8.1f} ms = "
              f"{row['grad_over_forward']:.2f}x its forward", flush=True)  # fmt: skip
    print(f"load over the rounds: {', '.join(f'{x:.2f}' for x in loads)}")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(dict(rollouts=side * side, steps=args.steps, loads=loads, rows=rows),
                                             indent=1) + "\n")  # fmt: skip


if __name__ == "__main__":
    main()
