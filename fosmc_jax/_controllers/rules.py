"""How the simulator checks its inputs, one field at a time (:class:`Field`), and the tests
its rules are made of.

A controller kind declares the rules of its own types (:attr:`fosmc_jax._controllers.kind.Kind.rules`,
e.g. ``{FOSMCParams: {"delta": Field((3,), positive, "3 positive numbers"), ...}}``);
:func:`fosmc_jax._simulator.checks.check_inputs` applies them, with its own rules for the plants,
the digital loop and the references, at :func:`fosmc_jax.simulate`'s edge.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

#: A field's ``shape`` when it holds an object checked by its own type's rules (if any).
NESTED = "nested"
#: A field's ``shape`` when it is static (a Python value fixing shapes or code paths).
STATIC = "static"


class Field(NamedTuple):
    """How one field is checked.

    ``shape``: the unbatched shape, a name (``"O"``) standing for any length; or
    :data:`NESTED`, :data:`STATIC`. ``rule``: for an array, an elementwise test of its
    concrete values (NumPy in, booleans out); for a static field, a test of its value; None:
    no test. ``what``: what is expected, in the errors. ``optional``: None is accepted."""

    shape: tuple | str
    rule: Callable[[Any], Any] | None
    what: str
    optional: bool = False


# Elementwise tests; NaN fails every one of them.
finite = np.isfinite


def positive(a: np.ndarray) -> np.ndarray:
    return np.isfinite(a) & (a > 0)


def non_negative(a: np.ndarray) -> np.ndarray:
    return np.isfinite(a) & (a >= 0)


def left_half_plane(a: np.ndarray) -> np.ndarray:
    return np.isfinite(a) & (np.real(a) < 0)


def positive_or_inf(a: np.ndarray) -> np.ndarray:
    return a > 0


def one_of(choices: tuple[str, ...]) -> Field:
    """A static field holding one of ``choices``."""
    return Field(STATIC, lambda v: v in choices, f"one of {', '.join(choices)}")


def integer(least: int) -> Field:
    """A static field holding a Python int (not a bool) of at least ``least``."""
    return Field(STATIC, lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= least,
                 f"an integer >= {least}")  # fmt: skip


NESTED_FIELD = Field(NESTED, None, "")
MATRIX_3x9 = Field((3, 9), finite, "a 3x9 matrix of finite numbers")
#: The nominal (or a linear plant's) rows 3, 6, 9 of A and B, as fields ``a_rows`` and ``b_rows``.
ROWS = {"a_rows": Field((3, 9), finite, "a 3x9 matrix of finite numbers (rows 3, 6, 9 of A)"),
        "b_rows": Field((3, 3), finite, "a 3x3 matrix of finite numbers (rows 3, 6, 9 of B)")}  # fmt: skip
GAINS = Field((3,), positive, "3 positive numbers")
PERIOD = Field((), positive, "a positive number (s)")
