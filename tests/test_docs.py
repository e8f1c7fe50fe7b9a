"""The documentation holds together: every relative link resolves, and the README speaks to users
(no study numbers: the history lives in docs/studies.md, whose index names every study section)."""

from __future__ import annotations

import re
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)#\s]+)(#[^)\s]*)?\)")


def _documents() -> list[Path]:
    return [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md")),
            *sorted((REPO_ROOT / "benchmarks").rglob("README.md"))]


def test_every_relative_link_resolves():
    broken = []
    for doc in _documents():
        for target, _ in LINK.findall(doc.read_text()):
            if re.match(r"[a-z]+://", target) or target.startswith("mailto:"):
                continue
            if not (doc.parent / target).exists():
                broken.append(f"{doc.relative_to(REPO_ROOT)} -> {target}")
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_the_readme_is_for_users():
    text = (REPO_ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    assert not re.search(r"\b[Ss]tud(y|ies) \d", text), "study numbers belong in docs/studies.md"
    for command in ("make demo", "make test", "stochastic-fields prepare", "stochastic-fields train",
                    "stochastic-fields export"):
        assert command in text


def test_the_research_log_indexes_every_study_section():
    log = (REPO_ROOT / "docs" / "studies.md").read_text()
    index = re.split(r"^## Study \d", log, maxsplit=1, flags=re.M)[0]
    numbers = set(re.findall(r"^## Study (\d+)", log, flags=re.M))
    assert numbers, "no study sections"
    for n in numbers:
        assert re.search(rf"^\| [^|]*\b{n}\b", index, flags=re.M), f"study {n} is missing from the index"
