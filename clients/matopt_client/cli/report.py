"""``matopt job report``: several jobs' loss and parameter errors against run time, as one CSV
and PNG plots, so that methods can be compared at equal time rather than at equal iterations.

The x axis is always ``seconds`` (the daemon's optimizing time): an iteration of a 16 spp job
costs four times one at 4 spp, so curves over iterations would flatter the expensive method.

Parameter errors come from ``IterationRecord.errors`` when the daemon recorded them (jobs
given ``JobSpec.ground_truth``). A daemon that keeps the ground truth in the spec but does not
fill ``errors`` yet still sends each iteration's small parameter values, so the same relative
error (rmse / rms(truth), as ``ParameterError.relative`` defines it) is computed here from
those; jobs without ground truth simply have no error columns.

The plotting functions take plain :class:`Series`, not jobs, so that ``bench/`` draws its
plain-Mitsuba baselines with exactly the same code as the daemon's jobs.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import click

from matopt_client import client as mc
from matopt_client import workflow
from matopt_client.cli.output import emit_json, note
from matopt_client.cli.params import JOB
from matopt_client.cli.session import connected
from matopt_api.v1 import matopt_pb2 as pb

PLOT_HINT = "plots need matplotlib: install matopt-mitsuba[plot] (pip install 'matopt-mitsuba[plot]')"
CSV_NAME = "report.csv"
LOSS_PNG, ERRORS_PNG, IMAGE_ERROR_PNG = "loss.png", "parameter_error.png", "image_error.png"
ERROR_PREFIX = "relative_error:"  # CSV column of one parameter's relative error
PSNR_PREFIX = "psnr:"             # ... and of its PSNR in dB (from the daemon only)
LINESTYLES = ("-", "--", ":", "-.")


@dataclass
class Row:
    """One iteration of one run: what the daemon's IterationRecord says, errors by key."""

    iteration: int
    seconds: float
    loss: float
    image_error: float | None = None
    errors: dict[str, float] = field(default_factory=dict)  # key -> relative error
    psnr: dict[str, float] = field(default_factory=dict)    # key -> PSNR (dB)


@dataclass
class Series:
    """One run (a daemon job or a baseline outside the daemon) under the name it is shown by."""

    job: str
    label: str
    rows: list[Row]
    # key -> (seconds, relative standard error) of the best result, with ground truth: the
    # error the images leave, drawn as an error bar on the parameter-error curve
    standard_errors: dict[str, tuple[float, float]] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# Errors and rows
# ---------------------------------------------------------------------------------------------


def relative_error(values: Sequence[float], truth: Sequence[float]) -> float:
    """rmse(values - truth) / rms(truth), or the rmse when the truth is 0 (as in the API).

    NaN when the sizes differ, so a mismatch can never look like a good result.
    """
    if not truth or len(values) != len(truth):
        return math.nan
    rmse = math.sqrt(sum((v - t) ** 2 for v, t in zip(values, truth)) / len(truth))
    scale = math.sqrt(sum(t * t for t in truth) / len(truth))
    return rmse / scale if scale > 0 else rmse


def truth_of(spec: pb.JobSpec) -> dict[str, list[float]]:
    """The inline ground-truth values of a job's spec, by key."""
    return {v.key: list(v.value) for v in spec.ground_truth if v.value}


def record_row(record: pb.IterationRecord, truth: dict[str, list[float]]) -> Row:
    """A history record as a row; errors from the daemon, else computed from the values."""
    errors = {e.key: e.relative for e in record.errors}
    if not errors and truth:
        values = {v.key: list(v.value) for v in record.parameters if v.value}
        errors = {key: relative_error(values[key], t) for key, t in truth.items()
                  if key in values}
    image_error = record.image_error if record.HasField("image_error") else None
    return Row(record.iteration, record.seconds, record.loss, image_error, errors,
               {e.key: e.psnr for e in record.errors})


def default_label(job: pb.Job) -> str:
    """The job's id and the settings that usually tell two compared methods apart."""
    spec = job.spec
    loss = workflow.choice_name(pb.Loss, spec.loss)
    schedule = workflow.choice_name(pb.Schedule, spec.schedule)
    return f"{job.name.removeprefix('jobs/')} ({loss}, {spec.spp} spp, {schedule})"


def job_series(client: mc.Client, name: str, label: str | None = None) -> Series:
    """GetJob and GetJobHistory of one job, as a series."""
    job = client.jobs.GetJob(pb.GetJobRequest(name=name))
    history = mc.job_history(client, name)
    truth = truth_of(job.spec)
    at = next((r.seconds for r in history if r.iteration == job.best_iteration), None)
    errors = {}
    for p in job.best_parameters:
        finite = [e for e in p.standard_error if math.isfinite(e)]
        if at is not None and p.key in truth and finite and len(finite) == len(p.value):
            errors[p.key] = (at, relative_error(finite, [0.0] * len(finite))
                             / max(relative_error(truth[p.key], [0.0] * len(finite)), 1e-30))
    return Series(job.name, label or default_label(job), [record_row(r, truth) for r in history],
                  errors)


# ---------------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------------


def error_keys(series: Iterable[Series]) -> list[str]:
    """Every parameter that has an error somewhere, in order of first appearance."""
    keys: dict[str, None] = {}
    for s in series:
        for row in s.rows:
            keys.update(dict.fromkeys(row.errors))
    return list(keys)


def _cell(value: float | None) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return repr(value)


def write_csv(series: Sequence[Series], path: Path) -> Path:
    """One row per run and iteration; ``relative_error:<key>`` and ``psnr:<key>`` columns per
    parameter (PSNR in dB, as ``ParameterError.psnr`` defines it).

    float32 values (loss, errors) are written as the shortest decimal that reads back as the
    same float32; seconds in full. A missing value is an empty cell.
    """
    keys = error_keys(series)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["job", "label", "iteration", "seconds", "loss", "image_error",
                      *(ERROR_PREFIX + k for k in keys), *(PSNR_PREFIX + k for k in keys)])
        for s in series:
            for r in s.rows:
                out.writerow([s.job, s.label, r.iteration, repr(r.seconds),
                              _cell(mc.short_float(r.loss)),
                              _cell(None if r.image_error is None
                                    else mc.short_float(r.image_error)),
                              *(_cell(mc.short_float(r.errors[k]) if k in r.errors else None)
                                for k in keys),
                              *(_cell(mc.short_float(r.psnr[k]) if k in r.psnr else None)
                                for k in keys)])
    return path


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only, no display), or a one-line error."""
    try:
        import matplotlib
    except ImportError:
        raise click.ClickException(PLOT_HINT) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _figure(plt, title: str, ylabel: str):
    fig, ax = plt.subplots(figsize=(8, 5), dpi=100)
    ax.set_title(title)
    ax.set_xlabel("seconds (optimizing time)")
    ax.set_ylabel(ylabel)
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    return fig, ax


def _save(plt, fig, ax, path: Path) -> Path:
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _positive(xs: list[float], ys: list[float | None]) -> tuple[list[float], list[float]]:
    """Points a log axis can show (a dual-buffer loss may be negative, a value missing)."""
    pairs = [(x, y) for x, y in zip(xs, ys)
             if y is not None and math.isfinite(y) and y > 0]
    return [p[0] for p in pairs], [p[1] for p in pairs]


def plot_loss(series: Sequence[Series], path: Path, title: str = "loss against time") -> Path:
    plt = pyplot()
    fig, ax = _figure(plt, title, "loss (log)")
    for s in series:
        ax.plot(*_positive([r.seconds for r in s.rows], [r.loss for r in s.rows]),
                label=s.label)
    return _save(plt, fig, ax, path)


def plot_errors(series: Sequence[Series], path: Path,
                title: str = "parameter error against time") -> Path:
    """One curve per parameter and run: colour by parameter, line style by run; an error bar
    at the best result where it has standard errors (the relative error the images leave)."""
    plt = pyplot()
    fig, ax = _figure(plt, title, "relative error (log)")
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, key in enumerate(error_keys(series)):
        for n, s in enumerate(series):
            rows = [r for r in s.rows if key in r.errors]
            if rows:
                ax.plot(*_positive([r.seconds for r in rows], [r.errors[key] for r in rows]),
                        color=colours[k % len(colours)], linestyle=LINESTYLES[n % len(LINESTYLES)],
                        label=f"{s.label}: {key}")
            at = s.standard_errors.get(key)
            best = next((r.errors[key] for r in rows if r.seconds == at[0]), None) if at else None
            if best and best > 0:  # the best result's relative standard error, about it
                ax.errorbar([at[0]], [best], yerr=[[min(at[1], 0.9 * best)], [at[1]]],
                            color=colours[k % len(colours)], capsize=3)
    return _save(plt, fig, ax, path)


def plot_image_error(series: Sequence[Series], path: Path,
                     title: str = "image error against time") -> Path:
    plt = pyplot()
    fig, ax = _figure(plt, title, "image RMSE (log)")
    for s in series:
        rows = [r for r in s.rows if r.image_error is not None]
        if rows:
            ax.plot(*_positive([r.seconds for r in rows], [r.image_error for r in rows]),
                    marker="o", label=s.label)
    return _save(plt, fig, ax, path)


def write_report(series: Sequence[Series], out_dir: Path, title: str = "") -> list[Path]:
    """The CSV and every plot there is data for; returns the files written.

    The parameter-error plot needs errors (ground truth), the image-error plot image errors;
    without them the plot is left out rather than drawn empty.
    """
    pyplot()  # a missing matplotlib fails here, before anything is written
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    prefix = f"{title}: " if title else ""
    written = [write_csv(series, out_dir / CSV_NAME),
               plot_loss(series, out_dir / LOSS_PNG, prefix + "loss against time")]
    if error_keys(series):
        written.append(plot_errors(series, out_dir / ERRORS_PNG,
                                   prefix + "parameter error against time"))
    if any(r.image_error is not None for s in series for r in s.rows):
        written.append(plot_image_error(series, out_dir / IMAGE_ERROR_PNG,
                                        prefix + "image error against time"))
    return written


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------


@click.command()
@click.argument("names", metavar="JOB [JOB ...]", nargs=-1, required=True, type=JOB)
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="directory to write into (created if needed)")
@click.option("--label", "labels", multiple=True, metavar="TEXT",
              help="legend label of the next JOB, in order (default: id, loss, spp, schedule)")
@click.option("--json", "as_json", is_flag=True, help="print the files written as JSON")
def report(names: tuple[str, ...], out_dir: str, labels: tuple[str, ...],
           as_json: bool) -> None:
    """Compare jobs' error against run time: report.csv and PNG plots in --out.

    report.csv has one row per job and iteration (seconds, loss, image error, and each
    parameter's relative error when the job was given ground truth). loss.png and
    parameter_error.png plot them against seconds on a log scale, all jobs in one plot, so
    methods compare at equal time. Needs matplotlib (install matopt-mitsuba[plot]).
    Prints the files written, one per line.
    """
    if len(labels) > len(names):
        raise click.BadParameter(f"{len(labels)} labels for {len(names)} job(s)",
                                 param_hint="--label")
    pyplot()  # a missing matplotlib is reported before anything is fetched
    client = connected()
    series = [job_series(client, name, label)
              for name, label in zip(names, [*labels, *[None] * len(names)])]
    written = write_report(series, Path(out_dir))
    if not error_keys(series):
        note("no parameter errors: none of the jobs was given ground truth, so "
             f"{ERRORS_PNG} is left out")
    if as_json:
        emit_json({"files": [str(p) for p in written]})
    else:
        for path in written:
            click.echo(str(path))
