"""The front door and the docs site: README.md stays short, and every relative link in it and
in docs/*.md points to a file that exists (and, for a link into a Markdown file, to a heading
that file has). `mkdocs build --strict` (.ci/run) checks the site's own links again, with
MkDocs' anchors; this test needs no MkDocs and also covers the README, which is no page of
the site."""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path
from urllib.parse import unquote

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
DOCS = REPO / "docs"
README_MAX_LINES = 200

# [text](target) and ![alt](target) with an optional "title"; <img src="..."> and <a href="...">
MD_LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HTML_LINK = re.compile(r"""<(?:img|a)\b[^>]*?\b(?:src|href)\s*=\s*["']([^"']+)["']""", re.IGNORECASE)
FENCE = re.compile(r"^\s*(```|~~~)")
SNIPPET = re.compile(r'^--8<--\s+"([^"]+)"\s*$', re.MULTILINE)


def markdown_files() -> list[Path]:
    return [README, *sorted(DOCS.glob("**/*.md"))]


def prose(text: str) -> str:
    """`text` without fenced code blocks, indented code blocks and inline code, where
    brackets and parentheses are code, not links."""
    kept, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        if fenced or line.startswith("    ") and not line.lstrip().startswith(("-", "*", "|")) and not kept_list(kept):
            kept.append("")
            continue
        kept.append(re.sub(r"`[^`]*`", "", line))
    return "\n".join(kept)


def kept_list(kept: list[str]) -> bool:
    """Whether an indented line continues a list item (then it is prose, not code)."""
    for line in reversed(kept):
        if not line.strip():
            return False
        if re.match(r"\s*([-*+]|\d+\.)\s", line):
            return True
    return False


def links(path: Path) -> list[str]:
    text = prose(path.read_text(encoding="utf-8"))
    return MD_LINK.findall(text) + HTML_LINK.findall(text)


def slug(heading: str) -> str:
    """The anchor Python-Markdown's toc extension (MkDocs) and GitHub give a heading, for the
    headings these files have: inline markup dropped, lower case, punctuation but - and _
    dropped, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)           # [text](link) -> text
    text = re.sub(r"[`*]|\{[^}]*\}\s*$", "", text)                        # code, emphasis, attr lists
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    text = re.sub(r"[^\w\s-]", "", text).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


def anchors(path: Path) -> set[str]:
    """The anchors of a Markdown file's headings (with the files it includes as snippets),
    numbered as the toc extension numbers repeats (x, x_1, ...)."""
    text = path.read_text(encoding="utf-8")
    for included in SNIPPET.findall(text):
        text += "\n" + (REPO / included).read_text(encoding="utf-8")
    found: set[str] = set()
    for line in prose(text).splitlines():
        heading = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if heading:
            name = slug(heading.group(1))
            unique, n = name, 0
            while unique in found:
                n += 1
                unique = f"{name}_{n}"
            found.add(unique)
    return found


def relative(target: str) -> bool:
    return not re.match(r"^[a-z][a-z0-9+.-]*:|^//", target, re.IGNORECASE)


def test_readme_is_a_front_door():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines: at most {README_MAX_LINES}, " \
                                           f"the rest belongs in docs/"


def test_readme_keeps_the_two_set_up_commands():
    text = README.read_text(encoding="utf-8")
    assert "    pip install -r requirements.txt && python batch_render.py\n" in text
    test_command = ("bash tools/install_system_packages.sh && bash tools/install_node_tools.sh && "
                    "pip install -r requirements-test.txt && python -m pytest")
    assert f"    {test_command}\n" in text
    ci = (REPO / ".ci" / "run").read_text(encoding="utf-8")
    assert "bash tools/install_system_packages.sh && bash tools/install_node_tools.sh" in ci
    assert "-r requirements-test.txt" in ci and "python -m pytest" in ci


@pytest.mark.parametrize("path", markdown_files(), ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_resolve(path: Path):
    broken = []
    for target in links(path):
        if not relative(target):
            continue
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / unquote(file_part)).resolve() if file_part else path
        if not dest.exists():
            broken.append(f"{target}: no file {dest.relative_to(REPO) if dest.is_relative_to(REPO) else dest}")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading with anchor #{anchor} in {dest.relative_to(REPO)}")
    assert not broken, f"{path.relative_to(REPO)}: " + "; ".join(broken)


def test_every_docs_page_is_in_the_nav():
    """mkdocs.yml's nav names every page under docs/ (MkDocs only warns of one left out)."""
    nav = (REPO / "mkdocs.yml").read_text(encoding="utf-8")
    named = set(re.findall(r":\s*([\w./-]+\.md)\s*$", nav, re.MULTILINE))
    pages = {str(p.relative_to(DOCS)) for p in DOCS.glob("**/*.md")}
    assert pages <= named, f"pages missing from mkdocs.yml's nav: {sorted(pages - named)}"
    assert named <= pages, f"nav entries without a page: {sorted(named - pages)}"


def test_images_the_pages_show_exist():
    """Every image under docs/images/ is made by a script (tools/docs_figures.py) and shown."""
    shown = {(path.parent / unquote(t.partition("#")[0])).resolve()
             for path in markdown_files() for t in links(path) if relative(t)}
    images = sorted((DOCS / "images").glob("*.png"))
    assert images, "docs/images/ holds no pictures"
    unused = [str(p.relative_to(REPO)) for p in images if p.resolve() not in shown]
    assert not unused, f"pictures no page shows: {unused}"


def test_slug_matches_the_toc_extension():
    assert slug("Headless: batch_render.py") == "headless-batch_renderpy"
    assert slug("Measured: quality against offline, latency") == "measured-quality-against-offline-latency"
    assert slug("Best of N windows (candidates)") == "best-of-n-windows-candidates"
    assert slug("A second speech input: HuBERT or the phonetic encoder") == \
        "a-second-speech-input-hubert-or-the-phonetic-encoder"


def test_checker_finds_a_broken_link(tmp_path: Path):
    page = tmp_path / "page.md"
    page.write_text("# Title\n\n[ok](#title) [bad](#nope) [gone](missing.md)\n\n    [code](not-a-link.md)\n"
                    "```\n[fenced](not-a-link.md)\n```\n`[inline](not-a-link.md)`\n", encoding="utf-8")
    assert links(page) == ["#title", "#nope", "missing.md"]
    assert anchors(page) == {"title"}


def test_model_card_lists_read_as_on_github():
    """tools/mkdocs_hooks.py: a list right under a paragraph line, nested by two spaces (as the
    model card writes them for GitHub), becomes a nested list on the site too; lists written for
    Python-Markdown (four spaces) and code are left alone."""
    markdown = pytest.importorskip("markdown")
    import importlib.util

    spec = importlib.util.spec_from_file_location("mkdocs_hooks", REPO / "tools" / "mkdocs_hooks.py")
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    github = "**What was trained.**\n- one\n  - nested\n    continued\n- two\n\nAfter.\n"
    html = markdown.markdown(github, extensions=[hooks.GitHubLists()])
    assert html.count("<ul>") == 2 and re.search(r"<li>nested\s+continued</li>", html) and "<p>After.</p>" in html
    python_markdown = "Steps:\n\n1. first\n    - sub\n\n```\n- not a list\n```\n"
    assert hooks.widen_nesting(hooks.separate_lists(python_markdown.splitlines())) == python_markdown.splitlines()
