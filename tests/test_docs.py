"""The documentation builds without a warning, and its API pages document every keyword of the algorithms."""

import inspect
import re
import subprocess
import sys
from pathlib import Path

import pytest

from sb3_cql import BC, CQL, IQL

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def html(tmp_path_factory) -> Path:
    """The site built as the docs say to build it: ``sphinx-build -W`` (every warning an error)."""
    out = tmp_path_factory.mktemp("html")
    build = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "-q", "-b", "html", str(ROOT / "docs"), str(out)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert build.returncode == 0, build.stderr[-4000:]
    return out


def documented_keywords(page: Path) -> set[str]:
    """The names of the parameter fields on a built page (autodoc renders ``:param name:`` as ``<strong>name</strong>``)."""
    return set(re.findall(r"<strong>(\w+)</strong>", page.read_text()))


@pytest.mark.parametrize(("algorithm", "page"), [(CQL, "cql.html"), (BC, "bc.html"), (IQL, "iql.html")])
def test_the_api_pages_document_every_keyword(html, algorithm, page):
    keywords = set(inspect.signature(algorithm.__init__).parameters) - {"self"}
    assert keywords - documented_keywords(html / page) == set()


def test_every_page_is_built_and_links_to_no_missing_page(html):
    sources = {path.stem for path in (ROOT / "docs").glob("*.md")}
    built = {path.stem for path in html.glob("*.html")}
    assert sources <= built
    for page in html.glob("*.html"):
        for target in re.findall(r'href="([\w-]+\.html)', page.read_text()):
            assert (html / target).exists(), f"{page.name} links to {target}"
    # The protocol page embeds the figures the report makes.
    protocol = (html / "protocol.html").read_text()
    for figure in (ROOT / "results" / "figures").glob("*.png"):
        assert figure.name in protocol
        assert (html / "_images" / figure.name).exists()
