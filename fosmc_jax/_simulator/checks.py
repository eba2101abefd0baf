"""The simulator's inputs checked at the API's edge (:func:`check_inputs`).

:func:`fosmc_jax.simulate` and :func:`fosmc_jax.simulate_batch` run :func:`check_inputs` on
every Python call, before their jitted programs. Every rule is one entry of :func:`rules`
(the package's plant, loop and reference types, field by field, in :data:`RULES`, and each
registered controller kind's types, in its ``Kind.rules``), of :data:`ARGUMENTS` (X0, dt, the
keys) or of :data:`OPTIONS` (the keyword options; a name the functions do not take is refused):
shapes are checked always, tracers included (under ``jit``, ``grad`` and ``vmap`` shapes are
known), values (finite, signs, ranges) wherever they are concrete. A type without rules (a
user's controller, plant or reference) passes as it is.
"""

from __future__ import annotations

import dataclasses
import functools
import numbers
import warnings
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._controllers import KINDS
from .._controllers.base import PlacedPoles
from .._controllers.fosmc import LAWS, SWITCHING
from .._controllers.rules import (
    NESTED,
    NESTED_FIELD,
    PERIOD,
    ROWS,
    STATIC,
    Field,
    finite,
    integer,
    non_negative,
    one_of,
    positive,
    positive_or_inf,
)
from .._design.gains import stable_step
from .._loop.digital import DERIVATIVES, DigitalLoop, Sensors
from .._plants.arm import Arm, ArmParams
from .._plants.linear import LinearPlant
from .._plants.reference import Cycloid, Sinusoid
from .step import INTEGRATORS

#: The last entry of a key's ``shape``: 2 for raw keys (uint32 pairs), none for typed keys.
KEY = "key"

_ANGLES = Field((3,), finite, "3 finite numbers (rad)")
_LENGTH = Field((), non_negative, "a non-negative length (m)")
_MASS = Field((), non_negative, "a non-negative mass (kg)")
_INERTIAS = Field((3,), non_negative, "3 non-negative inertias (kg m^2)")

#: The package's types other than the controller kinds' (which declare theirs: ``Kind.rules``),
#: field by field (from their docstrings and the config's validators,
#: ``fosmc_jax._problems.schema.SCHEMA``). In a batch of plants every array has a leading axis P too.
RULES: dict[type, dict[str, Field]] = {
    Sensors: {
        "counts": Field((3,), non_negative, "3 non-negative encoder counts per revolution (0: exact)"),
        "noise_std": Field((9,), non_negative, "9 non-negative standard deviations, or None", optional=True),
        "derivatives": one_of(DERIVATIVES),
    },
    DigitalLoop: {
        "law": NESTED_FIELD,
        "sensors": NESTED_FIELD,
        "u_max": Field((3,), positive_or_inf, "3 positive numbers (V; inf: no limit)"),
        "period": PERIOD,
        "sample_steps": integer(1),
        "delay": integer(0),
    },
    LinearPlant: dict(ROWS),
    ArmParams: {
        "d1": Field((), finite, "a finite number (m)"),
        "d2": Field((), finite, "a finite number (m)"),
        "d3": Field((), finite, "a finite number (m)"),
        "l2": _LENGTH,
        "l3": _LENGTH,
        "c2": _LENGTH,
        "c3": _LENGTH,
        "m2": _MASS,
        "m3": _MASS,
        "I1": Field((), non_negative, "a non-negative inertia (kg m^2)"),
        "I2": _INERTIAS,
        "I3": _INERTIAS,
        "Jm": _INERTIAS,
        "F": Field((3,), non_negative, "3 non-negative friction coefficients (N m s/rad)"),
        "g": Field((), finite, "a finite number (m/s^2)"),
        "R": Field((3,), non_negative, "3 non-negative resistances (ohm)"),
        "L": Field((3,), positive, "3 positive inductances (H)"),
        "Kt": Field((3,), positive, "3 positive torque constants (N m/A)"),
        "Kb": Field((3,), non_negative, "3 non-negative back-EMF constants (V s/rad)"),
        "Fc": Field((3,), non_negative, "3 non-negative Coulomb friction levels (N m), or None", optional=True),
        "v_coulomb": Field((), positive, "a positive velocity scale (rad/s)"),
        "tau_bias": Field((3,), finite, "3 finite torques (N m), or None", optional=True),
        "tau_step": Field((3,), finite, "3 finite torques (N m), or None", optional=True),
        "t_step": Field((), finite, "a finite time (s)"),
        "tau_sin": Field((3,), finite, "3 finite torques (N m), or None", optional=True),
        "f_sin": Field((3,), non_negative, "3 non-negative frequencies (Hz)"),
    },
    # the range of payloads belongs to the configured arm ([arm] payload_range, checked by the
    # config): an Arm does not carry it, so only a negative payload is refused here
    Arm: {"params": NESTED_FIELD, "payload": Field((), non_negative, "a non-negative payload (kg)")},
    Cycloid: {"start": _ANGLES, "end": _ANGLES, "duration": PERIOD},
    Sinusoid: {
        "offset": _ANGLES,
        "amplitude": _ANGLES,
        "frequency": Field((3,), finite, "3 finite numbers (rad/s)"),
        "phase": _ANGLES,
    },
}

_DT = Field((), positive, "a positive finite number (s)")
_ONE_KEY = Field((KEY,), None, "a key (jax.random.PRNGKey(seed): shape (2,); typed: ())")
#: The arguments of :func:`fosmc_jax.simulate` (False) and :func:`fosmc_jax.simulate_batch`
#: (True): the initial state(s), the step and the noise key(s) (options ``key``, ``keys``).
ARGUMENTS: dict[bool, dict[str, Field]] = {
    False: {"X0": Field((9,), finite, "9 finite numbers"), "dt": _DT, "key": _ONE_KEY},
    True: {
        "X0s": Field(("O", 9), finite, "initial states of 9 finite numbers each"),
        "dt": _DT,
        "keys": Field(("R", KEY), None, "R keys (jax.random.split(key, R): shape (R, 2); typed: (R,))"),
        "key": _ONE_KEY,
    },
}


def _count(least: int, what: str) -> Field:
    """A static option that is an integer (Python's or NumPy's, not a bool) of at least ``least``."""
    ok = lambda v: isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= least
    return Field(STATIC, ok, what)


_FLAG = Field(STATIC, lambda v: isinstance(v, bool), "True or False")
#: The options of :func:`fosmc_jax.simulate` and :func:`fosmc_jax.simulate_batch` whose values
#: are checked here; ``integrator`` and ``pairing`` the simulator checks itself, ``key`` and
#: ``keys`` are in :data:`ARGUMENTS`. Any name not among the function's options is refused.
OPTIONS: dict[str, Field] = {
    "n_steps": _count(1, "a positive integer (steps)"),
    "save_every": _count(0, "a non-negative integer (steps; 0: no trace)"),
    "checkpoint_every": _count(0, "a non-negative integer (steps; 0: none)"),
    "truncate_every": _count(0, "a non-negative integer (steps; 0: the full horizon)"),
    "switching": one_of(SWITCHING),
    "law": one_of(LAWS),
    "divergence_bound": Field((), positive_or_inf, "a positive number (inf: no bound)"),
    "chattering_cutoff": Field((), positive, "a positive frequency (Hz)"),
    "fast": _FLAG,
    "native": _FLAG,
}


def _check_options(walk: _Walk, batch: bool, options: dict, known: tuple[str, ...]) -> None:
    """``options``' names among ``known`` (else a ``TypeError`` naming the first unknown one)
    and the values of :data:`OPTIONS` (else a one-line ``ValueError``)."""
    unknown = [name for name in options if name not in known]
    if unknown:
        function = "simulate_batch" if batch else "simulate"
        raise TypeError(f"{unknown[0]}: not an option of {function} (its options: {', '.join(known)})")
    for name, field in OPTIONS.items():
        if name not in options:
            continue
        value = options[name]
        if field.shape is STATIC:
            if not field.rule(value):
                raise ValueError(f"{name}: expected {field.what}, got {_short(value)}")
        elif value is not None:
            walk.array(value, name, field)


def _shape_text(shape: tuple) -> str:
    return "(" + ", ".join(map(str, shape)) + ("," if len(shape) == 1 else "") + ")"


def _matches(shape: tuple, expected: tuple) -> bool:
    """Whether ``shape`` is ``expected``, where a name (``"O"``) stands for any length."""
    return len(shape) == len(expected) and all(isinstance(e, str) or e == n for e, n in zip(expected, shape))


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _replaced(obj: Any, changes: dict) -> Any:
    return dataclasses.replace(obj, **changes) if dataclasses.is_dataclass(obj) else obj._replace(**changes)


def rules() -> dict[type, Mapping[str, Field]]:
    """Every checked type's rules: each registered controller kind's (``Kind.rules``) and
    :data:`RULES`."""
    return {**{t: fields for kind in KINDS.values() for t, fields in kind.rules.items()}, **RULES}


class _Walk:
    """One call's walk over the inputs: the rules it applies, the dtype lists become, the
    leading axis of a batch of plants (set by its first array), and the parameters placing
    poles met (for the step warning)."""

    def __init__(self, X0: Any):
        self.X0 = X0
        self.rules = rules()
        self.lead: tuple | None = ()
        self.lead_path = ""
        self.placed: list[tuple[str, PlacedPoles]] = []

    @functools.cached_property
    def dtype(self) -> Any:
        """X0's floating dtype, else JAX's default float (the dtype lists become)."""
        dtype = getattr(self.X0, "dtype", None)
        return dtype if dtype is not None and jnp.issubdtype(dtype, jnp.floating) else jnp.result_type(float)

    def object(self, obj: Any, path: str) -> Any:
        """``obj`` with its fields checked and lists in them made arrays, if its type has
        :func:`rules` (recursively); as it is otherwise."""
        fields = self.rules.get(type(obj))
        if fields is None:
            return obj
        changes = {}
        for name, field in fields.items():
            value = getattr(obj, name)
            sub = f"{path}.{name}"
            if field.shape is NESTED:
                new = self.object(value, sub)
            elif field.shape is STATIC:
                if not field.rule(value):
                    raise ValueError(f"{sub}: expected {field.what}, got {_short(value)}")
                continue
            else:
                new = self.array(value, sub, field)
            if new is not value:
                changes[name] = new
        obj = _replaced(obj, changes) if changes else obj
        if isinstance(obj, PlacedPoles):
            self.placed.append((path, obj))
        return obj

    def array(self, value: Any, path: str, field: Field) -> Any:
        """``value`` (a list or tuple made an array) of ``field``'s shape (with the batch's
        leading axis), its concrete values passing ``field.rule``."""
        if value is None:
            if field.optional:
                return None
            raise ValueError(f"{path}: expected {field.what}, got None")
        if type(value) in (list, tuple):
            try:
                value = jnp.asarray(value, self.dtype)
            except (TypeError, ValueError):
                raise ValueError(f"{path}: expected {field.what}, got {_short(value)}") from None
        shape = getattr(value, "shape", None)
        if shape is None:
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise ValueError(f"{path}: expected {field.what}, got {type(value).__name__}")
            shape = ()
        expected = field.shape
        if expected and expected[-1] == KEY:
            typed = jax.dtypes.issubdtype(value.dtype, jax.dtypes.prng_key) if hasattr(value, "dtype") else False
            expected = expected[:-1] if typed else expected[:-1] + (2,)
        self.fit(path, tuple(shape), expected)
        if field.rule is not None and not isinstance(value, jax.core.Tracer):
            a = np.asarray(value)
            if a.dtype.kind not in "biufc":
                raise ValueError(f"{path}: expected {field.what}, got an array of {a.dtype}")
            ok = field.rule(a)
            if not ok.all():
                i = np.unravel_index(np.flatnonzero(~ok)[0], a.shape)
                at = "" if not i else f" at index {int(i[0])}" if len(i) == 1 else f" at index {tuple(map(int, i))}"
                raise ValueError(f"{path}: expected {field.what}, got {a[i]}{at}")
        return value

    def fit(self, path: str, shape: tuple, expected: tuple) -> None:
        """A one-line error unless ``shape`` is ``expected`` (names: any length) behind the
        batch's leading axis, which the first array of a batch of plants sets."""
        lead = self.lead
        full = ("P",) + expected if lead is None else lead + expected
        if shape != full and not _matches(shape, full):
            if lead is None:
                note = " (a leading axis of P plants)"
            else:
                note = f" (P = {lead[0]}, as {self.lead_path})" if lead else ""
            raise ValueError(f"{path}: expected shape {_shape_text(full)}{note}, got {shape}")
        if lead is None:
            self.lead, self.lead_path = shape[:1], path


# stable_step runs JAX in float64 (eigenvalues), hundreds of times the cost of the rest of the
# check. The check runs on every call, nearly always with the same parameters (but for a
# search's candidates, which are traced): a small cache of floats, keyed by the bytes.
@functools.lru_cache(maxsize=256)
def _stable_step(a_rows: bytes, b_rows: bytes, poles: bytes, poles_dtype: str, integrator: str) -> float:
    """:func:`fosmc_jax.stable_step` of the rows and poles given as bytes (float64; the poles
    of ``poles_dtype``), cached."""
    a = np.frombuffer(a_rows).reshape(3, 9)
    b = np.frombuffer(b_rows).reshape(3, 3)
    p = np.frombuffer(poles, poles_dtype).reshape(3, 3)
    with jax.ensure_compile_time_eval():  # concrete inputs: computed now, also inside a jit trace
        return stable_step(a, b, p, integrator)


def _step_limit(walk: _Walk, dt: Any, integrator: str) -> str | None:
    """The warning's text when concrete parameters placing poles in the controller
    (:class:`PlacedPoles`, as the FOSMC's) have a stable step below a concrete ``dt`` for a
    known ``integrator``; None otherwise."""
    if not walk.placed or isinstance(dt, jax.core.Tracer):
        return None
    if integrator not in INTEGRATORS:
        return None
    dt = float(np.asarray(dt))
    for path, params in walk.placed:
        rows = (params.a_rows, params.b_rows, params.poles)
        if any(isinstance(x, jax.core.Tracer) for x in rows):
            continue
        a, b = (np.asarray(x, np.float64).tobytes() for x in rows[:2])
        p = np.asarray(rows[2])
        p = p.astype(np.complex128 if np.iscomplexobj(p) else np.float64)
        h = _stable_step(a, b, p.tobytes(), p.dtype.str, integrator)
        if dt > h:
            return (f"dt = {dt:g} s exceeds the {integrator} stability limit {h:.3g} s of the nominal model's "
                    f"fastest mode ({path}): expect divergence")  # fmt: skip
    return None


def check_inputs(
    plant: Any, controller: Any, reference: Any, X0: Any, dt: Any, batch: bool, options: dict, known: tuple[str, ...]
) -> tuple[Any, ...]:
    """(plant, controller, reference, X0, dt) checked and normalised for :func:`fosmc_jax.simulate`
    (``batch`` False: X0 (9,), unbatched plant) or :func:`fosmc_jax.simulate_batch` (True:
    ``plants`` with a leading axis P on every leaf, X0s (O, 9), ``options["keys"]`` (R, 2) or R
    typed keys); ``options`` are theirs (read, not changed): a name not in ``known`` (the
    function's options, :func:`fosmc_jax._simulator.rollout.option_names`) is a ``TypeError``
    naming it, a value of :data:`OPTIONS` out of range (``n_steps`` not a positive integer) a
    ``ValueError``; X0 of an integer dtype a ``TypeError`` naming its dtype.

    The rules are :func:`rules` and :data:`ARGUMENTS`. Lists and tuples of numbers in the
    fields of those types, and X0 and dt given as lists, become arrays of X0's floating dtype
    (JAX's default float if X0 is not an array); other types are left alone. Raises a one-line
    ``ValueError`` naming the field by its path (``controller.params.delta``): on a wrong shape
    always (under ``jit``, ``grad`` and ``vmap`` too), on a non-finite or out-of-range value
    where the values are concrete. Warns (``UserWarning``) when dt exceeds
    :func:`fosmc_jax.stable_step` of concrete parameters placing poles in the controller
    (:class:`fosmc_jax._controllers.base.PlacedPoles`, as :class:`fosmc_jax.FOSMCParams`) for
    ``options["integrator"]`` (default ``rk4``).
    """
    names = ARGUMENTS[batch]
    x0_name, plant_name = ("X0s", "plants") if batch else ("X0", "plant")
    walk = _Walk(X0)
    _check_options(walk, batch, options, known)
    X0 = walk.array(X0, x0_name, names[x0_name])
    dtype = getattr(X0, "dtype", None)
    if dtype is not None and not jnp.issubdtype(dtype, jnp.floating):  # X0's dtype is the run's
        raise TypeError(f"{x0_name}: expected floating-point numbers (float32 or float64: the dtype sets the run's "
                        f"precision), got an array of {dtype}")  # fmt: skip
    dt = walk.array(dt, "dt", names["dt"])
    for key in ("keys", "key"):
        if key in names and options.get(key) is not None:
            walk.array(options[key], key, names[key])
    controller = walk.object(controller, "controller")
    reference = walk.object(reference, "reference")
    walk.lead = None if batch else ()
    plant = walk.object(plant, plant_name)
    message = _step_limit(walk, dt, options.get("integrator", "rk4"))
    if message is not None:
        warnings.warn(message, stacklevel=4)  # the caller of simulate / simulate_batch (through _checked)
    return plant, controller, reference, X0, dt
