"""The arm's fast path: :func:`fosmc_jax.simulate_batch` of :class:`fosmc_jax.Arm` plants with
its time loop in one compiled kernel (``arm_kernel.cc``, built by :mod:`fosmc_jax._simulator.native`).

XLA:CPU copies the arm's closed form into every fusion that uses it (an RK4 step of the vmapped
``simulate`` evaluates its sines and cosines many times over) and runs each of its fusions per
step as one more pass over the batch, far below a hand-written C kernel of the same loop
(BENCHMARKS.md, "Figures behind the code" and "Issue 21"). The kernel runs the loop of
:func:`fosmc_jax.simulate` for the two controllers the tuner and the presets use:

- :class:`fosmc_jax.FOSMC`, the ideal loop, every switching function and law;
- :class:`fosmc_jax.DigitalLoop` around :class:`fosmc_jax.DiscreteFOSMC` without Gaussian noise
  (encoder quantization, measured or differenced rates, a delay of up to 8 samples, the
  voltage limit, any sample period);

Euler or RK4, float32 or float64. Everything else (other controllers, noise, traces) runs the
``vmap`` of :func:`fosmc_jax.simulate`, and so does everything where the kernel is not built.

What stays in JAX: the first sample (:func:`fosmc_jax._simulator.step.start`, vmapped), everything
derived from the controller's parameters (K, (CB)^-1, S), the time-only terms (X_d at the stage
times, Omega, their norms: a table per call, so any reference works) and
:func:`fosmc_jax._simulator.metrics.finish`. Every parameter (the arm's, the controller's, the loop's) is
an input per rollout, so a vmapped batch of candidate controllers (``fosmc front``'s chunks) is
folded into one call (``custom_vmap``). Derivatives (``custom_jvp``, forward mode and reverse
mode by its transpose) are those of the ``vmap`` path, which the tuner's gradients use anyway.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .._controllers.base import ArmKernelLaw, KernelLaw
from .._controllers.fosmc import reference_terms
from .._loop.digital import DigitalLoop
from .._plants.arm import Arm, ArmParams, cast_params
from .._plants.reference import desired_state
from . import metrics as _metrics
from . import native as _native
from .generated import jvp_perturbed
from .step import Result, start_batch

# The layouts of arm_kernel.cc: its lane rows, and where the carry's rows hold the accumulator's
# fields (field-major), the divergence flag and its time, the delay line after them (defined in
# fosmc_jax._simulator.native, which writes them into the kernels' layout.h).
LANE_ROWS = _native.ARM_LANE_ROWS
METRICS = slice(_native.ARM_MET, _native.ARM_DIV)
DIVERGED, DIVERGED_AT, CARRY_ROWS = _native.ARM_DIV, _native.ARM_DIV + 1, _native.ARM_CARRY_ROWS
MAX_DELAY = 8
# Steps per kernel call: as many as keep the call's time table within 24 KiB (the core's L1).
TABLE_BYTES = 24 * 1024


def _kernel_law(ctrl):
    """(the law the kernel would run, its code in arm_kernel.cc or None where the kernel does not
    run it): a DigitalLoop's law, sampled, or the ideal loop's controller itself
    (:class:`fosmc_jax._controllers.base.ArmKernelLaw`, declared by the laws themselves)."""
    sampled = type(ctrl) is DigitalLoop
    law = ctrl.law if sampled else ctrl
    return law, law.arm_kernel_code(sampled) if isinstance(law, ArmKernelLaw) else None


def supports(plants, ctrl, integrator: str) -> bool:
    """Whether the kernel runs this batch: arms under a law the kernel runs (the FOSMC, SMC or
    super-twisting), in the ideal loop or in a DigitalLoop without noise, on a CPU where the
    kernel is built."""
    if not isinstance(plants, Arm) or integrator not in ("euler", "rk4"):
        return False
    ok = _kernel_law(ctrl)[1] is not None
    if type(ctrl) is DigitalLoop:
        ok = ok and ctrl.sensors.noise_std is None and ctrl.delay <= MAX_DELAY
    return ok and jax.default_backend() == "cpu" and _native.available()


def _law_rows(kernel: KernelLaw, dtype) -> Array:
    """The law's lane rows of arm_kernel.cc (96), then its period (0 in the ideal loop)."""
    return jnp.concatenate([jnp.ravel(jnp.asarray(x, dtype)) for x in (*kernel.rows, kernel.period)])


def _lane_rows(plants: Arm, ctrl, kernel: KernelLaw, O: int, dtype) -> Array:
    """(LANE_ROWS, P O): the arm's parameters (each plant O times: plant-major), then the law's and
    the loop's, as in arm_kernel.cc."""
    p = cast_params(plants.params, dtype)
    P = plants.payload.shape[0]
    field = lambda k: jnp.zeros((P, 3), dtype) if getattr(p, k) is None else getattr(p, k)  # None: a term left out
    arm = [plants.payload] + [field(k) for k in ArmParams._fields if k != "d1"]  # native.ARM_PARAM_ROWS
    arm = jnp.concatenate([jnp.asarray(a, dtype).reshape(P, -1) for a in arm], axis=1)  # (P, 52)
    if type(ctrl) is DigitalLoop:
        counts = ctrl.sensors.counts
        on = counts > 0
        step = jnp.where(on, 2 * jnp.pi / jnp.where(on, counts, 1), 0)  # as fosmc_jax._loop.digital.quantize
        loop = [jnp.broadcast_to(step, (3,)), jnp.broadcast_to(ctrl.u_max, (3,)), ctrl.period]
    else:
        loop = [jnp.zeros(3), jnp.full(3, jnp.inf), 0.0]
    law = _law_rows(kernel, dtype)
    rest = jnp.concatenate([law[:-1], *(jnp.ravel(jnp.asarray(x, dtype)) for x in loop), law[-1:]])
    lanes = jnp.concatenate([jnp.repeat(arm, O, axis=0), jnp.broadcast_to(rest, (P * O, rest.shape[0]))], axis=1)
    assert lanes.shape[1] == LANE_ROWS, lanes.shape
    return lanes.T


def _pack(carry, acc3: Array, digital: bool, delay: int, integral) -> Array:
    """The kernel's carry rows (56 + 3 delay, N) from a batch of :class:`_simulator._Carry`
    (leading axis N) and the accelerations of its plant states (N, 3); ``integral``: the law's
    state -> its integral (:attr:`KernelLaw.memory`; None: zeros)."""
    ps, cs = carry.plant_state, carry.ctrl_state
    law = cs.law if digital else cs
    N = acc3.shape[0]
    dtype = acc3.dtype
    col = lambda x: jnp.asarray(x, dtype).reshape(N, -1)
    w = integral(law) if integral is not None else jnp.zeros((N, 3), dtype)
    memory = [cs.memory.theta, cs.memory.dtheta] if digital else [jnp.zeros((N, 6), dtype)]
    a = carry.acc
    metrics = [jnp.broadcast_to(col(a.count), (N, 3))] + [col(f) for f in a[1:]]
    parts = [*ps.theta, *ps.dtheta, *ps.current, acc3, w, carry.U, *memory, *metrics, carry.diverged,
             carry.diverged_at]  # fmt: skip
    if digital and delay:
        parts.append(cs.pending)
    rows = jnp.concatenate([col(x) for x in parts], axis=1).T
    assert rows.shape[0] == CARRY_ROWS + 3 * delay, rows.shape
    return rows


def _table(reference, a_rows, b_rows, dt, k: Array, *, stages: int, m: int) -> Array:
    """The time-only terms of steps ``k`` (a vector), (len(k), 9 stages + 20): X_d at the stage
    times, then at t' = (k + 1) dt X_d, Omega (10), ||X_d||, ||Omega||, t', the sample flag and
    the reference's third derivatives, then t = k dt (the external torque's stage times)."""
    X_d_at = jax.vmap(lambda t: desired_state(reference(t)))
    t = k.astype(dt.dtype) * dt
    cols = [X_d_at(t)] if stages == 1 else [X_d_at(t), X_d_at(t + dt / 2), X_d_at(t + dt)] if stages == 3 else []
    t1 = (k + 1).astype(dt.dtype) * dt
    refs = jax.vmap(reference)(t1)
    X_d, Omega, norm_X_d, norm_Omega = jax.vmap(functools.partial(reference_terms, a_rows, b_rows))(refs)
    flag = ((k + 1) % m == 0).astype(dt.dtype)
    parts = [*cols, X_d, Omega, jnp.stack([norm_X_d, norm_Omega, t1, flag], 1), refs[:, 3], t[:, None]]
    return jnp.concatenate(parts, axis=1)


def _advance(carry: Array, lanes: Array, shared, *, n_steps: int, rk4: bool, digital: bool, flags: dict) -> Array:
    """``n_steps`` steps of the kernel: ``carry`` (R, N) and ``lanes`` (LANE_ROWS, N) with any N (padded
    here to whole blocks), ``shared`` = (reference, a_rows, b_rows, dt, the low-pass's (decay,
    weight), bound). Calls of a few hundred steps (see TABLE_BYTES) in a scan."""
    reference, a_rows, b_rows, dt, gain, bound = shared
    dtype = carry.dtype
    N = carry.shape[1]
    pad = (-N) % (_native.LANES if dtype == jnp.float32 else _native.LANES // 2)
    carry, lanes = (jnp.pad(x, ((0, 0), (0, pad)), mode="edge") for x in (carry, lanes))
    consts = jnp.stack([dt, *gain, jnp.minimum(bound, jnp.finfo(dtype).max)]).astype(dtype)
    stages = 0 if digital else 3 if rk4 else 1
    call = jax.ffi.ffi_call(_native.ARM_TARGET, jax.ShapeDtypeStruct(carry.shape, dtype), vmap_method="sequential")
    m = flags["m"]  # the sample period in steps: the table's flag; the rest are the kernel's attributes
    attrs = {name: np.int32(v) for name, v in dict(flags, rk4=rk4, digital=digital).items() if name != "m"}

    def chunk(c, k0, length):
        table = _table(reference, a_rows, b_rows, dt, k0 + jnp.arange(length), stages=stages, m=m)
        return call(lanes, consts, table.astype(dtype), c, **attrs)

    steps = max(64, TABLE_BYTES // ((9 * stages + _native.ARM_SAMPLE_COLS) * dtype.itemsize))
    chunks, rest = divmod(n_steps, steps)
    if chunks:
        carry = jax.lax.scan(lambda c, i: (chunk(c, i * steps, steps), None), carry, jnp.arange(chunks))[0]
    if rest:
        carry = chunk(carry, chunks * steps, rest)
    return carry[:, :N]


def _folded(advance):
    """``advance`` under ``vmap`` as one call: the mapped axis of ``carry`` and ``lanes`` folded into
    their lanes (a chunk of candidate controllers becomes one batch), the mapped axis of
    ``shared`` (a batch of references) run one after the other."""
    run = jax.custom_batching.custom_vmap(advance)

    @run.def_vmap
    def rule(axis_size, in_batched, carry, lanes, shared):
        carry_b, lanes_b, shared_b = in_batched
        full = lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + x.shape)
        if any(jax.tree.leaves(shared_b)):
            shared = jax.tree.map(full, shared, shared_b)
            return jax.lax.map(lambda a: run(*a), (full(carry, carry_b), full(lanes, lanes_b), shared)), True
        fold = lambda x, b: jnp.moveaxis(full(x, b), 0, -2).reshape(x.shape[-2], -1)
        out = run(fold(carry, carry_b), fold(lanes, lanes_b), shared)
        return jnp.moveaxis(out.reshape(out.shape[0], axis_size, -1), 1, 0), True

    return run


def _native_batch(plants, ctrl, reference, X0s, dt, *, n_steps, integrator, divergence_bound, chattering_cutoff,
                  paired=False):  # fmt: skip
    dtype = X0s.dtype
    dt = jnp.asarray(dt, dtype)
    P = plants.payload.shape[0]
    O = 1 if paired else X0s.shape[0]  # initial states per plant
    N = P * O
    digital = type(ctrl) is DigitalLoop
    bound = jnp.asarray(divergence_bound, dtype)
    carry = start_batch(plants, ctrl, reference, X0s, None, bound, paired)
    acc3 = jax.vmap(lambda plant, state: plant.accelerations(state, jnp.zeros((), dtype)), (0, 0))(
        jax.tree.map(lambda x: jnp.repeat(x, O, axis=0), plants), carry.plant_state
    )
    delay = ctrl.delay if digital else 0
    law, code = _kernel_law(ctrl)
    kernel = law.arm_kernel_law()
    flags = dict(kind=code, delay=delay, switching=kernel.switching, law=kernel.law,
                 difference=digital and ctrl.sensors.derivatives == "difference",
                 m=ctrl.sample_steps if digital else 1)  # fmt: skip
    gain = _metrics.lowpass(dt, jnp.asarray(chattering_cutoff, dtype))
    shared = (reference, *kernel.surface[1:], dt, gain, bound)
    advance = _folded(
        functools.partial(_advance, n_steps=n_steps, rk4=integrator == "rk4", digital=digital, flags=flags)
    )
    out = advance(_pack(carry, acc3, digital, delay, kernel.memory), _lane_rows(plants, ctrl, kernel, O, dtype), shared)
    fields = out[METRICS].reshape(_native.ACC, 3, N)
    acc = _metrics.Accumulator(*(jnp.moveaxis(f, 0, -1) for f in fields))
    acc = acc._replace(count=acc.count[:, :1])
    diverged = out[DIVERGED] != 0
    return Result(_metrics.masked(_metrics.finish(acc, n_steps * dt), diverged), diverged, out[DIVERGED_AT], None)


def simulate_batch(args: tuple, derivative, *, n_steps: int, integrator: str, paired: bool = False) -> Result:  # noqa: F821
    """:func:`fosmc_jax.simulate_batch` in the kernel (:func:`supports` must hold) for ``args`` =
    (plants, ctrl, reference, X0s, dt, keys, divergence_bound, chattering_cutoff), plants
    crossed with initial states or (``paired``) the i-th with the i-th; the loop draws no
    noise, so ``keys`` only reach the derivatives, which are those of ``derivative(*args)``
    (the generated kernel's: :mod:`fosmc_jax._simulator.generated`)."""

    def kernel(plants, ctrl, reference, X0s, dt, keys, bound, cutoff):
        return _native_batch(plants, ctrl, reference, X0s, dt, n_steps=n_steps, integrator=integrator,
                             divergence_bound=bound, chattering_cutoff=cutoff, paired=paired)  # fmt: skip

    run = jax.custom_jvp(kernel)
    run.defjvp(lambda primals, tangents: jvp_perturbed(derivative, primals, tangents), symbolic_zeros=True)
    return run(*args)
