"""Every option of ``matoptd``, declared once in ``OPTIONS``: its flag, its environment
variable, its key in a config file, how its text is read, its default and its help all come
from there, so ``--help``, the environment and the config file cannot disagree.

A value comes from the first of: the command line, the environment (``MATOPTD_<NAME>``), the
config file (``--config`` or ``MATOPTD_CONFIG``, ``config.py``), the default. An empty
environment variable counts as unset: systemd's EnvironmentFile= leaves a blank one as
``VAR=``.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Callable, Mapping

from . import __version__, config
from .server import admission
from .workers import devices

ENV_PREFIX = "MATOPTD_"
LOG_LEVELS = ("debug", "info", "warning", "error", "critical")
LOG_FORMATS = ("text", "json")
METRICS_HOST = "127.0.0.1"  # where --metrics-port serves when it names no host
# Nice levels of the server's threads below the workers', so that rendering goes first: the
# lowest where CPU workers render on the server's own cores, else SERVER_NICE (server_nice).
SERVER_NICE, SERVER_NICE_SHARED = 10, 19
# ... and where it is niced beside CPU workers, the seconds a lane leaves the CPU to it at a
# job's load and first iteration (scheduling.State.server_turn).
SERVER_TURN_S = 0.005


@dataclass(frozen=True)
class Option:
    """One option. ``help`` None hides it (not in --help, the environment or a config
    file). ``default`` is shown in --help unless ``help`` already says it ("default")."""

    name: str
    help: str | None
    parse: Callable[[str], Any] = str
    default: Any = None
    metavar: str | None = None
    choices: tuple[str, ...] | None = None

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def variable(self) -> str:
        return ENV_PREFIX + self.name.upper()

    def describe(self) -> str | None:
        if self.help is None or self.default is None or "default" in self.help:
            return self.help
        shown = (f"{self.default >> 30}G" if self.parse is devices.parse_size
                 else f"{self.default:,}" if isinstance(self.default, int)
                 else f"{self.default:g}" if isinstance(self.default, float) else self.default)
        return f"{self.help} (default {shown})"


def _limit(name: str, text: str) -> Option:
    """An admission limit (admission.Limits), its default there; sizes take suffixes (4G)."""
    size = name.endswith("_memory")
    return Option(name, text, devices.parse_size if size else int,
                  getattr(admission.Limits, name), "SIZE" if size else "N")


OPTIONS = (
    Option("config", "TOML file of settings, keys as the long flags (listen = "
           "\"0.0.0.0:50051\"); the command line and the environment win over it",
           Path, metavar="FILE"),
    Option("listen", "HOST:PORT to serve on; port 0 picks a free one",
           default="127.0.0.1:50051", metavar="HOST:PORT"),
    Option("data_dir", "where scenes, jobs, results and blobs live", Path,
           Path.home() / ".local" / "share" / "matoptd", "DIR"),
    Option("tokens", "file of 'TOKEN USER' lines, read again on SIGHUP; without it only a "
           "local user, on loopback, is served", Path, metavar="FILE"),
    Option("tls_cert", "PEM certificate chain to serve TLS with (with --tls-key); without "
           "both the API is plaintext", Path, metavar="FILE"),
    Option("tls_key", "PEM private key of --tls-cert", Path, metavar="FILE"),
    Option("variant", "Mitsuba variant (default: cuda_ad_rgb on each CUDA device that works, "
           "else llvm_ad_rgb)"),
    Option("devices", "CUDA devices to run workers on, e.g. 0,1 (default: every one that "
           "works); a device named twice gets two workers", metavar="LIST"),
    Option("workers", "run N CPU workers instead, the cores split between them", int,
           metavar="N"),
    Option("ray", "host the workers as Ray actors on a cluster: 'auto' (the cluster this "
           "machine runs in), 'ray://HEAD:10001', 'HOST:PORT', or 'local' for a private Ray "
           "instance on this machine; one worker per GPU of the cluster, or with --workers N "
           "(or no GPU in the cluster at start) N CPU workers per machine (needs "
           "matopt-mitsuba[daemon,ray])", metavar="ADDRESS"),
    Option("workers_per_device", "worker processes sharing each CUDA device: 'auto' as many "
           "as its free memory holds for jobs up to --max-samples (at most 8), or N; on a "
           "CPU-only host N workers that each render on all cores ('auto': one, or --workers)",
           default="auto", metavar="auto|N"),
    Option("server_cores", "keep the first N cores this process may use for the server (API, "
           "store, scheduler) and give the workers only the others, so that status traffic "
           "never competes with rendering (default: all shared)", int, metavar="N"),
    Option("server_nice", "nice levels the server's threads (gRPC, the API's handlers) run "
           "below the workers, so that on cores they share rendering goes first; 0 leaves "
           f"them as started (default: {SERVER_NICE_SHARED} where CPU workers render on the "
           f"server's cores, else {SERVER_NICE})", int, metavar="N"),
    Option("worker_memory", "resident memory a worker may use before it is stopped and its "
           "job fails, e.g. 8G (default: 80%% of the machine's memory, shared among the "
           "workers)", metavar="SIZE"),
    Option("watchdog", "seconds without an answer after which a worker counts as hung and is "
           "restarted; an iteration gets 20x its job's usual time if that is more, a load or "
           "first iteration 5x this", float, 120.0, "SECONDS"),
    Option("quota", "bytes of blobs each user may own (uploads, renders, results), e.g. 20G; "
           "past it uploads are refused, and new scenes, renders and jobs until the user "
           "deletes blobs; results of running jobs are still kept (default: no limit)",
           metavar="SIZE"),
    _limit("max_samples", "samples (film pixels x spp) one render call may take; 2^26 is "
           "4096x4096 at 4 spp or 1024x1024 at 64 spp"),
    _limit("max_film_side", "pixels on a side of any film a request renders"),
    _limit("max_film_memory", "memory of all films one request renders (16 bytes a pixel)"),
    _limit("max_reference_pixels", "pixels of one reference image, read from its header"),
    _limit("max_reference_memory", "memory to decode one reference image"),
    _limit("max_jobs_per_user", "queued or running jobs of one user"),
    _limit("max_tasks_per_user", "scene requests (CreateScene, RenderScene, CreateJob) of one "
           "user in progress at once"),
    Option("metrics_port", "serve Prometheus metrics over HTTP at /metrics on PORT (on "
           f"{METRICS_HOST}) or HOST:PORT; port 0 picks a free one, which the log names "
           "(default: no metrics)", metavar="[HOST:]PORT"),
    Option("port_file", "write the bound port here once serving (useful with port 0)", Path,
           metavar="FILE"),
    Option("log_level", "least severity logged", str.lower, "info", choices=LOG_LEVELS),
    Option("log_format", "'text' lines, or 'json': one object a line with time, level, "
           "logger, message, and job and user where a line is about one", str.lower, "text",
           choices=LOG_FORMATS),
    Option("slice", None, float),  # seconds of a job's slice, for tests
)
BY_NAME = {o.name: o for o in OPTIONS}
LIMITS = tuple(f.name for f in fields(admission.Limits))
# What a config file may set: every visible option but the file itself.
CONFIG_KEYS = frozenset(o.name for o in OPTIONS if o.help is not None and o.name != "config")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="matoptd", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="The matopt material-reconstruction daemon (gRPC API matopt.v1).",
        epilog=_epilog(), argument_default=argparse.SUPPRESS)
    for o in OPTIONS:
        p.add_argument(o.flag, dest=o.name, type=o.parse, metavar=o.metavar, choices=o.choices,
                       help=o.describe() if o.help is not None else argparse.SUPPRESS)
    p.add_argument("--version", action="version", version=f"matoptd {__version__}")
    return p


def _epilog() -> str:
    shown = [o for o in OPTIONS if o.help is not None]
    width = max(len(o.variable) for o in shown)
    lines = [f"  {o.variable:<{width}}  {o.flag}" for o in shown]
    return "\n".join([
        "Environment: each option is also read from a variable (empty counts as unset):",
        *lines,
        "The workers also read Dr.Jit's DRJIT_LIBLLVM_PATH and DRJIT_CACHE_DIR, and",
        "CUDA_VISIBLE_DEVICES.",
        "",
        "Precedence: command line > environment > config file (--config) > default.",
        "A config file is TOML with the long flags as keys, dashes or underscores alike:",
        '  listen = "0.0.0.0:50051"',
        '  data-dir = "/var/lib/matoptd"    # relative paths: from the file\'s folder',
        "  max_jobs_per_user = 8",
        "An unknown key is an error. SIGHUP reads the --tokens file again.",
    ])


def parse_args(argv: list[str] | None = None,
               environ: Mapping[str, str] | None = None) -> argparse.Namespace:
    """Every option's value, by the precedence above; a bad value exits (status 2) with a
    message naming where it came from."""
    environ = os.environ if environ is None else environ
    p = parser()
    given = vars(p.parse_args(argv))
    env = {o.name: environ[o.variable] for o in OPTIONS
           if o.help is not None and environ.get(o.variable, "") != ""}
    values: dict[str, Any] = {}
    for name, text in env.items():
        if name not in given:
            values[name] = _read(p, BY_NAME[name], text, BY_NAME[name].variable)
    path = given.get("config", values.get("config"))
    if path is not None:
        try:
            settings = config.load(path, CONFIG_KEYS)
        except config.ConfigError as exc:
            p.error(str(exc))
        for name, value in settings.items():
            if name not in given and name not in values:
                o = BY_NAME[name]
                read = _read(p, o, value, f"{path}: '{name}'")
                values[name] = config.relative(read, Path(path)) if o.parse is Path else read
    values.update(given)
    return argparse.Namespace(**{o.name: values.get(o.name, o.default) for o in OPTIONS})


def _read(p: argparse.ArgumentParser, o: Option, given: Any, where: str) -> Any:
    """``given`` (a variable's text, a config file's value) as the option reads it; a bad
    one exits naming ``where`` it came from."""
    try:
        text = config.text(given)
        value = o.parse(text)
    except (TypeError, ValueError) as exc:
        p.error(f"{where}: invalid value {given!r} for {o.flag}: {exc}")
    if o.choices and value not in o.choices:
        p.error(f"{where}: '{text}' for {o.flag} is not one of {', '.join(o.choices)}")
    return value
