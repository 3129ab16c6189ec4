"""Benchmark tables written into the project's markdown files between markers.

A file holds ``<!-- bench:KEY -->`` ... ``<!-- /bench:KEY -->``; :func:`write_section`
replaces what lies between them (the markers stay), so a document quotes the numbers of the
last run of the bench that owns KEY and nothing else edits them by hand.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

_KEY = re.compile(r"[a-z0-9]+(-[a-z0-9]+)*")


def markers(key: str) -> tuple[str, str]:
    """The two markers of section ``key``: lower-case letters and digits, words joined by '-'
    (ValueError otherwise)."""
    if not _KEY.fullmatch(key):
        raise ValueError(
            f"section name {key!r}: use lower-case letters and digits, words joined by '-'"
        )
    return f"<!-- bench:{key} -->", f"<!-- /bench:{key} -->"


def section_span(path: Path, key: str) -> tuple[str, int, int]:
    """``path``'s text and the span between its markers for ``key`` (ValueError: none; OSError:
    unreadable)."""
    begin, end = markers(key)
    doc = path.read_text(encoding="utf-8")
    i, j = doc.find(begin), doc.find(end)
    if i < 0 or j < i:
        raise ValueError(f"{path} has no '{begin}' ... '{end}' section to write into")
    return doc, i + len(begin), j


def write_section(path: Path, key: str, text: str) -> None:
    """Put ``text`` between ``path``'s markers for ``key``; a file without them is refused."""
    doc, i, j = section_span(path, key)
    new = doc[:i] + "\n" + text.strip("\n") + "\n" + doc[j:]
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(new, encoding="utf-8")
    os.replace(tmp, path)
