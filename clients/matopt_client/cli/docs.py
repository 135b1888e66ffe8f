"""docs/cli.md, written from the click commands themselves so that it cannot drift from them.

``python -m matopt_client.cli.docs > docs/cli.md`` regenerates it; a test fails, naming this
command, when the committed file differs from what the commands say now.
"""

from __future__ import annotations

import inspect
import re

import click

from matopt_client.cli import cli, exit_codes
from matopt_client.cli.session import CONNECTION_OPTIONS

REGENERATE = "python -m matopt_client.cli.docs > docs/cli.md"

COMPLETION = """\
Click completes commands and options; the names of your scenes, jobs and blobs (`matopt job
status <TAB>`) come from the daemon at `--server` (or `MATOPT_SERVER`), asked with a deadline
of a second. When it does not answer, nothing is completed. Bare ids are completed, full names
(`jobs/...`) once you have typed the `/`.

Bash, in `~/.bashrc`:

```sh
eval "$(_MATOPT_COMPLETE=bash_source matopt)"
```

Zsh, in `~/.zshrc`:

```sh
eval "$(_MATOPT_COMPLETE=zsh_source matopt)"
```

Fish, in `~/.config/fish/completions/matopt.fish`:

```sh
_MATOPT_COMPLETE=fish_source matopt | source
```

Each runs `matopt` once per shell start; to save that, write the script to a file once
(`_MATOPT_COMPLETE=bash_source matopt > ~/.matopt-complete.bash`) and source the file.
"""


def _text(text: str) -> str:
    """Help text as markdown: ``<key>`` stays visible rather than read as an HTML tag."""
    return re.sub(r"([<>*])", r"\\\1", text)


def _help(command: click.Command) -> str:
    lines = [line for line in inspect.cleandoc(command.help or "").splitlines()
             if line.strip() != "\b"]
    return _text("\n".join(lines)).split("\f")[0].strip()


def _walk(command: click.Command, ctx: click.Context):
    """(context, command) of ``command`` and every command below it, in --help's order."""
    yield ctx, command
    if isinstance(command, click.Group):
        for name in command.list_commands(ctx):
            sub = command.get_command(ctx, name)
            if sub is not None and not sub.hidden:
                yield from _walk(sub, click.Context(sub, info_name=name, parent=ctx))


def _section(ctx: click.Context, command: click.Command) -> list[str]:
    out = [f"## {ctx.command_path}", "", "```", f"{ctx.command_path} "
           f"{' '.join(command.collect_usage_pieces(ctx))}", "```", "", _help(command), ""]
    if isinstance(command, click.Group):
        out += ["Commands:", ""]
        for name in command.list_commands(ctx):
            sub = command.get_command(ctx, name)
            out.append(f"- [`{name}`](#{_anchor(f'{ctx.command_path} {name}')}): "
                       f"{_text(sub.get_short_help_str(limit=200))}")
        out.append("")
    root = ctx.parent is None  # the connection options, which every command takes, go here
    records = [p.get_help_record(ctx) for p in command.get_params(ctx)
               if isinstance(p, click.Option) and (root or p.name not in CONNECTION_OPTIONS)]
    records = [r for r in records if r is not None]
    if records:
        out += ["Options:", ""]
        out += [f"- `{opts}`: {_text(text)}" if text else f"- `{opts}`"
                for opts, text in records]
        out.append("")
    if not root:
        out += ["And the connection options of [`matopt`](#matopt).", ""]
    return out


def _anchor(title: str) -> str:
    """The id GitHub gives a heading: lower case, spaces as dashes."""
    return re.sub(r"[^a-z0-9 -]", "", title.lower()).replace(" ", "-")


def render() -> str:
    """The whole of docs/cli.md."""
    root = click.Context(cli, info_name="matopt", **cli.context_settings)
    sections = list(_walk(cli, root))
    out = ["# The `matopt` command", "",
           f"Written from the commands themselves (`{REGENERATE}`); `matopt COMMAND --help` "
           "says the same.", "",
           "- " + "\n- ".join(f"[`{c.command_path}`](#{_anchor(c.command_path)})"
                              for c, _ in sections),
           "- [Exit status](#exit-status)",
           "- [Shell completion](#shell-completion)", ""]
    for ctx, command in sections:
        out += _section(ctx, command)
    out += ["## Exit status", "",
            "Every failure prints one line, `matopt: error: ...`, on stderr.", ""]
    out += [f"- `{code}`: {_text(text)}" for code, text in exit_codes.MEANINGS.items()]
    out += ["", "## Shell completion", "", COMPLETION]
    return "\n".join(out).rstrip("\n") + "\n"


if __name__ == "__main__":
    click.echo(render(), nl=False)
