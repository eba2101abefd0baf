"""Shared test setup: float64 for the numerics tests (float32 is tested explicitly, with
float32 inputs, in test_simulator.py), and one compilation cache for the whole session.

The cache: several code paths jit a fresh closure on every call (the front's and the tuner's
update steps, a CLI run), and some tests start a second Python process (a killed tuning run,
the sharded batch), so the same XLA program would be compiled again and again. JAX's
persistent compilation cache, keyed by the program itself (HLO, options, backend, version),
hands back the executable compiled the first time. It lives in a fresh directory per session
(also handed to subprocesses through the environment) and is removed at the end, so a run
never reuses what an earlier run compiled: the first compilation of each program is still
paid, and counted by the tests that count compilations."""

import atexit
import os
import shutil
import tempfile

import jax

jax.config.update("jax_enable_x64", True)
# One CPU device in the test process, whichever test runs first: the command line's default
# (every core, `use_all_cores`) respects a count the user set, so in-process CLI runs shard
# nothing and equal the functions they are compared with; the tests that shard start their
# own process without this setting.
jax.config.update("jax_num_cpu_devices", 1)

_CACHE = tempfile.mkdtemp(prefix="fosmc-test-jax-cache-")
atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)
os.environ["JAX_COMPILATION_CACHE_DIR"] = _CACHE
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0.2"
jax.config.update("jax_compilation_cache_dir", _CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
