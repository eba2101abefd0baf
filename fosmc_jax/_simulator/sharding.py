"""The batch of rollouts split over several devices, with JAX's own SPMD machinery.

:func:`simulate_sharded` is :func:`fosmc_jax.simulate_batch` with the rollouts laid out over
a one-axis device mesh named ``batch`` (``jax.sharding.Mesh`` + ``NamedSharding``) and run
under ``jax.shard_map``: each device integrates its own slice of the batch with no
communication inside the time loop, and the results come back as one global array per
field, in the same order as the single-device run and equal to it (rollouts are independent;
each runs the same operations).

Devices. On GPUs the devices are the GPUs; on several hosts, after
``jax.distributed.initialize()`` on each, ``jax.devices()`` lists every host's devices and the
same call spans them all (each host supplies its own shards of the inputs, which every host
holds in full). On CPU, XLA shows one device per process unless asked for more before JAX
initialises: call :func:`use_all_cores` (one device per core unless the user set a count) or
:func:`use_host_devices` first, or set ``XLA_FLAGS=--xla_force_host_platform_device_count=N``
or ``JAX_NUM_CPU_DEVICES=N`` in the environment.

Several processes or hosts (tested on one machine with two processes on 127.0.0.1, CPU,
gloo collectives: tests/test_distributed.py). On each of N processes, before any other JAX
operation::

    jax.distributed.initialize(coordinator_address="HOST0:PORT", num_processes=N, process_id=i)
    res = simulate_sharded(plants, ctrl, ref, X0s, dt, devices=None, n_steps=..., ...)
    res = jax.experimental.multihost_utils.process_allgather(res, tiled=True)  # full result everywhere

Every process passes the same full inputs (each supplies its own shards). On CPU the
cross-process collectives (only the final gather uses them) go through gloo
(``jax_cpu_collectives_implementation``, the default in jax 0.10); each process may show
several CPU devices (:func:`use_all_cores` before ``initialize``). On GPUs (``pip install
"jax[cuda12]"``), one process per host sees its GPUs and ``devices=None`` spans every GPU of
every process; on a GPU cluster under SLURM or Open MPI ``jax.distributed.initialize()``
needs no arguments. The GPU commands are not tested here (no GPU on the development machine).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as Spec

from .._plants.arm import without_idle_terms
from .rollout import Result, simulate_batch

AXIS = "batch"


def use_host_devices(n: int) -> None:
    """Make the CPU show ``n`` devices (one per host core, say). Must run before JAX
    initialises its backends (before the first JAX operation); afterwards it only checks
    that at least ``n`` devices are there and raises ``RuntimeError`` if not."""
    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError:
        if jax.device_count() < n:
            raise RuntimeError(
                f"{n} devices requested but JAX is already initialised with {jax.device_count()}; "
                f"call use_host_devices({n}) before any JAX operation, or set "
                f"XLA_FLAGS=--xla_force_host_platform_device_count={n}"
            ) from None
        return
    flag = f"--xla_force_host_platform_device_count={n}"
    os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), flag]).strip()


def _cores() -> int:
    """The cores this process may run on (its CPU affinity; ``os.cpu_count()`` where that is
    unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _user_device_count() -> int | None:
    """A CPU device count the user set: ``jax_num_cpu_devices`` (``jax.config.update`` or the
    ``JAX_NUM_CPU_DEVICES`` environment variable) or ``--xla_force_host_platform_device_count``
    in ``XLA_FLAGS``; None when neither is set."""
    n = jax.config.jax_num_cpu_devices
    if n is not None and n > 0:
        return int(n)
    for flag in os.environ.get("XLA_FLAGS", "").split():
        if flag.startswith("--xla_force_host_platform_device_count="):
            return int(flag.split("=", 1)[1])
    return None


def use_all_cores() -> int:
    """Show one CPU device per host core unless the user chose a count, and return the number
    of devices a batch should be split over by default (``simulate_sharded(devices=...)``).

    Call it before the first JAX operation (as :func:`use_host_devices`). The rules, in order:

    - a count the user set wins and is left alone: ``jax.config.update("jax_num_cpu_devices",
      N)``, ``JAX_NUM_CPU_DEVICES=N`` or ``XLA_FLAGS=--xla_force_host_platform_device_count=N``
      (so ``N = 1`` turns sharding off);
    - otherwise the CPU shows as many devices as this process has cores
      (``os.sched_getaffinity``: a ``taskset`` or container CPU set is respected);
    - if JAX is already initialised, nothing can change: the devices it has are used.

    The count returned is that of the local devices of the default backend once JAX starts:
    on a GPU host the GPUs (the CPU count only matters for the CPU backend); after
    ``jax.distributed.initialize`` pass ``devices=None`` to :func:`simulate_sharded` to span
    every process's devices. Sharding never changes results (tests/test_performance_paths.py).
    """
    show_all_cores()
    return jax.local_device_count()


def show_all_cores() -> None:
    """:func:`use_all_cores` without starting JAX (it returns nothing): what a process that
    joins others (``jax.distributed.initialize``, which must come before JAX starts) calls."""
    if _user_device_count() is None:
        try:
            jax.config.update("jax_num_cpu_devices", _cores())
        except RuntimeError:  # backends already initialised
            pass


def batch_mesh(devices: int | Sequence[jax.Device] | None = None) -> Mesh:
    """A one-axis mesh named ``batch`` over ``devices``: a count (the first n of
    ``jax.devices()``), a list of devices, or ``None`` for all of them."""
    available = jax.devices()
    if devices is None:
        devices = available
    elif isinstance(devices, int):
        if not 1 <= devices <= len(available):
            raise ValueError(f"devices = {devices}, but {len(available)} available (on CPU, see use_host_devices)")
        devices = available[:devices]
    return Mesh(np.asarray(devices), (AXIS,))


def _global(x, sharding: NamedSharding) -> Array:
    """``x`` (held in full by every process) as a global array laid out by ``sharding``."""
    x = jnp.asarray(x)
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])


def simulate_sharded(
    plants,
    controller,
    reference,
    X0s: Array,
    dt: Array,
    *,
    devices: int | Sequence[jax.Device] | None = None,
    keys: Array | None = None,
    **options,
) -> Result:
    """:func:`fosmc_jax.simulate_batch` with the batch split over ``devices``.

    The initial states ``X0s`` (O, 9) are split over the devices (padded with copies of the
    last one up to a multiple of their number, the padding dropped from the results); if O
    does not divide but the number of plants P does, the plants are split instead. Each
    device runs ``simulate_batch`` on its slice. ``options`` are ``simulate_batch``'s; with
    ``pairing = "paired"`` plants and initial states are split alike (both padded).

    Returns the :class:`Result` of all P x O (x R, for R ``keys``) rollouts, plant-major,
    shape (P*O*R, ...) (paired: (P*R, ...)), equal to ``simulate_batch``'s.
    """
    mesh = batch_mesh(devices)
    n = mesh.devices.size
    P = jax.tree.leaves(plants)[0].shape[0]
    O = X0s.shape[0]
    if keys is None:
        key = options.pop("key", None)
        keys = (jax.random.PRNGKey(0) if key is None else key)[None]
    R = keys.shape[0]
    over = Spec(AXIS)
    if options.get("pairing") == "paired":  # the i-th plant with the i-th state: both split alike
        pad = (-P) % n
        extend = lambda x: jnp.concatenate([jnp.asarray(x), jnp.repeat(jnp.asarray(x)[-1:], pad, axis=0)])
        if pad:
            plants, X0s = jax.tree.map(extend, plants), extend(X0s)
        result = _run(mesh, over, over, options, plants, controller, reference, X0s, dt, keys)
        return jax.tree.map(lambda r: r[:P].reshape((P * R,) + r.shape[2:]), result)
    split_plants = O % n != 0 and P % n == 0
    pad = 0 if split_plants else (-O) % n
    if pad:
        X0s = jnp.concatenate([jnp.asarray(X0s), jnp.repeat(jnp.asarray(X0s)[-1:], pad, axis=0)])
    plant_spec, x0_spec = (over, Spec()) if split_plants else (Spec(), over)
    result = _run(mesh, plant_spec, x0_spec, options, plants, controller, reference, X0s, dt, keys)
    return jax.tree.map(lambda r: r[:, :O].reshape((P * O * R,) + r.shape[3:]), result)


def _run(mesh, plant_spec, x0_spec, options, plants, controller, reference, X0s, dt, keys) -> Result:
    put = lambda tree, spec: jax.tree.map(lambda x: _global(x, NamedSharding(mesh, spec)), tree)
    args = (put(plants, plant_spec), put(controller, Spec()), put(reference, Spec()),
            put(X0s, x0_spec), put(dt, Spec()), put(keys, Spec()))  # fmt: skip
    return _sharded(mesh, plant_spec, x0_spec, tuple(sorted(options.items())), *args)


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3))
def _sharded(mesh, plant_spec, x0_spec, options, plants, controller, reference, X0s, dt, keys) -> Result:
    return _split(mesh, plant_spec, x0_spec, dict(options), plants, controller, reference, X0s, dt, keys)


def across_processes() -> bool:
    """Whether this run spans several processes (``jax.distributed.initialize`` came first):
    then every process holds the same inputs in full, the device meshes span every process's
    devices, and results are gathered so that every process sees all of them."""
    return jax.process_count() > 1


def leads() -> bool:
    """Whether this process prints and writes a run's outputs: process 0 (the only one of a
    run in one process)."""
    return jax.process_index() == 0


def spread(tree, mesh: Mesh, spec: Spec):
    """``tree`` (held in full by every process) as global arrays laid out by ``spec`` on
    ``mesh``, each process supplying its own devices' slices."""
    return jax.tree.map(lambda x: _global(x, NamedSharding(mesh, spec)), tree)


def gathered(tree):
    """``tree``'s arrays as NumPy arrays holding every process's part: the full results on
    every process (``process_allgather``; plain ``np.asarray`` in one process)."""
    if not across_processes():
        return jax.tree.map(np.asarray, tree)
    return jax.tree.map(np.asarray, multihost_utils.process_allgather(tree, tiled=True))


def first(value):
    """Process 0's ``value`` (a NumPy scalar or array, a bool, an int or a float) on every
    process: a decision taken from a clock (a deadline passed, a measured cost) must be the
    same everywhere, or the processes run different work. A collective: every process calls it
    at the same point. ``value`` itself in one process."""
    if not across_processes():
        return value
    a = np.asarray(value)
    raw = np.frombuffer(np.ascontiguousarray(a).tobytes(), np.uint8)  # bytes: no dtype is cast (x64 off)
    got = np.asarray(multihost_utils.broadcast_one_to_all(raw), np.uint8)
    out = np.frombuffer(got.tobytes(), a.dtype).reshape(a.shape)
    return type(value)(out.item()) if isinstance(value, (bool, int, float)) else out


def replicated(tree):
    """``tree`` placed whole on every local device, on :func:`simulate_split`'s mesh: how the
    gradients of a loss on it come out, so that a jitted optimizer step fed its own outputs
    compiles once (an uncommitted first input compiles a second program; what that cost:
    BENCHMARKS.md, "Figures behind the code")."""
    if across_processes():  # every process's devices: the tuner's loss spans them
        return spread(tree, Mesh(np.asarray(jax.devices()), (AXIS,)), Spec())
    if jax.local_device_count() == 1:
        return tree
    sharding = NamedSharding(Mesh(np.asarray(jax.local_devices()), (AXIS,)), Spec())
    return jax.device_put(tree, sharding)


def simulate_split(plants, controller, reference, X0s, dt, *, keys: Array | None = None, **options) -> Result:
    """:func:`fosmc_jax.simulate_batch` with its rollouts split over this process's devices
    (every process's, in a run across processes: :func:`across_processes`) when the initial
    states (O) or else the plants (P) divide evenly among them (the choice of
    :func:`simulate_sharded`, which pads where neither does), and ``simulate_batch`` itself
    otherwise. Traceable (inside ``jit`` and ``grad``, unlike
    :func:`simulate_sharded`, which places concrete inputs): the tuner's loss runs on it.
    Returns the same :class:`Result`, plant-major, (P*O*R, ...)."""
    devices = jax.devices() if across_processes() else jax.local_devices()
    n = len(devices)
    P, O = jax.tree.leaves(plants)[0].shape[0], X0s.shape[0]
    paired = options.get("pairing") == "paired"
    if n == 1 or (P % n and (paired or O % n)):
        return simulate_batch(plants, controller, reference, X0s, dt, keys=keys, **options)
    mesh = Mesh(np.asarray(devices), (AXIS,))
    plants = without_idle_terms(plants)  # before shard_map makes its amplitudes tracers
    if paired:
        plant_spec = x0_spec = Spec(AXIS)
    else:
        plant_spec, x0_spec = (Spec(), Spec(AXIS)) if O % n == 0 else (Spec(AXIS), Spec())
    if keys is None:
        key = options.pop("key", None)
        keys = (jax.random.PRNGKey(0) if key is None else key)[None]
    r = _split(mesh, plant_spec, x0_spec, options, plants, controller, reference, X0s, dt, keys)
    return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2 if paired else 3 :]), r)


def _split(mesh, plant_spec, x0_spec, options, plants, controller, reference, X0s, dt, keys) -> Result:
    """The rollouts under ``jax.shard_map``: each device runs ``simulate_batch`` on its plants or
    initial states (paired: both); results (P, O, R, ...) (paired: (P, R, ...)), split on the
    axis that was."""

    def local(plants, controller, reference, X0s, dt, keys):
        p, o, r = jax.tree.leaves(plants)[0].shape[0], X0s.shape[0], keys.shape[0]
        res = simulate_batch(plants, controller, reference, X0s, dt, keys=keys, **options)
        lead = (p, r) if options.get("pairing") == "paired" else (p, o, r)
        return jax.tree.map(lambda x: x.reshape(lead + x.shape[1:]), res)

    out = Spec(AXIS) if plant_spec == Spec(AXIS) else Spec(None, AXIS)
    return jax.shard_map(
        local,
        mesh=mesh,
        in_specs=(plant_spec, Spec(), Spec(), x0_spec, Spec(), Spec()),
        out_specs=out,
        check_vma=False,  # rollouts are independent: nothing is reduced over the mesh
    )(plants, controller, reference, X0s, dt, keys)
