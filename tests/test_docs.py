"""The documentation holds together: every relative link resolves (file and
heading), every page of docs/ is listed in the README's table, every
``bodynet ...`` line of a shell block is a command the real parser accepts,
and the README stays short enough to read in ten minutes."""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
PAGES = sorted((ROOT / "docs").glob("*.md"))
MAX_README_LINES = 260

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.MULTILINE | re.DOTALL)
HEADING = re.compile(r"^#{1,6}\s+(.+?)\s*#*\s*$", re.MULTILINE)


def _prose(path: Path) -> str:
    """The file's text without fenced code blocks (no links live there)."""
    return FENCE.sub("", path.read_text(encoding="utf-8"))


def _anchors(path: Path) -> set[str]:
    """GitHub's anchors of a Markdown file's headings."""
    anchors: set[str] = set()
    for title in HEADING.findall(_prose(path)):
        slug = re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")
        base, n = slug, 1
        while slug in anchors:  # repeated headings get -1, -2...
            slug, n = f"{base}-{n}", n + 1
        anchors.add(slug)
    return anchors


def _relative_links(path: Path) -> list[str]:
    return [t for t in LINK.findall(_prose(path)) if not re.match(r"[a-z][a-z0-9+.-]*:", t)]


def _broken_links(doc: Path) -> list[str]:
    broken = []
    for target in _relative_links(doc):
        file_part, _, anchor = target.partition("#")
        dest = (doc.parent / file_part).resolve() if file_part else doc
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target}: no heading #{anchor} in {dest.name}")
    return broken


@pytest.mark.parametrize("doc", [README, *PAGES], ids=lambda p: p.name)
def test_every_relative_link_resolves(doc: Path) -> None:
    assert _broken_links(doc) == []


def test_every_docs_page_is_in_the_readme_table() -> None:
    text = README.read_text(encoding="utf-8")
    rows = [line for line in text.splitlines() if line.startswith("|")]
    listed = {m for row in rows for m in re.findall(r"\]\((docs/[^)#]+\.md)\)", row)}
    pages = {f"docs/{p.name}" for p in PAGES}
    assert pages - listed == set(), "add a line to the README's docs table for each of these"
    assert listed - pages == set(), "the README's docs table lists pages that do not exist"


def test_the_readme_table_rows_are_in_order() -> None:
    rows = re.findall(r"^\| \[[^\]]+\]\(docs/([^)]+)\.md\)", README.read_text(), re.MULTILINE)
    assert rows == sorted(rows), "keep the docs table in alphabetical order of the file name"


def test_the_readme_stays_short() -> None:
    lines = README.read_text(encoding="utf-8").count("\n")
    assert lines < MAX_README_LINES, f"README.md has {lines} lines: move details into docs/"


def test_the_link_checker_finds_broken_links(tmp_path: Path) -> None:
    """A missing file and a missing heading are found; links in code are not links."""
    page = tmp_path / "a.md"
    page.write_text("# A title\n\n[x](b.md) [y](#nowhere) [z](#a-title) [w](a.md#a-title)\n"
                    "```\n[q](c.md)\n```\n")  # fmt: skip
    assert _broken_links(page) == ["b.md: no such file", "#nowhere: no heading #nowhere in a.md"]


def _command_lines(doc: Path) -> list[str]:
    """The ``bodynet`` command lines of a page's ``sh`` blocks, comments cut off."""
    lines = []
    for block in re.findall(r"^```sh\n(.*?)^```", doc.read_text(encoding="utf-8"), re.M | re.S):
        for line in block.splitlines():
            command = re.match(r"(?:\S+=\S+ )*(?:\.venv/bin/)?bodynet (.*)", line.split(" #")[0])
            if command:
                lines.append(command.group(1).strip())
    return lines


# A page's commands name files the reader has (session.mcap, subject-1.toml...):
# where the parser refuses one for not being there, it is made, empty, and the
# line is parsed again. Any other refusal is the page's error.
MISSING = (
    (re.compile(r"cannot read '([^']+)': no such file"), "file"),
    (re.compile(r"its folder '([^']+)' does not exist"), "dir"),
    (re.compile(r"'([^']+)' is not a folder \(no such path\)"), "dir"),
)


def _refusal(parser: argparse.ArgumentParser, argv: list[str]) -> str | None:
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            parser.parse_args(argv)
    except SystemExit as exc:
        if exc.code:
            return (err.getvalue().strip().splitlines() or [""])[-1]
    return None


@pytest.mark.parametrize("doc", [README, *PAGES], ids=lambda p: p.name)
def test_every_command_shown_parses(
    doc: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from bodynet.cli.main import build_parser

    parser = build_parser()
    monkeypatch.chdir(tmp_path)
    refused = []
    for line in _command_lines(doc):
        argv = shlex.split(line)
        for _ in range(8):  # each round makes one missing file or folder
            why = _refusal(parser, argv)
            made = next(((m.group(1), kind) for pattern, kind in MISSING
                         if why and (m := pattern.search(why))), None)  # fmt: skip
            if made is None:
                break
            path = tmp_path / made[0]
            if made[1] == "dir":
                path.mkdir(parents=True, exist_ok=True)
            else:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.touch()
        if why:
            refused.append(f"bodynet {line}: {why}")
    assert not refused, "\n".join(refused)


def test_the_command_check_reads_shell_blocks(tmp_path: Path) -> None:
    page = tmp_path / "a.md"
    page.write_text(
        "```sh\n.venv/bin/bodynet view -e tcp/h:7447   # a comment\n"
        "bodynet record -o x.mcap\nls\n```\n\n    bodynet not-in-a-block\n"
    )
    assert _command_lines(page) == ["view -e tcp/h:7447", "record -o x.mcap"]
