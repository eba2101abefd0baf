"""Property-based tests of config validation: random malformed configs never raise anything but
:class:`ConfigError`, whose message is one line naming a key; through the CLI, exit status 2
and one stderr line, before any simulation.

Gaps these properties found (integers beyond float range, newlines in unknown keys, bools and
strings inside arrays, unbounded step counts) are fixed; the tests at the end pin them.
"""

import math
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from fosmc_jax import _problems as _config
from fosmc_jax._app.cli import main


def _paths(schema, prefix=""):
    for key, rule in schema.items():
        name = f"{prefix}.{key}" if prefix else key
        yield name, rule
        if isinstance(rule, dict):
            yield from _paths(rule, name)


PATHS = dict(_paths(_config.SCHEMA))  # "sim.dt" -> validator or sub-schema
LEAVES = sorted(k for k, v in PATHS.items() if not isinstance(v, dict))
SECTIONS = sorted(k for k, v in PATHS.items() if isinstance(v, dict))
KEY_TEXT = st.text("abcdefgh_-XYZ0123456789", min_size=1, max_size=8)

# TOML integers are arbitrary-size in tomllib, but those beyond float range are a known gap
# (see test_huge_integer_is_a_config_error); keep to 64-bit here, as TOML 1.0 requires.
INT64 = st.integers(-(2**63), 2**63 - 1)
FLOATS = st.floats(allow_nan=True, allow_infinity=True)
scalars = st.one_of(
    st.booleans(),
    INT64,
    FLOATS,
    st.sampled_from([0, -1, 0.0, -0.0, 1e-300, 1e300, float("nan"), float("inf"), -float("inf")]),
    st.text(max_size=6),
    st.sampled_from(["sign", "ratio", "euler", "rk4", "linear", "arm", "float64", "1.0", "nan"]),
)
matrices = st.integers(0, 4).flatmap(
    lambda r: st.integers(0, 10).flatmap(
        lambda c: st.lists(
            st.lists(st.one_of(st.floats(-1e3, 1e3), FLOATS), min_size=c, max_size=c),
            min_size=r,
            max_size=r,
        )
    )
)
values = st.recursive(
    st.one_of(scalars, matrices, st.lists(st.floats(-20, 20), max_size=10)),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(KEY_TEXT, inner, max_size=3),
    max_leaves=10,
)


#: Valid values for the keys that have no default (absent means "off": no voltage limit).
NO_DEFAULT = {"actuator.u_max": [10.0, 10.0, 10.0]}


def _default(path):
    if path in NO_DEFAULT:
        return NO_DEFAULT[path]
    node = _config.defaults()
    for part in path.split("."):
        node = node[part]
    return node


def _perturbed(path):
    """The default value of ``path`` with one entry spoiled, or the default itself."""
    d = _default(path)
    if isinstance(d, list) and d and not isinstance(d[0], str):
        flat = np.asarray(d, dtype=float).ravel()

        def spoil(i, v):
            out = flat.astype(object)
            out[i % out.size] = v
            return np.asarray(out).reshape(np.shape(d)).tolist()

        return st.builds(
            spoil,
            st.integers(0, 100),
            st.sampled_from([float("nan"), float("inf"), -1.0, 0.0, 1e9]),
        )
    return st.just(d)


@st.composite
def configs(draw):
    cfg: dict = {}
    for path in draw(st.lists(st.sampled_from(LEAVES), max_size=5, unique=True)):
        value = draw(st.one_of(values, _perturbed(path)))
        node = cfg
        *parents, leaf = path.split(".")
        for p in parents:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                break
        else:
            node[leaf] = value
    if draw(st.booleans()):  # an unknown key somewhere
        where = draw(st.sampled_from([""] + SECTIONS))
        node = cfg
        for p in filter(None, where.split(".")):
            node = node.setdefault(p, {})
        if isinstance(node, dict):
            node[draw(KEY_TEXT)] = draw(scalars)
    if draw(st.integers(0, 9)) == 0:  # a whole section of the wrong type
        cfg[draw(st.sampled_from([s for s in SECTIONS if "." not in s]))] = draw(scalars)
    return cfg


def _names_a_key(msg: str, cfg: dict) -> bool:
    head = msg.split(":", 1)[0]
    if head in PATHS or head == "config":
        return True
    # an unknown key: "<known section path>.<the key>"
    parent, _, _ = head.rpartition(".")
    return parent == "" or parent in SECTIONS


def _check_error(e: _config.ConfigError, cfg) -> None:
    msg = str(e)
    assert msg and "\n" not in msg, msg
    assert _names_a_key(msg, cfg), msg


# Derandomized by default, so that a CI run cannot go red on a draw no one can replay; set
# FOSMC_HYPOTHESIS_RANDOM=1 (and FOSMC_HYPOTHESIS_EXAMPLES=5000) to explore fresh cases.
FAST = settings(
    max_examples=int(os.environ.get("FOSMC_HYPOTHESIS_EXAMPLES", 300)),
    derandomize=not os.environ.get("FOSMC_HYPOTHESIS_RANDOM"),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)


@FAST
@given(configs())
def test_resolve_returns_a_config_or_raises_config_error(cfg):
    try:
        out = _config.resolve(cfg)
    except _config.ConfigError as e:
        _check_error(e, cfg)
        assert isinstance(e, ValueError)
        return
    assert isinstance(out, _config.Config) and set(out) == set(_config.SCHEMA)


@FAST
@given(st.sampled_from(LEAVES), values)
def test_any_value_at_any_key(path, value):
    cfg: dict = {}
    node = cfg
    *parents, leaf = path.split(".")
    for p in parents:
        node = node.setdefault(p, {})
    node[leaf] = value
    try:
        _config.resolve(cfg)
    except _config.ConfigError as e:
        _check_error(e, cfg)
        # cross-field rules name the key they hold: a link's centre of mass within its length,
        # the payloads within the arm's range
        related = {"arm.l2": "arm.c2", "arm.l3": "arm.c3", "arm.payload_range": "plant.payloads"}
        assert e.args[0].split(":", 1)[0] in (
            path,
            related.get(path),
            "controller",
            "sim.dt",
            "model.B_rows",
        ) or path.startswith("plant.box")


# ---------------------------------------------------------------------------- through the CLI


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f'"{k}" = {_toml_value(x)}' for k, x in v.items()) + "}"
    raise TypeError(type(v))


def _toml(cfg: dict) -> str:
    top = [f'"{k}" = {_toml_value(v)}' for k, v in cfg.items() if not isinstance(v, dict)]
    return "\n".join(top + [f'"{k}" = {_toml_value(v)}' for k, v in cfg.items() if isinstance(v, dict)]) + "\n"


@settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(cfg=configs())
def test_cli_exits_2_with_one_line(cfg, tmp_path_factory, capsys):
    try:
        _config.resolve(cfg)
    except _config.ConfigError:
        pass
    else:
        assume(False)  # valid configs would simulate: not this test's business
    path = tmp_path_factory.mktemp("cfg") / "c.toml"
    path.write_text(_toml(cfg))
    capsys.readouterr()
    code = main(["simulate", "--config", str(path)])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fosmc: error: "), err


@pytest.mark.parametrize(
    "text",
    [None, "", "[sim\n", "sim = 1 = 2", "[sim]\ndt = 0.1\n[sim]\ndt = 0.2\n", "\x00"],
    ids=["missing", "directory", "bad-toml-1", "bad-toml-2", "duplicate-table", "nul"],
)
def test_cli_unreadable_or_invalid_files(text, tmp_path, capsys):
    if text is None:
        path = tmp_path / "nope.toml"
    elif text == "":
        path = tmp_path  # a directory
    else:
        path = tmp_path / "c.toml"
        path.write_text(text)
    code = main(["simulate", "--config", str(path)])
    _, err = capsys.readouterr()
    assert code == 2 and len(err.strip().splitlines()) == 1 and err.startswith("fosmc: error: "), err


@pytest.mark.parametrize(
    "cfg",
    [
        {"plant": {"payloads": []}},
        {"sim": {"initial_offset": []}},
        {"tune": {"params": []}},
        {"plant": {"samples": 0}},
        {"sim": {"dt": 0.0}},
        {"sim": {"t_final": -1.0}},
        {"controller": {"delta": [1.0, 0.0, 1.0]}},
        {"controller": {"poles": [[-1, -2, 0], [-1, -2, -3], [-1, -2, -3]]}},
        {"controller": {"C": [[0] * 9] * 3}},
        {"plant": {"payloads": [11.0]}},
        {"model": {"B_rows": [[1, 2, 3], [2, 4, 6], [0, 0, 1]]}},
    ],
)
def test_named_malformed_configs(cfg):
    with pytest.raises(_config.ConfigError) as e:
        _config.resolve(cfg)
    _check_error(e.value, cfg)


# ---------------------------------------------------------------------------- gaps found by the properties, fixed


@pytest.mark.parametrize(
    "cfg",
    [
        {"sim": {"dt": 10**400}},
        {"trajectory": {"start": [10**400, 0, 0]}},
        {"plant": {"payloads": [10**400]}},
    ],
    ids=["number", "array", "payloads"],
)
def test_huge_integer_is_a_config_error(cfg):
    with pytest.raises(_config.ConfigError):
        _config.resolve(cfg)


def test_unknown_key_with_newline_is_one_line():
    with pytest.raises(_config.ConfigError) as e:
        _config.resolve({"a\nb": 1})
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("cfg", [{"controller": {"gamma": [1, 2, "3"]}}, {"plant": {"payloads": [True]}}])
def test_non_numbers_inside_arrays_are_rejected(cfg):
    with pytest.raises(_config.ConfigError):
        _config.resolve(cfg)


def test_step_count_is_bounded():
    with pytest.raises(_config.ConfigError):
        _config.n_steps(_config.resolve({"sim": {"t_final": 1e300, "dt": 1e-300}}))


# ---------------------------------------------------------------------------- the typed config


@pytest.mark.parametrize("user", [{}, {"plant": {"kind": "arm", "payloads": [0.0, 5.0]}, "actuator": {},
                                      "controller": {"kind": "smc", "sample_period": 1e-3},
                                      "sensors": {"encoder_counts": 4096}}])  # fmt: skip
def test_a_resolved_config_is_typed_frozen_and_its_mapping_is_the_toml_layout(user):
    cfg = _config.resolve(user)
    layout = cfg.as_dict()
    assert set(layout) == set(_config.SCHEMA) and _config.resolve(layout) == cfg  # resolving it again: the same
    assert cfg.sim.dt == cfg["sim"]["dt"] == layout["sim"]["dt"]
    assert cfg.controller.delta == tuple(layout["controller"]["delta"])  # vectors: tuples typed, lists in the layout
    assert cfg["controller"]["delta"] == layout["controller"]["delta"] and cfg.model.source == layout["model"]["from"]
    assert cfg.controller.gains["smc_k"] == tuple(layout["controller"]["smc_k"]) == tuple(cfg["controller"]["smc_k"])
    assert (
        cfg.arm.params.F == tuple(layout["arm"]["F"])
        and cfg.arm.uncertainty.widths.F == layout["arm"]["uncertainty"]["F"]
    )
    assert ("u_max" in cfg["actuator"]) == (cfg.actuator.u_max is not None) == ("u_max" in layout["actuator"])
    hash(cfg)
    with pytest.raises(TypeError):
        cfg["sim"]["dt"] = 1.0
    with pytest.raises(AttributeError):
        cfg.sim.dt = 1.0


def test_replace_makes_a_variant_checked_again():
    cfg = _config.resolve({})
    short = _config.replace(cfg, sim={"t_final": 0.5}, controller={"delta": [1.0, 2.0, 3.0]})
    assert short.sim.t_final == 0.5 and short.controller.delta == (1.0, 2.0, 3.0) and cfg.sim.t_final != 0.5
    assert short.sim.dt == cfg.sim.dt and short.plant == cfg.plant
    with pytest.raises(_config.ConfigError, match=r"^sim\.dt: expected at most sim\.t_final"):
        _config.replace(cfg, sim={"t_final": 1e-5})
    with pytest.raises(_config.ConfigError, match=r"^simm: unknown table"):
        _config.replace(cfg, simm={"dt": 1e-3})
