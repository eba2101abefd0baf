"""Controller kinds (``[controller] kind``). A kind is one file, its law and a :class:`Kind`
record, plus one registry line (:func:`register`; the built-in kinds are registered in
``fosmc_jax/_controllers/__init__.py``): the config, ``fosmc tune``, ``fosmc front`` and the
result files then know it by its name, its parameters and its config keys.

A kind's tunable parameters are fields of its law (a dataclass pytree: the tuner replaces
them with ``dataclasses.replace``), except the FOSMC's, which are fields of its parameters
(:class:`fosmc_jax.FOSMCParams`). Every kind shares the FOSMC's sliding-surface matrix C and
nominal design rows (the ``[controller] C`` and ``[model]`` keys), which its law receives.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from collections.abc import Callable, Iterator, Mapping
from typing import Any, NamedTuple

import numpy as np

from .rules import Field


class Param(NamedTuple):
    """One tunable parameter: an array with one row per joint, scaled by one factor per joint."""

    name: str  # its field in the kind's parameters and law, and its name in result files
    key: str  # the [controller] config key it comes from and goes back to
    sign: int  # +1: positive, x = exp(u); -1: negative, x = -exp(u)
    box: tuple[float, float]  # log10 range of the front's scale factors around the config's value


class Space(NamedTuple):
    """A controller kind's tunable parameter set: the NamedTuple ``values`` holding them (its
    fields are the ``params``' names, in order) and the :class:`Param` of each."""

    kind: str
    values: type
    params: tuple[Param, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    @property
    def dim(self) -> int:
        """Number of the front's log factors: one per joint per parameter."""
        return 3 * len(self.params)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The front's box of log factors (dim,): each parameter's range, three joints each."""
        return np.repeat([p.box[0] for p in self.params], 3), np.repeat([p.box[1] for p in self.params], 3)


class Kind(NamedTuple):
    """Everything the package needs to know about a controller kind.

    ``space``: its tunable parameters (names, config keys, signs, the front's box); its name
    is ``space.kind``. ``gains``: its own ``[controller]`` keys, each three positive numbers
    (one per joint), with their defaults. ``law(params, controller, T)``: the law, from the
    FOSMC parameters (C and the nominal rows; the FOSMC's own gains), the resolved, typed
    ``[controller]`` table (``controller.gains``: the kind's gains as arrays of the run's dtype)
    and the sample period T (an array; ``controller.sample_period`` = 0: the ideal loop). ``ideal``: the
    ideal loop's controller around the law (None: the law itself). ``tunes_params``: its tunable
    parameters are fields of the FOSMC parameters the law is made from (the FOSMC's own), not of
    its law (every other kind's). ``hitting_condition``: the paper's hitting condition (20) is
    this kind's, so that ``fosmc certify`` checks it (the FOSMC's). ``gamma_bounds``: the paper's
    gamma bounds (24)-(26) are this kind's, so that ``[tune] keep_gamma_bound`` may hold its
    ``gamma`` above them (the FOSMC's). ``rules``: the input rules of its types (its law's, its
    parameters'), field by field (:class:`fosmc_jax._controllers.rules.Field`), which
    :func:`fosmc_jax.simulate` checks at its edge; a type without rules passes as it is.
    """

    space: Space
    gains: dict[str, tuple[float, float, float]]
    law: Callable[[Any, Any, Any], Any]
    ideal: Callable[[Any], Any] | None = None
    tunes_params: bool = False
    hitting_condition: bool = False
    gamma_bounds: bool = False
    rules: Mapping[type, Mapping[str, Field]] = {}

    @property
    def name(self) -> str:
        return self.space.kind


#: The registered kinds by name, in registration order.
KINDS: dict[str, Kind] = {}


def register(kind: Kind) -> Kind:
    """Make ``kind`` known by its name (a second registration of a name replaces the first)."""
    if not kind.name.isidentifier():
        raise ValueError(f"a controller kind's name must be an identifier, got {kind.name!r}")
    taken = {key for k in KINDS.values() if k.name != kind.name for key in k.gains}
    if taken & set(kind.gains):
        raise ValueError(f"controller kind {kind.name!r}: config keys {sorted(taken & set(kind.gains))} are taken")
    KINDS[kind.name] = kind
    return kind


#: The entry-point group through which an installed package registers its controller kinds: each
#: entry point names a :class:`Kind` (``[project.entry-points."fosmc_jax.kinds"]``,
#: ``mykind = "mypkg.mykind:KIND"``).
ENTRY_POINTS = "fosmc_jax.kinds"


def load(spec: str) -> Kind:
    """The kind a ``module:attribute`` spec names (``[controller] kind = "mypkg.mykind:KIND"``),
    imported and registered; a one-line ``ValueError`` when the module or the attribute is not
    found or is not a :class:`Kind`."""
    module, _, attribute = spec.partition(":")
    try:
        kind = getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError, ValueError) as e:
        raise ValueError(f"cannot load the controller kind {spec!r} ({type(e).__name__}: {e})") from None
    if not isinstance(kind, Kind):
        raise ValueError(f"{spec!r} is a {type(kind).__name__}, not a controller kind (fosmc_jax.search.Kind)")
    return register(kind)


def load_entry_points() -> list[Kind]:
    """Every kind installed packages declare in the :data:`ENTRY_POINTS` group, registered (a
    one-line ``ValueError`` naming an entry point that does not load or is not a :class:`Kind`)."""
    kinds = []
    for entry in importlib.metadata.entry_points(group=ENTRY_POINTS):
        kinds.append(load(entry.value))
    return kinds


def space_of(params: Any) -> Space:
    """The registered kind whose parameter set holds every name of ``params`` (a dict by
    parameter name, as result.json and front.json hold them); a one-line ``ValueError`` naming
    every kind's parameters otherwise."""
    if isinstance(params, dict) and params:
        for kind in KINDS.values():
            if set(params) <= set(kind.space.names):
                return kind.space
    kinds = "; ".join(f"{k.name}: {', '.join(k.space.names)}" for k in KINDS.values())
    got = sorted(params) if isinstance(params, dict) else type(params).__name__
    raise ValueError(f"params are no controller kind's parameter set ({kinds}), got {got}")


class _Spaces(Mapping):
    """Every registered kind's :class:`Space` by name (a live view of :data:`KINDS`)."""

    def __getitem__(self, name: str) -> Space:
        return KINDS[name].space

    def __iter__(self) -> Iterator[str]:
        return iter(KINDS)

    def __len__(self) -> int:
        return len(KINDS)


SPACES: Mapping[str, Space] = _Spaces()
