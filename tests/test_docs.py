"""The repository's Markdown pages: every relative link and image resolves, anchors included.

The docs cross-link heavily (README -> docs -> results -> docs); a renamed heading or a moved
section silently breaks a link on GitHub. Anchors follow GitHub's rule for heading ids.
"""

import pathlib
import re
import unicodedata
from typing import Dict, List, Set, Tuple

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
SKIP_PARTS = {".git", ".venv", "node_modules", ".pytest_cache"}
FENCE = re.compile(r"^```.*?^```", re.M | re.S)
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.M)
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def github_anchor(heading: str) -> str:
    """The id GitHub gives a heading: markup dropped, lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`([^`]*)`", r"\1", heading)
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link in a heading keeps its text
    kept = [
        ch
        for ch in text.lower()
        if ch in "-_ " or (ch.isalnum() and unicodedata.category(ch) in {"Lu", "Ll", "Lt", "Lm", "Lo", "Nd"})
    ]
    return "".join(kept).replace(" ", "-")


def anchors_of(text: str) -> Set[str]:
    """Every heading id of a page, with GitHub's -1, -2 suffixes for repeated headings."""
    seen: Dict[str, int] = {}
    anchors = set()
    for heading in HEADING.findall(FENCE.sub("", text)):
        anchor = github_anchor(heading)
        count = seen.get(anchor, 0)
        anchors.add(anchor if count == 0 else f"{anchor}-{count}")
        seen[anchor] = count + 1
    return anchors


def markdown_pages() -> List[pathlib.Path]:
    return sorted(p for p in ROOT.rglob("*.md") if not SKIP_PARTS.intersection(p.relative_to(ROOT).parts))


def broken_links(pages: List[pathlib.Path], root: pathlib.Path = ROOT) -> List[Tuple[str, str, str]]:
    """(page, link, why) for each relative link of ``pages`` (under ``root``) that does not resolve."""
    texts = {page.resolve(): page.read_text(encoding="utf-8") for page in pages}
    broken = []
    for page in pages:
        for link in LINK.findall(FENCE.sub("", texts[page.resolve()])):
            if re.match(r"^[a-z][a-z0-9+.-]*:", link):  # http:, https:, mailto:
                continue
            path, _, fragment = link.partition("#")
            target = (page.parent / path).resolve() if path else page.resolve()
            where = str(page.relative_to(root))
            if not target.exists():
                broken.append((where, link, "no such file"))
            elif fragment and target.suffix == ".md":
                text = texts.get(target) or target.read_text(encoding="utf-8")
                if fragment not in anchors_of(text):
                    broken.append((where, link, "no such heading"))
    return broken


def test_github_anchor_follows_githubs_rule():
    assert github_anchor("The paper's Figures 5 and 6") == "the-papers-figures-5-and-6"
    assert github_anchor("Figure 6: MetaCook (under way)") == "figure-6-metacook-under-way"
    assert github_anchor("`predict` with state") == "predict-with-state"
    assert github_anchor("RL2DQN: a recurrent DQN for SB3") == "rl2dqn-a-recurrent-dqn-for-sb3"
    assert anchors_of("# A\n## A\n```\n# not a heading\n```\n## A\n") == {"a", "a-1", "a-2"}


def test_broken_links_are_found(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "page.md").write_text("# Page\n## The paper's baselines\n")
    readme = tmp_path / "README.md"
    readme.write_text(
        "[ok](docs/page.md#the-papers-baselines) [top](#readme) ![img](docs/missing.png)\n"
        "[gone](docs/page.md#the-baselines) [web](https://example.com/x#y)\n# Readme\n"
        "```\n[in code](nowhere.md)\n```\n"
    )
    broken = broken_links([readme, tmp_path / "docs" / "page.md"], root=tmp_path)
    assert broken == [
        ("README.md", "docs/missing.png", "no such file"),
        ("README.md", "docs/page.md#the-baselines", "no such heading"),
    ]


def test_every_link_of_the_repositorys_pages_resolves():
    pages = markdown_pages()
    assert ROOT / "README.md" in pages and ROOT / "docs" / "baselines.md" in pages
    broken = broken_links(pages)
    assert not broken, "\n".join(f"{page}: {link} ({why})" for page, link, why in broken)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(pytest.main([__file__]))
