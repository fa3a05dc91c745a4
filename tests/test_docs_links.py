"""The README and the pages under docs/: every relative link resolves inside the repository
(files and #anchors), every page is linked from the README, and the README states the defaults
the code has."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = sorted((ROOT / "docs").glob("*.md"))
DOCUMENTS = [README, *PAGES]

#: [text](target) and ![alt](target), the target up to a space or the closing parenthesis.
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)


def _prose(text: str) -> str:
    """The text without fenced code blocks and inline code (links there are not links)."""
    text = FENCE.sub("", text)
    return re.sub(r"`[^`\n]*`", "", text)


def links(path: Path) -> list[str]:
    return LINK.findall(_prose(path.read_text(encoding="utf-8")))


def anchors(path: Path) -> set[str]:
    """GitHub's heading anchors of a Markdown file."""
    out = set()
    for line in FENCE.sub("", path.read_text(encoding="utf-8")).splitlines():
        m = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower().replace("`", ""))
            out.add(slug.replace(" ", "-"))
    return out


def test_there_are_pages_and_links():
    assert len(PAGES) >= 8
    assert len(links(README)) >= len(PAGES)


@pytest.mark.parametrize("doc", DOCUMENTS, ids=[str(p.relative_to(ROOT)) for p in DOCUMENTS])
def test_relative_links_resolve_inside_the_repository(doc):
    for target in links(doc):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        where, _, anchor = target.partition("#")
        path = (doc.parent / where).resolve() if where else doc
        assert path.is_relative_to(ROOT), f"{doc.name}: {target} leaves the repository"
        assert path.exists(), f"{doc.name}: {target} does not exist"
        if anchor:
            assert path.suffix == ".md", f"{doc.name}: {target}: anchor into a non-Markdown file"
            assert anchor in anchors(path), f"{doc.name}: {target}: no such heading"


@pytest.mark.parametrize("doc", DOCUMENTS, ids=[str(p.relative_to(ROOT)) for p in DOCUMENTS])
def test_nothing_points_outside_the_clone(doc):
    assert "shared/" not in doc.read_text(encoding="utf-8"), doc.name


def test_every_page_is_linked_from_the_readme():
    linked = {(ROOT / t.partition("#")[0]).resolve() for t in links(README)}
    assert set(PAGES) <= linked, sorted(p.name for p in set(PAGES) - linked)


def test_the_readme_is_about_one_page_and_names_the_defaults():
    from service.schemas import build_schemas
    from service.settings import default_settings

    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 120
    fields = build_schemas(default_settings().limits).PlanRequest.model_fields
    method, objective = fields["method"].default, fields["objective"].default
    assert re.search(rf"default method is `{method}`", text), method
    assert re.search(rf"default objective is `{objective}`", text), objective
    for command in ("bash scripts/serve.sh", "bash scripts/test.sh"):
        assert command in text


def test_the_readme_example_request_is_a_valid_plan_request():
    import json

    from service.schemas import build_schemas
    from service.settings import default_settings

    body = json.loads((ROOT / "examples" / "request.json").read_text(encoding="utf-8"))
    build_schemas(default_settings().limits).PlanRequest.model_validate(body)
    assert "examples/request.json" in README.read_text(encoding="utf-8")
