"""The README's Python example runs as written (so the README stays true)."""

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def test_python_api_example_runs():
    code = re.search(r"## Python API\n\n```python\n(.*?)```", README.read_text(), re.S).group(1)
    scope: dict = {}
    exec(compile(code, "README.md", "exec"), scope)
    assert scope["res"].metrics.max_abs_error.shape == (256, 3)


def test_readme_opens_with_the_two_commands():
    lines = README.read_text().splitlines()
    block = lines[lines.index("```bash") + 1 : lines.index("```bash") + 3]
    assert block[0].startswith("make run") and block[1].startswith("make test")


def commands_example() -> str:
    text = README.read_text()
    section = text[text.index("### The commands from Python") :]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_commands_example_shows_every_command_function():
    import fosmc_jax

    code = commands_example()
    for command in ("simulate", "bounds", "certify", "tune", "front", "reproduce"):
        assert f"fj.run_{command}(" in code and f"run_{command}" in fosmc_jax.__all__


@pytest.mark.slow  # one short run of every command (~1 min on 2 cores)
def test_commands_example_runs(capsys):
    scope: dict = {}
    exec(compile(commands_example(), "README.md", "exec"), scope)
    assert scope["sim"]["rollouts"][0]["metrics"]["rms_error"].shape == (3,)
    assert scope["cert"]["holds"] in (True, False) and len(scope["front"]["points"]) >= 1
    assert capsys.readouterr().out.strip() == scope["tables"]["files"]["metrics.md"].strip()
