"""The benchmark pages hold together: every link into the history lands on a section, the
page of current figures names no commit or scratch path, and every script in ``bench/``
is in its index.

Section anchors are computed as GitHub renders Markdown headings (lower case; letters,
digits, spaces, hyphens and underscores kept; spaces to hyphens; ``-1``, ``-2`` for
repeats; github-slugger's rules), plus explicit ``<a id="...">`` anchors.
"""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HISTORY = "docs/benchmarks-history.md"
LINK = re.compile(r"\]\(([^)#\s]*\.md)#([^)\s]+)\)")


def heading_anchor(title: str) -> str:
    kept = (c for c in title.strip().lower() if unicodedata.category(c)[0] in "LMN" or c in " -_")
    return "".join(kept).replace(" ", "-")


def anchors(markdown: str) -> set[str]:
    found: set[str] = set(re.findall(r'<a id="([^"]+)"></a>', markdown))
    seen: dict[str, int] = {}
    fenced = False
    for line in markdown.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        match = re.match(r"#{1,6} (.+)", line)
        if match and not fenced:
            slug = heading_anchor(match.group(1))
            repeat = seen.get(slug, 0)
            seen[slug] = repeat + 1
            found.add(slug if repeat == 0 else f"{slug}-{repeat}")
    return found


def test_anchors_follow_githubs_rules_for_symbols_punctuation_and_repeats() -> None:
    text = "# Issue 3's 20× on a quiet machine (2 December)\n## Round 4\n```sh\n# not a heading\n```\n## Round 4\n"
    assert anchors(text) == {"issue-3s-20-on-a-quiet-machine-2-december", "round-4", "round-4-1"}
    stop = "stop-button--motors-zero-target-p99--100-ms"
    assert heading_anchor("Stop button → motors zero (target p99 ≤ 100 ms)") == stop


def test_every_link_to_a_benchmark_section_lands_on_one() -> None:
    pages = [REPO / "BENCHMARKS.md", REPO / "README.md", REPO / "bench" / "README.md", *(REPO / "docs").glob("*.md")]
    links = 0
    for page in pages:
        for target, anchor in LINK.findall(page.read_text(encoding="utf-8")):
            linked = (page.parent / target).resolve()
            if linked.name.lower() not in ("benchmarks.md", "benchmarks-history.md"):
                continue
            links += 1
            assert anchor in anchors(linked.read_text(encoding="utf-8")), f"{page.name} links to {target}#{anchor}"
    assert links >= 30  # the page of current figures links a section for nearly every row


def test_the_page_of_current_figures_names_no_commit_and_no_scratch_path() -> None:
    page = (REPO / "BENCHMARKS.md").read_text(encoding="utf-8")
    assert "/tmp" not in page
    assert not re.findall(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b", page)


def test_every_script_in_bench_is_in_its_index() -> None:
    index = (REPO / "bench" / "README.md").read_text(encoding="utf-8")
    listed = set(re.findall(r"^\| `([a-z_0-9]+\.py)` \|", index, flags=re.MULTILINE))
    assert listed == {p.name for p in (REPO / "bench").glob("*.py")}
