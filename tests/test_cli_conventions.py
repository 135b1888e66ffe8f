"""What every ``matopt`` command has in common: --json, the exit statuses, completion of
names from the daemon, and docs/cli.md written from the commands.

The commands run as processes against a real daemon (the tests' shared one), as a script
would run them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import click
import pytest
from click.shell_completion import BashComplete

from matopt_client.cli import cli, docs, exit_codes

ROOT = Path(__file__).resolve().parent.parent
KEY = "red.reflectance.value"  # a wall of the built-in Cornell box
NOWHERE = "127.0.0.1:1"  # no daemon answers here


def matopt(env: dict[str, str], *args: str, extra: dict[str, str] | None = None
           ) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "matopt_client.cli", *args],
                          capture_output=True, text=True, env={**env, **(extra or {})},
                          timeout=600)


def as_json(env: dict[str, str], *args: str) -> dict:
    out = matopt(env, *args, "--json")
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def leaves(command: click.Command, path: tuple[str, ...] = ("matopt",)):
    if isinstance(command, click.Group):
        for name, sub in command.commands.items():
            yield from leaves(sub, path + (name,))
    else:
        yield " ".join(path), command


def test_every_command_takes_json():
    found = dict(leaves(cli))
    assert {"matopt job export", "matopt blob rm", "matopt job delete", "matopt scene delete",
            "matopt demo"} <= set(found)
    lacking = [path for path, command in found.items()
               if not any("--json" in p.opts for p in command.params)]
    assert not lacking, f"commands without --json: {lacking}"


@pytest.fixture(scope="module")
def cornell(tmp_path_factory, daemon):
    """A small Cornell box on the daemon, a reference rendered from it and a finished job."""
    env = dict(os.environ, MATOPT_SERVER=daemon.address)
    env.pop("MATOPT_TOKEN", None)
    folder = tmp_path_factory.mktemp("cornell")
    scene = as_json(env, "scene", "load", "--cornell-box", "--set", "resx=16", "--set",
                    "resy=16")
    rendered = as_json(env, "scene", "render", scene["name"], "--out", str(folder / "ref"),
                       "--spp", "16", "--sensor", "0")
    job = as_json(env, "job", "start", scene["name"], "--ref", rendered["files"][1],
                  "--param", KEY, "--iterations", "2", "--spp", "1", "--wait")
    return env, folder, scene, rendered, job


def test_json_of_representative_commands(cornell):
    env, folder, scene, rendered, job = cornell
    assert scene["name"].startswith("scenes/") and scene["sensors"][0]["width"] == 16
    assert [Path(f).name for f in rendered["files"]] == ["sensor0_render.png",
                                                         "sensor0_render.exr"]
    assert job["name"].startswith("jobs/") and job["state"] == "JOB_STATE_SUCCEEDED"
    assert job["iteration"] == 2 and job["spec"]["scene"] == scene["name"]

    out = folder / "export"
    exported = as_json(env, "job", "export", job["name"], "--out", str(out), "--which", "last")
    assert exported["job"] == job["name"] and exported["which"] == "last"
    assert exported["iteration"] == 1 and exported["directory"] == str(out)
    assert str(out / "parameters.json") in exported["files"]
    assert all(Path(f).is_file() for f in exported["files"])
    written = json.loads((out / "parameters.json").read_text())
    assert written["loss"] == exported["loss"] and KEY in written["parameters"]


def test_export_refuses_a_folder_that_is_not_empty(cornell):
    env, folder, _, _, job = cornell
    out = folder / "other"
    out.mkdir()
    (out / "parameters.json").write_text("another job's\n")
    refused = matopt(env, "job", "export", job["name"], "--out", str(out))
    assert refused.returncode == exit_codes.USAGE, refused.stderr
    assert f"folder '{out}' is not empty" in refused.stderr and "--force" in refused.stderr
    assert refused.stderr.count("\n") == 1 and not refused.stdout
    assert [p.name for p in out.iterdir()] == ["parameters.json"]
    assert (out / "parameters.json").read_text() == "another job's\n"

    forced = as_json(env, "job", "export", job["name"], "--out", str(out), "--force")
    assert json.loads((out / "parameters.json").read_text())["job"] == job["name"]
    assert str(out / "history.csv") in forced["files"]


def test_deletes_say_what_they_deleted(cornell):
    env, _, _, rendered, _ = cornell
    scene = as_json(env, "scene", "load", "--cornell-box", "--set", "resx=8", "--set", "resy=8")
    job = as_json(env, "job", "start", scene["name"], "--ref", rendered["files"][1],
                  "--param", KEY, "--iterations", "1", "--spp", "1", "--wait")
    assert as_json(env, "job", "delete", job["name"]) == {"deleted": [job["name"]]}
    assert as_json(env, "scene", "delete", scene["name"]) == {"deleted": [scene["name"]]}
    blobs = {b["name"]: b for b in as_json(env, "blob", "list")["blobs"]}
    unused = sorted(name for name, b in blobs.items() if not b.get("usedBy"))
    assert unused  # the deleted job's result images
    gone = as_json(env, "blob", "rm", "--unused")
    assert sorted(gone["deleted"]) == unused
    assert not set(unused) & {b["name"] for b in as_json(env, "blob", "list")["blobs"]}


def test_exit_statuses(cli_env, tmp_path):
    missing_xml = matopt(cli_env, "scene", "load", str(tmp_path / "gone.xml"))
    assert missing_xml.returncode == exit_codes.USAGE
    assert f"scene file '{tmp_path / 'gone.xml'}' does not exist" in missing_xml.stderr
    # A local file is checked before anything is asked of a daemon.
    assert matopt(cli_env, "scene", "load", str(tmp_path / "gone.xml"),
                  extra={"MATOPT_SERVER": NOWHERE}).returncode == exit_codes.USAGE

    missing_ref = matopt(cli_env, "job", "start", "scenes/x", "--ref",
                         str(tmp_path / "gone.exr"), "--param", KEY)
    assert missing_ref.returncode == exit_codes.USAGE
    assert f"reference image '{tmp_path / 'gone.exr'}' is not a file" in missing_ref.stderr

    refused = matopt(cli_env, "job", "status", "doesnotexist")
    assert refused.returncode == exit_codes.DAEMON
    assert refused.stderr.startswith("matopt: error: NOT_FOUND: ")
    assert "jobs/doesnotexist" in refused.stderr and refused.stderr.count("\n") == 1

    assert matopt(cli_env, "job", "status").returncode == exit_codes.USAGE  # click's own
    shown = matopt(cli_env, "--help").stdout
    assert "Exit status:" in shown
    assert all(f"  {code} " in shown for code in exit_codes.MEANINGS)


def bash_complete(env: dict[str, str], *words: str) -> list[str]:
    """What bash is given for the last word of ``matopt WORDS``, as the script that
    ``_MATOPT_COMPLETE=bash_source matopt`` writes asks for it."""
    out = subprocess.run([sys.executable, "-m", "matopt_client.cli"], capture_output=True,
                         text=True, timeout=60,
                         env={**env, "_MATOPT_COMPLETE": "bash_complete",
                              "COMP_WORDS": " ".join(("matopt",) + words),
                              "COMP_CWORD": str(len(words))})
    assert out.returncode == 0, out.stderr
    return [line.split(",", 1)[1] for line in out.stdout.splitlines()]


def test_completion_of_job_and_scene_ids_from_the_daemon(cornell, monkeypatch):
    env, _, scene, _, job = cornell
    job_id, scene_id = job["name"].removeprefix("jobs/"), scene["name"].removeprefix("scenes/")
    assert job_id in bash_complete(env, "job", "status", "")
    assert bash_complete(env, "job", "status", job_id[:6]) == [job_id]
    assert bash_complete(env, "job", "start", scene_id[:6], "--from", "jobs/" + job_id[:6]) \
        == [job["name"]]
    assert scene_id in bash_complete(env, "scene", "show", "")
    assert scene_id not in bash_complete(env, "job", "status", "")

    # The daemon named before the command or after it, not only by the environment.
    monkeypatch.delenv("MATOPT_SERVER", raising=False)
    monkeypatch.delenv("MATOPT_TOKEN", raising=False)
    shell = BashComplete(cli, {}, "matopt", "_MATOPT_COMPLETE")
    address = env["MATOPT_SERVER"]
    for args in (["--server", address, "job", "status"],
                 ["job", "status", "--server", address]):
        assert job_id in [c.value for c in shell.get_completions(args, "")], args
        item = next(c for c in shell.get_completions(args, job_id))
        assert item.help == "SUCCEEDED 2/2"


@pytest.mark.parametrize("shell", ["bash", "zsh", "fish"])
def test_the_completion_scripts_docs_cli_md_names_are_printed(shell):
    out = subprocess.run([sys.executable, "-m", "matopt_client.cli"], capture_output=True,
                         text=True, timeout=60,
                         env={**os.environ, "_MATOPT_COMPLETE": f"{shell}_source"})
    assert out.returncode == 0 and "_matopt_completion" in out.stdout, out.stderr
    assert f"_MATOPT_COMPLETE={shell}_source matopt" in (ROOT / "docs" / "cli.md").read_text()


def test_completion_without_a_daemon_completes_nothing(monkeypatch):
    monkeypatch.setenv("MATOPT_SERVER", NOWHERE)
    started = time.monotonic()
    assert BashComplete(cli, {}, "matopt", "_MATOPT_COMPLETE").get_completions(
        ["job", "status"], "") == []
    assert time.monotonic() - started < 5


def test_docs_cli_md_is_written_from_the_commands():
    committed = (ROOT / "docs" / "cli.md").read_text()
    assert committed == docs.render(), \
        f"docs/cli.md differs from the commands: run '{docs.REGENERATE}' in the " \
        "repository root and commit docs/cli.md"
    assert "## matopt job export" in committed and "`--force`" in committed
    assert '_MATOPT_COMPLETE=bash_source matopt' in committed
    assert all(f"- `{code}`: " in committed for code in exit_codes.MEANINGS)
