"""JAX's persistent compilation cache: off on import, on in the command line (in the user's
cache folder, overridden by JAX_COMPILATION_CACHE_DIR, off with FOSMC_JAX_COMPILATION_CACHE=0),
and a second run loads what the first compiled, with the same results."""

import json
import os
import subprocess
import sys

import pytest

CONFIG = """
[plant]
kind = "arm"
payloads = [0.0, 10.0]
[sim]
integrator = "rk4"
t_final = 0.05
dt = 1e-4
"""


def env_without_cache(tmp_path, **extra):
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", "FOSMC_JAX_CACHE")}
    return dict(env, FOSMC_JAX_CACHE=str(tmp_path / "cache"), **extra)


def test_import_changes_no_jax_setting(tmp_path):
    code = "import jax, fosmc_jax; print(jax.config.jax_compilation_cache_dir)"
    out = subprocess.run([sys.executable, "-c", code], env=env_without_cache(tmp_path), capture_output=True,
                         text=True, timeout=120, check=True)  # fmt: skip
    assert out.stdout.strip() == "None"


@pytest.mark.slow
def test_command_line_runs_reuse_their_compilations(tmp_path):
    config = tmp_path / "arm.toml"
    config.write_text(CONFIG)
    xla = tmp_path / "cache" / "xla"

    def simulate(**extra):
        cmd = [sys.executable, "-m", "fosmc_jax", "simulate", "--config", str(config), "--json", "--devices", "1"]
        out = subprocess.run(cmd, env=env_without_cache(tmp_path, **extra), capture_output=True, text=True,
                             timeout=300, check=True)  # fmt: skip
        return [r["metrics"] for r in json.loads(out.stdout)["rollouts"]]

    off = simulate(FOSMC_JAX_COMPILATION_CACHE="0")
    assert not xla.exists()
    first = simulate()
    entries = {p.name for p in xla.iterdir()}
    assert entries, "the first run wrote its programs"
    assert simulate() == first == off
    assert {p.name for p in xla.iterdir()} == entries, "the second run compiled nothing new"
    other = tmp_path / "jax-own"
    simulate(JAX_COMPILATION_CACHE_DIR=str(other))
    assert any(other.iterdir())
