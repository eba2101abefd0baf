"""Shared test setup: float64 for the numerics tests (float32 is tested explicitly, with
float32 inputs, in test_simulator.py), one compilation cache for the whole session, and, in a run
with pytest-xdist workers (`make test`), the long files scheduled first and the native kernel
built once (at the bottom).

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


# ------------------------------------------------------------------ pytest-xdist (`make test`)

#: The files that take longest in the default tier, longest first (compilation time per file
#: measured with jax.monitoring over a whole `make test` run on the 2-core machine; most of a
#: file's time is XLA compilation). Under `-n N --dist loadfile` whole files go to the workers in
#: this order, then the rest in collection order, so that no long file starts last while the other
#: workers idle: xdist's own order (the files with the most tests first) sent the long files with
#: few tests, test_arm_kernel.py's 4 for one, last. A file missing here only runs later.
LONG_FILES = (
    "test_simulator.py",
    "test_tuning_kinds.py",
    "test_arm_kernel.py",
    "test_front.py",
    "test_arm_disturbances.py",
    "test_digital_loop.py",
    "test_generated.py",
    "test_kernel_noise.py",
    "test_build.py",
    "test_arm.py",
    "test_performance_paths.py",
    "test_certify.py",
    "test_cli.py",
    "test_tuning.py",
    "test_export.py",
    "test_paper_results.py",
    "test_design_from_arm.py",
    "test_smc.py",
    "test_checks.py",
    "test_readme.py",
    "test_design.py",
    "test_robust_arms.py",
    "test_api.py",
)


def pytest_configure(config):
    if getattr(config, "workerinput", None) is not None or not getattr(config.option, "numprocesses", None):
        return  # a worker, or a run without workers
    # The controller of a run with workers: schedule in LONG_FILES' order (not by test count)
    config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file's order kept
