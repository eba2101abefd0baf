"""Shared test setup: float64 for the numerics tests (float32 is tested explicitly, with
float32 inputs, in test_simulator.py)."""

import jax

jax.config.update("jax_enable_x64", True)
