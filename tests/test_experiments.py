"""A smoke test of the research scripts in research/scripts/: each imports and shows its usage. Their own tests, which
run each script end to end, are in research/tests/ (``python -m pytest -n 0 research/tests``), outside the default
suite."""

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS_DIR = ROOT / "research" / "scripts"
SCRIPTS = sorted(path.stem for path in SCRIPTS_DIR.glob("[!_]*.py"))


def test_there_are_research_scripts():
    assert len(SCRIPTS) >= 13


@pytest.mark.parametrize("name", SCRIPTS)
def test_a_research_script_imports_and_shows_its_usage(name, capsys, monkeypatch):
    """The script loaded as ``python research/scripts/NAME.py`` loads it (its folder first on ``sys.path``, for
    ``_cli``), its ``main`` given ``--help``."""
    monkeypatch.syspath_prepend(str(SCRIPTS_DIR))
    spec = importlib.util.spec_from_file_location(f"research_scripts_{name}", SCRIPTS_DIR / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    with pytest.raises(SystemExit) as exit_:
        module.main(["--help"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: python research/scripts/{name}.py")


def test_the_package_never_imports_research():
    for path in (ROOT / "sb3_cql").rglob("*.py"):
        text = path.read_text()
        assert "import research" not in text and "from research" not in text, path
