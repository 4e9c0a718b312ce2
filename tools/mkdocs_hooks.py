"""MkDocs hooks of the documentation site (mkdocs.yml: `hooks`).

Lists as GitHub reads them. The model card (diffsheg_core/weights/README.md, included into
docs/model-card.md by pymdownx.snippets) is written for GitHub, where (CommonMark) a list may
start right under a paragraph line and nest by two spaces; Python-Markdown needs a blank line
before a list and four spaces to nest. A preprocessor that runs after the snippets are
included puts a blank line before such a list and, in a list that nests by two spaces, doubles
the indentation. Fenced code and lists written for Python-Markdown are left as they are.
"""

from __future__ import annotations

import re

from markdown import Extension
from markdown.preprocessors import Preprocessor

LIST_START = re.compile(r"^(?:[-*+]|1[.)])\s+\S")
LIST_ITEM = re.compile(r"^\s*(?:[-*+]|\d+[.)])\s+")
FENCE = re.compile(r"^\s*(```|~~~)")


def separate_lists(lines: list[str]) -> list[str]:
    """`lines` with a blank line before every list that starts right under a paragraph line."""
    out: list[str] = []
    fenced = False
    for line in lines:
        if FENCE.match(line):
            fenced = not fenced
        elif not fenced and LIST_START.match(line) and out:
            before = out[-1]
            if before.strip() and not LIST_ITEM.match(before) and not before.startswith((" ", "\t", "|", "#", ">")):
                out.append("")
        out.append(line)
    return out


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip(" "))


def widen_nesting(lines: list[str]) -> list[str]:
    """`lines` with the indentation doubled in every list whose nested items are indented by
    two spaces (a list runs from an unindented item to the next unindented line that is no
    item, or a fence)."""
    out: list[str] = []
    i = 0
    while i < len(lines):
        if not LIST_START.match(lines[i]):
            if FENCE.match(lines[i]):  # copy a fenced block as it is
                out.append(lines[i])
                i += 1
                while i < len(lines) and not FENCE.match(lines[i]):
                    out.append(lines[i])
                    i += 1
                if i < len(lines):
                    out.append(lines[i])
                    i += 1
                continue
            out.append(lines[i])
            i += 1
            continue
        end = i + 1
        while end < len(lines) and not FENCE.match(lines[end]) and \
                (not lines[end].strip() or _indent(lines[end]) > 0 or LIST_ITEM.match(lines[end])):
            end += 1
        region = lines[i:end]
        nested = [_indent(line) for line in region if _indent(line) > 0 and LIST_ITEM.match(line)]
        if nested and min(nested) == 2:
            region = [" " * _indent(line) + line if line.strip() else line for line in region]
        out.extend(region)
        i = end
    return out


class _SeparateLists(Preprocessor):
    def run(self, lines: list[str]) -> list[str]:
        return widen_nesting(separate_lists(lines))


class GitHubLists(Extension):
    def extendMarkdown(self, md) -> None:  # noqa: N802 (Python-Markdown's name)
        # after pymdownx.snippets (priority 32) has included the files, before the block parser
        md.preprocessors.register(_SeparateLists(md), "github_lists", 25)


def on_config(config, **kwargs):
    config.markdown_extensions.append(GitHubLists())
    return config
