"""A resolved config as typed values: one frozen dataclass per TOML table (:class:`Config` holds
:class:`Trajectory`, :class:`Model`, :class:`Controller`, :class:`Sensors`, :class:`Actuator`,
:class:`Plant`, :class:`Sim`, :class:`Sample`, :class:`Arm`, :class:`Tune`), made only by
:func:`fosmc_jax._problems.resolve.resolve` from values its schema has checked.

Numbers are Python ``float``/``int``, vectors and matrices nested tuples (``np.asarray`` turns
them into arrays), choices strings. Read a value as an attribute (``cfg.sim.dt``). Each table is
also a read-only mapping in the TOML's layout (``cfg["sim"]["dt"]``; vectors as lists), and
:meth:`Table.as_dict` is that layout as a fresh plain ``dict``: what result files record, and
what :func:`fosmc_jax.config.replace` and :func:`fosmc_jax.config.resolve` take back.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from typing import Any, ClassVar

from .._plants.arm import ArmParams

#: A vector (3 numbers), matrix (3 x 9) or list of vectors, as nested tuples.
Numbers = tuple


def frozen(value: Any) -> Any:
    """Lists (nested) as tuples; anything else as it is."""
    return tuple(frozen(v) for v in value) if isinstance(value, (list, tuple)) else value


def as_toml(value: Any) -> Any:
    """The TOML layout of a typed value: tables as dicts, tuples as lists."""
    if isinstance(value, Table):
        return value.as_dict()
    if isinstance(value, (list, tuple)):
        return [as_toml(v) for v in value]
    return value


class Table(Mapping):
    """A table of a resolved config: a frozen dataclass whose fields are its keys (``KEYS``
    renames a key that is no identifier), read-only as a mapping in the TOML's layout."""

    #: config key -> attribute, where they differ
    KEYS: ClassVar[dict[str, str]] = {}
    #: attribute -> the table class of a sub-table
    TABLES: ClassVar[dict[str, type]] = {}

    def entries(self) -> Iterator[tuple[str, Any]]:
        """(config key, typed value) in the TOML's order."""
        names = {attr: key for key, attr in self.KEYS.items()}
        for f in dataclasses.fields(self):
            yield names.get(f.name, f.name), getattr(self, f.name)

    @classmethod
    def of(cls, table: Mapping[str, Any]) -> Table:
        """The typed table of a validated plain one (every key present)."""
        names = {attr: key for key, attr in cls.KEYS.items()}
        values = {}
        for f in dataclasses.fields(cls):
            value = table[names.get(f.name, f.name)]
            values[f.name] = cls.TABLES[f.name].of(value) if f.name in cls.TABLES else frozen(value)
        return cls(**values)

    def as_dict(self) -> dict[str, Any]:
        """The table in the TOML's layout, a fresh plain dict (JSON-ready)."""
        return {key: as_toml(value) for key, value in self.entries()}

    def __getitem__(self, key: str) -> Any:
        for k, value in self.entries():
            if k == key:
                return value if isinstance(value, Table) else as_toml(value)
        raise KeyError(key)

    def __iter__(self) -> Iterator[str]:
        return (key for key, _ in self.entries())

    def __len__(self) -> int:
        return sum(1 for _ in self.entries())


_table = dataclasses.dataclass(frozen=True, eq=True, repr=True)


@_table
class Trajectory(Table):
    start: Numbers  # (3,) rad
    end: Numbers  # (3,) rad
    duration: float  # s


@_table
class Model(Table):
    KEYS: ClassVar[dict[str, str]] = {"from": "source"}
    source: str  # [model] from: "paper" or "arm"
    A_rows: Numbers  # (3, 9)
    B_rows: Numbers  # (3, 3)


@_table
class Gains(Mapping):
    """Every registered controller kind's own gains by config key (``smc_k``: 3 numbers), in
    registration order."""

    pairs: tuple[tuple[str, Numbers], ...]

    def __getitem__(self, key: str) -> Numbers:
        return dict(self.pairs)[key]

    def __iter__(self) -> Iterator[str]:
        return (key for key, _ in self.pairs)

    def __len__(self) -> int:
        return len(self.pairs)


@_table
class Controller(Table):
    C: Numbers  # (3, 9)
    poles: Numbers  # (3, 3) 1/s
    gamma: Numbers  # (3,)
    switching: str
    delta: Numbers  # (3,)
    law: str
    sample_period: float  # s; 0: the ideal loop
    delay_samples: int
    kind: str
    gains: Gains  # the kinds' own keys, flat in the TOML's table

    def entries(self) -> Iterator[tuple[str, Any]]:
        for key, value in super().entries():
            if key == "gains":
                yield from value.pairs
            else:
                yield key, value

    @classmethod
    def of(cls, table: Mapping[str, Any]) -> Controller:
        fixed = [f.name for f in dataclasses.fields(cls) if f.name != "gains"]
        gains = Gains(tuple((k, frozen(v)) for k, v in table.items() if k not in fixed))
        return cls(**{k: frozen(table[k]) for k in fixed}, gains=gains)


@_table
class Sensors(Table):
    encoder_counts: Numbers  # (3,) int counts per revolution; 0: exact
    derivatives: str
    noise_std: Numbers  # (9,)
    seed: int
    realizations: int


@_table
class Actuator(Table):
    u_max: Numbers | None = None  # (3,) V; None: no limit (absent from the TOML's table)

    def entries(self) -> Iterator[tuple[str, Any]]:
        return iter(() if self.u_max is None else (("u_max", self.u_max),))

    @classmethod
    def of(cls, table: Mapping[str, Any]) -> Actuator:
        return cls(frozen(table.get("u_max")))


@_table
class Box(Table):
    A_lower: Numbers  # (3, 9)
    A_upper: Numbers
    B_lower: Numbers  # (3, 3)
    B_upper: Numbers


@_table
class Plant(Table):
    TABLES: ClassVar[dict[str, type]] = {"box": Box}
    kind: str
    payloads: Numbers  # kg
    uncertainty: str
    dA_rows: Numbers  # (3, 9)
    dB_rows: Numbers  # (3, 3)
    samples: int
    seed: int
    box: Box


@_table
class Sim(Table):
    t_final: float  # s
    dt: float  # s
    integrator: str
    initial_offset: Numbers  # (9,) or (N, 9)
    precision: str
    save_every: int
    divergence_bound: float
    pairing: str


@_table
class Sample(Table):
    count: int
    seed: int
    payloads: Numbers  # () or (low, high) kg
    offsets: Numbers  # (9,) standard deviations


def _arm_fields(table: Mapping[str, Any]) -> ArmParams:
    return ArmParams(**{k: frozen(table[k]) for k in ArmParams._fields})


@_table
class ArmUncertainty(Table):
    widths: ArmParams  # relative half-widths by arm field (a number or one per joint)
    samples: int
    seed: int
    sampling: str

    def entries(self) -> Iterator[tuple[str, Any]]:
        yield from zip(ArmParams._fields, self.widths)
        yield from (("samples", self.samples), ("seed", self.seed), ("sampling", self.sampling))

    @classmethod
    def of(cls, table: Mapping[str, Any]) -> ArmUncertainty:
        return cls(_arm_fields(table), table["samples"], table["seed"], table["sampling"])


@_table
class Arm(Table):
    params: ArmParams  # the nominal arm: every ArmParams field as Python numbers and tuples
    payload_range: Numbers  # (low, high) kg
    uncertainty: ArmUncertainty

    def entries(self) -> Iterator[tuple[str, Any]]:
        yield from zip(ArmParams._fields, self.params)
        yield from (("payload_range", self.payload_range), ("uncertainty", self.uncertainty))

    @classmethod
    def of(cls, table: Mapping[str, Any]) -> Arm:
        return cls(_arm_fields(table), frozen(table["payload_range"]), ArmUncertainty.of(table["uncertainty"]))


@_table
class Tune(Table):
    params: tuple[str, ...]
    weight_error: float
    weight_chattering: float
    worst_case: str
    worst_weight: float
    cvar_alpha: float
    penalty: float
    steps: int
    optimizer: str
    learning_rate: float
    schedule: str
    clip: float
    mode: str
    checkpoint_every: int
    remat_steps: int
    gradient_window: float
    train_dt: float
    train_t_final: float
    keep_gamma_bound: bool
    gamma_bound_convention: str
    global_candidates: int
    starts: int
    cma_generations: int
    objective: str
    scale: str
    error_metric: str
    chattering_metric: str
    error_bound: float
    chattering_bound: float
    bound_weight: float


@_table
class Config(Table):
    """A resolved config: every table typed, every key filled in and checked."""

    TABLES: ClassVar[dict[str, type]] = {
        "trajectory": Trajectory, "model": Model, "controller": Controller, "sensors": Sensors,
        "actuator": Actuator, "plant": Plant, "sim": Sim, "sample": Sample, "arm": Arm, "tune": Tune,
    }  # fmt: skip
    trajectory: Trajectory
    model: Model
    controller: Controller
    sensors: Sensors
    actuator: Actuator
    plant: Plant
    sim: Sim
    sample: Sample
    arm: Arm
    tune: Tune
