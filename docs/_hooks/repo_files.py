"""mkdocs hook: the repository's files that docs/ links to (``../README.md``, ``../scripts/figures/*.png``,
``../examples/*.py``, ...) become part of the site, so that every link resolves and ``mkdocs build --strict``
checks them.

- ``README.md`` becomes the page ``readme.md`` (its links into ``docs/`` point at the pages, the others at the
  copied files);
- every other file a page links to with ``../<path>`` is copied to ``repo/<path>`` and the link rewritten.
"""
from __future__ import annotations

import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[2]
LINK = re.compile(r"\]\(\.\./([^)#\s]+)(#[^)]*)?\)")          # a top-level page's link out of docs/
RELATIVE = re.compile(r"\]\((\.\./[^)#\s]+)(#[^)]*)?\)")         # any page's relative link upwards
README_LINK = re.compile(r"\]\((?!https?://|#)([^)#\s]+)(#[^)]*)?\)")


def _target(path: str) -> str:
    return "readme.md" if path == "README.md" else f"repo/{path}"


def _linked() -> set:
    """The repository paths that docs/*.md and README.md link to outside docs/."""
    out = set()
    for page in (ROOT / "docs").glob("*.md"):
        out.update(m.group(1) for m in LINK.finditer(page.read_text(encoding="utf-8")))
    for m in README_LINK.finditer((ROOT / "README.md").read_text(encoding="utf-8")):
        if not m.group(1).startswith("docs/"):
            out.add(m.group(1))
    return {p for p in out if p != "README.md" and (ROOT / p).is_file()}


def on_files(files, config):
    for path in sorted(_linked()):
        files.append(File.generated(config, f"repo/{path}", abs_src_path=str(ROOT / path)))
    files.append(File.generated(config, "readme.md", content=_readme()))
    return files


def _readme() -> str:
    """README.md with its links rewritten for the site (docs/x.md -> x.md, other files -> repo/...)."""
    def fix(m):
        path, anchor = m.group(1), m.group(2) or ""
        return f"]({path[len('docs/'):]}{anchor})" if path.startswith("docs/") else f"](repo/{path}{anchor})"

    return README_LINK.sub(fix, (ROOT / "README.md").read_text(encoding="utf-8"))


def on_page_markdown(markdown, page, config, files):
    if page.file.src_uri == "readme.md":
        return markdown
    base = posixpath.dirname(page.file.src_uri)
    up = "../" * (base.count("/") + 1) if base else ""

    def fix(m):
        path = posixpath.normpath(posixpath.join(base, m.group(1)))
        if not path.startswith("../"):   # a page of docs/ itself
            return m.group(0)
        return f"]({up}{_target(path[3:])}{m.group(2) or ''})"

    return RELATIVE.sub(fix, markdown)
