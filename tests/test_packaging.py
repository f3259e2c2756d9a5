"""What a fresh install may pick up: every dependency bounded below its next breaking release."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _requirements():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    yield from project["dependencies"]
    for extra in project["optional-dependencies"].values():
        yield from extra


def test_every_dependency_has_a_lower_and_an_upper_bound():
    for req in _requirements():
        name = re.match(r"[A-Za-z0-9_.-]+", req).group(0)
        spec = req[len(name):]
        assert ">=" in spec and "<" in spec.replace("<=", ""), (
            f"{req}: give a lower bound and an upper bound (the next major release), so a fresh "
            "install cannot pick up a breaking release unnoticed")


def test_readme_commands_use_a_virtual_environment():
    # Debian's system Python refuses pip outside a venv (PEP 668): both commands make one.
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)\n```", text, flags=re.S)
    main_job, tests = blocks[0], blocks[1]
    for cmd in (main_job, tests):
        assert cmd.count("\n") == 0, cmd
        assert "python3 -m venv .venv" in cmd and ".venv/bin/python -m pip install" in cmd
    assert main_job.endswith(".venv/bin/aerec view")
    assert tests.endswith(".venv/bin/python -m pytest -p no:dash -q")
    ci = (ROOT / ".ci" / "run").read_text()
    assert tests in ci, ".ci/run must run the README's test command verbatim"
