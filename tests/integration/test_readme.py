"""The README opens with the two commands, and CI runs the second one verbatim."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    return re.findall(r"```bash\n(.+?)\n```", text)[:2]


def test_readme_opens_with_two_commands():
    install_run, install_test = readme_commands()
    assert "evchain run pipelines/quickstart.yaml" in install_run
    assert "pytest" in install_test
    head = (ROOT / "README.md").read_text().split("```bash")[0]
    assert head.strip().startswith("# evchain") and len(head.strip().splitlines()) <= 2


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    test_cmd = readme_commands()[1].split("&& ", 2)[2]  # after creating/activating the venv
    assert test_cmd in ci
