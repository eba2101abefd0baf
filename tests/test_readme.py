"""The README's Python example, and docs/api.md's commands from Python, run as written (so the
README and the API page stay true)."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
API = ROOT / "docs" / "api.md"


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
    """The first Python block of docs/api.md's section "The commands from Python"."""
    text = API.read_text()
    section = text[text.index("## The commands from Python") :]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_commands_example_shows_every_command_function():
    import fosmc_jax

    code = commands_example()
    for command in ("simulate", "bounds", "certify", "tune", "front", "reproduce"):
        assert f"fj.run_{command}(" in code and f"run_{command}" in fosmc_jax.__all__


@pytest.mark.slow  # one short run of every command (~1 min on 2 cores)
def test_commands_example_runs(capsys):
    scope: dict = {}
    exec(compile(commands_example(), "docs/api.md", "exec"), scope)
    assert scope["sim"]["rollouts"][0]["metrics"]["rms_error"].shape == (3,)
    assert scope["cert"]["holds"] in (True, False) and len(scope["front"]["points"]) >= 1
    assert capsys.readouterr().out.strip() == scope["tables"]["files"]["metrics.md"].strip()


def slug(heading: str) -> str:
    """GitHub's anchor for a Markdown heading: lower case, punctuation dropped, spaces to '-'."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_relative_links_resolve():
    """Every relative link of README.md and docs/*.md names a file of the repository (and, with
    #anchor into a Markdown file, one of its headings): the pages stand alone in a clone."""
    broken = []
    for page in [README, *sorted((ROOT / "docs").glob("*.md"))]:
        text = page.read_text()
        for target in re.findall(r"\]\(([^)\s]+)\)", text) + re.findall(r'href="([^"]+)"', text):
            if re.match(r"[a-z]+:", target):
                continue
            path, _, anchor = target.partition("#")
            file = (page.parent / path).resolve() if path else page
            if not file.exists() or ROOT not in file.parents:
                broken.append(f"{page.name}: {target}")
            elif anchor and file.suffix == ".md":
                headings = re.findall(r"^#+ (.+)$", file.read_text(), re.M)
                if anchor not in {slug(h) for h in headings}:
                    broken.append(f"{page.name}: {target} (no such heading)")
    assert not broken, broken
