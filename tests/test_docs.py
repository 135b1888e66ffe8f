"""The docs against the code: every `matopt`/`matoptd` command in a ```sh block of README.md
and docs/*.md names a command and options that exist, so that a renamed command or option
fails here rather than in a reader's shell; every relative link points to a file (and
heading) that exists. No daemon: the CLI's click tree and matoptd's flags are read as they
are. Also the benchmark writer's summary, which docs/benchmarks.md is."""

from __future__ import annotations

import re
import shlex
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import click
import pytest

from conftest import ROOT

from matopt_client.cli import cli
from matoptd.main import parse_args

PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# A fence may be indented (a block inside a list item): its closing fence is indented alike.
FENCE = re.compile(r"^( *)```(\w*)\n(.*?)^\1```", re.DOTALL | re.MULTILINE)
SEPARATORS = {";", "&&", "||", "|", "(", ")", "&"}


def _where(page: Path, line: int) -> str:
    return f"{page.relative_to(ROOT)}:{line}"


def commands(page: Path) -> Iterator[tuple[str, list[str]]]:
    """(where, words) of each matopt or matoptd command in the page's ```sh blocks: lines
    joined at a trailing backslash, comments dropped, split at ; && || | and $( )."""
    text = page.read_text()
    for block in FENCE.finditer(text):
        if block.group(2) != "sh":
            continue
        first = text.count("\n", 0, block.start(3)) + 1
        logical: list[tuple[int, str]] = []
        for n, line in enumerate(textwrap.dedent(block.group(3)).splitlines(), first):
            if logical and logical[-1][1].endswith("\\"):
                logical[-1] = (logical[-1][0], logical[-1][1][:-1] + " " + line)
            else:
                logical.append((n, line))
        for n, line in logical:
            lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
            lexer.whitespace_split = True
            lexer.commenters = "#"
            segment: list[str] = []
            for token in [*lexer, ";"]:
                if token not in SEPARATORS:
                    segment.append(token.removesuffix("$") if token.endswith("=$") else token)
                    continue
                while segment and re.fullmatch(r"\w+=.*", segment[0]):  # VAR=... prefix
                    segment.pop(0)
                if segment and Path(segment[0]).name in ("matopt", "matoptd"):
                    yield _where(page, n), segment
                segment = []


def _option(command: click.Command, ctx: click.Context, word: str) -> click.Parameter | None:
    name = word.split("=", 1)[0]
    for param in command.get_params(ctx):
        if name in (*param.opts, *param.secondary_opts):
            return param
    return None


def check_matopt(words: list[str]) -> None:
    """Walks the click tree as the shell would run `matopt WORDS`: each subcommand must
    exist, each option must be one its command takes, and a choice's value one it offers."""
    command: click.Command = cli
    ctx = click.Context(cli, info_name="matopt")
    path = ["matopt"]
    i = 0
    while i < len(words):
        word = words[i]
        if word == "--":
            return
        if word.startswith("-") and word != "-":
            param = _option(command, ctx, word)
            assert param is not None, f"'{' '.join(path)}' has no option {word.split('=')[0]}"
            takes_value = isinstance(param, click.Option) and not (param.is_flag or param.count)
            if takes_value and "=" not in word:
                i += 1
                assert i < len(words), f"{word} needs a value"
                value = words[i]
                if isinstance(param.type, click.Choice) and not value.startswith("$"):
                    offered = [str(c).lower() for c in param.type.choices]
                    assert value.lower() in offered, f"{word} {value}: not one of {offered}"
        elif isinstance(command, click.Group):
            sub = command.get_command(ctx, word)
            assert sub is not None, f"'{' '.join(path)}' has no command {word!r}"
            command, path = sub, [*path, word]
            ctx = click.Context(sub, info_name=word, parent=ctx)
        i += 1
    assert not isinstance(command, click.Group) or path == ["matopt"], \
        f"'{' '.join(path)}' names a group, not a command"


def check_matoptd(words: list[str]) -> None:
    try:
        parse_args(words)
    except SystemExit as exc:  # argparse has printed why
        raise AssertionError(f"matoptd refuses {' '.join(words)}") from exc


def all_commands() -> list[tuple[str, list[str]]]:
    return [c for page in PAGES for c in commands(page)]


def test_the_docs_name_commands_at_all():
    """The harvest below finds the quick start's commands (a parser that found none would
    pass every check)."""
    found = {tuple(words[:3]) for _, words in commands(ROOT / "README.md")}
    assert ("matopt", "scene", "load") in found and ("matopt", "job", "start") in found
    assert ("matoptd", "--data-dir", "~/matopt-data") in found


@pytest.mark.parametrize("where,words", all_commands(), ids=lambda v: v if isinstance(v, str) else "")
def test_each_command_in_the_docs_parses(where, words):
    try:
        (check_matoptd if Path(words[0]).name == "matoptd" else check_matopt)(words[1:])
    except AssertionError as exc:
        pytest.fail(f"{where}: {' '.join(words)}\n  {exc}")


def test_a_renamed_option_or_command_is_caught():
    with pytest.raises(AssertionError, match="no option --wiat"):
        check_matopt(["job", "start", "S", "--ref", "r.exr", "--wiat"])
    with pytest.raises(AssertionError, match="no command 'strat'"):
        check_matopt(["job", "strat", "S"])
    with pytest.raises(AssertionError, match="not one of"):
        check_matopt(["job", "result", "J", "--which", "worst"])
    with pytest.raises(AssertionError, match="matoptd refuses"):
        check_matoptd(["--data-dri", "x"])


LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+)$", text, re.MULTILINE)}


def links() -> list[tuple[Path, str]]:
    found = []
    for page in PAGES:
        text = FENCE.sub("", page.read_text())  # a link in a code block is not one
        found += [(page, m.group(1)) for m in LINK.finditer(text)]
    return found


def test_every_relative_link_points_to_a_file_that_exists():
    broken = []
    for page, target in links():
        if re.match(r"[a-z]+:", target):  # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(f"{page.relative_to(ROOT)}: {target} (no file {path})")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            broken.append(f"{page.relative_to(ROOT)}: {target} (no heading #{anchor} in "
                          f"{file.relative_to(ROOT)})")
    assert not broken, "links to nothing:\n" + "\n".join(broken)


def test_the_benchmark_summary_keeps_the_results_page_shape(tmp_path):
    """bench/run.py rewrites docs/benchmarks.md whole from ``summary``: the title, the
    targets table, one section per case, and the link to the history page kept by hand."""
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import run
        from common import Result, Settings, Target
    finally:
        sys.path.remove(str(ROOT / "bench"))
    results = [Result("overhead", "Daemon overhead", [Target("ratio", "1.02", True)], ["- a"]),
               Result("memory", "Daemon memory", [Target("growth", "0 KiB", None)])]
    settings = Settings(out=tmp_path, quick=False, work=tmp_path)
    page = run.summary(results, settings, None, 60.0, (1.0, 2.0), "../bench/results/",
                       run.HISTORY.name)
    assert page.startswith("# matopt benchmarks\n")
    assert "[benchmarks-history.md](benchmarks-history.md)" in page
    assert run.HISTORY.exists() and run.HISTORY.parent == run.DOCS.parent
    assert "| overhead | ratio | 1.02 | met |" in page and "| memory | growth | 0 KiB | n/a |" in page
    sections = re.findall(r"^## (.+)$", page, re.MULTILINE)
    assert sections[0] == "Targets" and sections[-1] == "Retired cases"
    assert [s.split(" (`")[0] for s in sections[1:-1]] == ["Daemon overhead", "Daemon memory"]
    assert "benchmarks-history" not in run.summary(results, settings, None, 60.0, (1.0, 2.0))
