"""Scale-out past one process with ``jax.distributed``: two Python processes on 127.0.0.1, each
with its own CPU device, run one batch sharded over both with ``simulate_sharded`` and check
that the gathered result equals the single-process run (issue 13).

CPU collectives across processes go through gloo (``jax_cpu_collectives_implementation``,
the default in jax 0.10); the simulation itself exchanges nothing between processes, only
the final gather of the results does.
"""

import os
import socket
import subprocess
import sys
import textwrap
import time

import pytest

WORKER = textwrap.dedent(
    """
    import sys
    address, pid = sys.argv[1], int(sys.argv[2])
    import jax
    jax.config.update("jax_num_cpu_devices", 1)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.config.update("jax_enable_x64", True)
    jax.distributed.initialize(coordinator_address=address, num_processes=2, process_id=pid,
                               initialization_timeout=60)
    import numpy as np
    from jax.experimental import multihost_utils
    import fosmc_jax as fj
    from fosmc_jax._simulator.sharding import simulate_sharded
    import test_performance_paths as performance_paths

    assert jax.process_count() == 2 and jax.device_count() == 2 and jax.local_device_count() == 1, jax.devices()
    for P, O, opts in ((3, 4, dict(n_steps=300, integrator="rk4")),  # X0s split over the processes
                       (2, 3, dict(n_steps=90, save_every=30))):     # plants split, with a trace
        args = performance_paths.setup(P, O)
        a = simulate_sharded(*args, 1e-3, devices=None, **opts)
        assert len(a.metrics.rms_error.sharding.device_set) == 2
        assert {d.process_index for d in a.metrics.rms_error.sharding.device_set} == {0, 1}
        a = multihost_utils.process_allgather(a, tiled=True)
        b = fj.simulate_batch(*args, 1e-3, **opts)  # this process alone, its own device
        performance_paths.assert_close(a, b, rtol=1e-12)
    multihost_utils.sync_global_devices("done")
    print(f"process {pid}: ok", flush=True)
    """
)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow  # two processes start, connect and compile (~25-40 s)
def test_two_processes_equal_single_process(tmp_path):
    tests = os.path.dirname(os.path.abspath(__file__))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")]))
    for k in ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES", "JAX_PLATFORMS"):
        env.pop(k, None)
    env["JAX_PLATFORMS"] = "cpu"
    address = f"127.0.0.1:{free_port()}"
    logs = [open(tmp_path / f"process{i}.log", "w+") for i in range(2)]
    procs = [subprocess.Popen([sys.executable, "-c", WORKER, address, str(i)], env=env, stdout=logs[i],
                              stderr=subprocess.STDOUT, text=True) for i in range(2)]  # fmt: skip
    deadline = time.monotonic() + 120
    try:
        for p in procs:
            p.wait(timeout=max(1.0, deadline - time.monotonic()))
    except subprocess.TimeoutExpired:
        pass
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    out = []
    for f in logs:
        f.seek(0)
        out.append(f.read())
        f.close()
    report = "\n".join(f"--- process {i} (exit {p.returncode}) ---\n{o[-3000:]}" for i, (p, o) in
                       enumerate(zip(procs, out)))  # fmt: skip
    if any(p.returncode != 0 for p in procs) and any("UNAVAILABLE" in o or "collectives" in o.lower() for o in out):
        pytest.fail("the two jax.distributed processes failed (coordinator or CPU collectives):\n" + report)
    assert all(p.returncode == 0 for p in procs), "a process failed or timed out (120 s):\n" + report
    assert all(f"process {i}: ok" in o for i, o in enumerate(out)), report
