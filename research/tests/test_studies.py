"""Every study folder in research/studies/ names its commands and their dates, and the research index lists it."""

import re
from pathlib import Path

import pytest

RESEARCH = Path(__file__).resolve().parents[1]
STUDIES = sorted(path for path in (RESEARCH / "studies").iterdir() if path.is_dir())


def test_there_are_studies():
    assert len(STUDIES) >= 8


@pytest.mark.parametrize("study", STUDIES, ids=lambda path: path.name)
def test_every_study_folder_names_its_command_and_date(study):
    readme = (study / "README.md").read_text()
    assert re.search(r"python (-m |benchmarks/|research/scripts/)", readme) and re.search(r"\b2026-\d\d-\d\d\b", readme)
    assert f"](studies/{study.name}/README.md)" in (RESEARCH / "README.md").read_text()  # listed in the index
