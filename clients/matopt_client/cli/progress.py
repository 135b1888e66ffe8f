"""Following a running job on the terminal, and turning how it ended into an exit status.

Shared by ``job start --wait``, ``job watch`` and ``demo`` so that all three report progress and
failures the same way: a job that FAILED or was CANCELLED makes the command exit non-zero.
"""

from __future__ import annotations

import shutil
import sys
from typing import Callable

import click
import grpc
from tqdm import tqdm

from matopt_client import client as mc
from matopt_client import workflow
from matopt_client.cli.output import best, note, number, parameter_error, stop_reason
from matopt_api.v1 import matopt_pb2 as pb

# tqdm's layout; {postfix} comes with its own leading ", ".
BAR_FORMAT = "{desc} {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt}{postfix}"
MIN_BAR_WIDTH = 10  # narrower, the best loss and then the time are left out to keep the bar


class Interrupted(click.ClickException):
    """Ctrl-C while following a job: the job itself keeps running on the daemon."""

    exit_code = 130


class JobProgress:
    """Shows a job's progress on stderr while it runs (tqdm draws the bar).

    On a terminal one line rewrites itself (state, bar, iteration/total, loss, time, best),
    fitted to the terminal's width. In a log (not a terminal), a line per state change and
    per tenth of the iterations, each a complete line, so CI logs stay short but show
    movement.

    "best" is the daemon's best iteration, shown with its number (``best 0.0111 at 369``),
    the one ``job status`` and ``job result --which best`` name. It may read higher than the
    loss beside it, for two reasons the label makes visible rather than hides: the loss is
    the latest iteration's, while the daemon ranks iterations in batches (its best comes with
    the job after each batch), so a newer iteration that did better is not ranked yet; and
    for a windowed loss (dual_buffer, whose single estimates are noisy) the daemon ranks the
    mean over the iterations ending there, shown as ``best mean``. Recomputing a best here
    from the losses would name another iteration than the result a user then fetches.
    """

    def __init__(self, interactive: bool | None = None) -> None:
        self.interactive = sys.stderr.isatty() if interactive is None else interactive
        self.state = ""
        self.total = 0
        self.iteration = 0
        self.loss: float | None = None
        self.best: tuple[int, float] | None = None  # the daemon's (iteration, loss)
        self.windowed = False  # the daemon ranks a mean over iterations, not single losses
        self.seconds = 0.0
        self._last_tenth = -1
        self._bar: tqdm | None = None

    def __call__(self, event: pb.JobEvent) -> None:
        if event.HasField("job"):
            job = event.job
            changed = mc.state_name(job.state) != self.state
            self.state = mc.state_name(job.state)
            self.total, self.iteration = job.spec.iterations, job.iteration
            self.seconds = job.elapsed_seconds
            if job.iteration:
                self.loss = job.loss
            self.best = workflow.best(job) or self.best
            self.windowed = job.spec.loss == pb.LOSS_DUAL_BUFFER
            if changed and not self.interactive:
                self._last_tenth = self._tenth()
                note(self.line())
        else:
            record = event.iteration
            # Records are numbered from 0; after record i, i + 1 iterations are complete.
            self.iteration = record.iteration + 1
            self.loss, self.seconds = record.loss, record.seconds
            tenth = self._tenth()
            if not self.interactive and tenth != self._last_tenth:
                self._last_tenth = tenth
                note(self.line())
        if self.interactive:
            self._draw()

    def _tenth(self) -> int:
        return self.iteration * 10 // self.total if self.total else 0

    def _meter(self, width: int | None) -> dict:
        """tqdm's fields for a line of at most ``width`` columns (None: any)."""
        extras = [f"loss {number(self.loss)}"] if self.loss is not None else []
        extras.append(f"{self.seconds:.1f} s")
        if self.best is not None:
            label = "best mean" if self.windowed else "best"
            extras.append(f"{label} {number(self.best[1])} at {self.best[0]}")
        while True:
            meter = dict(n=min(self.iteration, self.total), total=self.total or None,
                         elapsed=self.seconds, prefix=self.state, postfix="  ".join(extras),
                         bar_format=BAR_FORMAT)
            bare = tqdm.format_meter(**{**meter, "bar_format": BAR_FORMAT.replace("{bar}", "")})
            if width is None or not extras or width - len(bare) >= MIN_BAR_WIDTH:
                return meter
            extras.pop()

    def line(self, width: int | None = None) -> str:
        """The progress in at most ``width`` columns (None: with a bar of tqdm's size)."""
        return tqdm.format_meter(ncols=width, **self._meter(width))

    def _draw(self) -> None:
        # One column short of the width: a line filling the last column wraps on some
        # terminals, and the next carriage return would then rewrite the wrong line.
        width = shutil.get_terminal_size().columns - 1
        meter = self._meter(width)
        if self._bar is None:
            self._bar = tqdm(file=sys.stderr, bar_format=BAR_FORMAT, mininterval=0)
        self._bar.ncols, self._bar.total, self._bar.n = width, meter["total"], meter["n"]
        self._bar.set_description_str(meter["prefix"], refresh=False)
        self._bar.set_postfix_str(meter["postfix"], refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()  # leaves the last line standing
            self._bar = None


def describe(event: pb.JobEvent, total: int = 0) -> str:
    """One line per event, for ``job watch``."""
    if event.HasField("job"):
        job = event.job
        text = f"{job.name} {mc.state_name(job.state)} {job.iteration}/{job.spec.iterations}"
        if job.iteration:
            text += f" loss {number(job.loss)}"
        if best(job):
            text += f", best {best(job)}"
        if job.error:
            text += f": {job.error}"
        phase = next((n for n in job.notes if n.startswith("end phase: ")), None)
        if phase and job.state == pb.JOB_STATE_RUNNING:  # e.g. rendering result images 3/8
            text += f" ({phase})"
        return text
    record = event.iteration
    of = f"/{total}" if total else ""
    text = f"iteration {record.iteration}{of} loss {number(record.loss)} ({record.seconds:.2f} s)"
    for e in record.errors:  # with ground truth
        text += f"; {e.key}: {parameter_error(e)}"
    for g in record.gains:  # with --fit-exposure
        text += f", gain {workflow.gain_reference(g)} " + "/".join(f"{v:.3g}" for v in g.rgb)
    return text


def describe_state(job: pb.Job) -> str:
    """What of a job the reader of ``job watch`` follows besides iterations: its state, its
    end phase and its error."""
    phase = next((n for n in job.notes if n.startswith("end phase: ")), "")
    return f"{mc.state_name(job.state)} {phase} {job.error}"


def follow(client: mc.Client, name: str, on_event: Callable[[pb.JobEvent], None]) -> pb.Job:
    """Waits for the job to end; says what became of the job when the waiting stops early.

    Ctrl-C leaves the job running; a lost connection (the daemon stopped or restarted) leaves
    it running or INTERRUPTED. Either way the user learns how to pick it up again.
    """
    try:
        return mc.wait(client, name, on_event)
    except KeyboardInterrupt:
        raise Interrupted(f"interrupted; {name} keeps running on the daemon "
                          f"('matopt job cancel {name}' stops it)") from None
    except grpc.RpcError as exc:
        if exc.code() != grpc.StatusCode.UNAVAILABLE:
            raise
        raise click.ClickException(
            f"lost the connection to matoptd while following {name} ({mc.error_message(exc)}); "
            f"'matopt job status {name}' shows what became of it") from None


def outcome(job: pb.Job) -> None:
    """Reports how the job ended; raises (exit status 1) unless it SUCCEEDED."""
    state = mc.state_name(job.state)
    if job.state == pb.JOB_STATE_SUCCEEDED:
        reason = stop_reason(job)
        lowest = f"; best loss {best(job)}" if best(job) else ""
        note(f"{job.name} SUCCEEDED after {job.iteration} iterations"
             f"{f' ({reason})' if reason else ''}{lowest}")
        return
    if job.state == pb.JOB_STATE_FAILED:
        raise click.ClickException(f"job '{job.name}' FAILED: {job.error or 'no reason given'}")
    if job.state == pb.JOB_STATE_CANCELLED:
        raise click.ClickException(f"job '{job.name}' was cancelled")
    hint = f" ('matopt job resume {job.name}' continues it)" if job.state == pb.JOB_STATE_INTERRUPTED else ""
    raise click.ClickException(f"job '{job.name}' stopped in state {state}{hint}")
