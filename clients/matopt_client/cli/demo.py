"""``matopt demo``: the whole loop on the built-in Cornell box, with nothing set up beforehand.

It renders a reference from the true wall colours, starts a job from grey walls, and shows
how close the recovered colours come: a check that an installation works end to end, and a
first example to read. Without a daemon at --server it runs a private one for its duration.
"""

from __future__ import annotations

import contextlib
import math
import time
from pathlib import Path

import click

from matopt_client import client as mc
from matopt_client.client import short_float, short_floats
from matopt_client import workflow
from matopt_client.cli.output import emit_json, json_option, note, number, table
from matopt_client.cli.progress import JobProgress, outcome
from matopt_client.cli.session import Settings
from matopt_client.export import export_job
from matopt_client.local_daemon import LocalDaemon
from matopt_api.v1 import matopt_pb2 as pb

KEYS = ("red.reflectance.value", "green.reflectance.value", "white.reflectance.value")
START = [0.5, 0.5, 0.5]  # grey: far from every wall's true colour
REFERENCE_SPP = 256
PROBE_TIMEOUT_S = 2.0


def _client(stack: contextlib.ExitStack) -> mc.Client:
    """The daemon at --server if one answers, else a private one stopped when ``stack`` closes."""
    settings = click.get_current_context().ensure_object(Settings)
    try:
        client = mc.connect(settings.server, settings.token, settings.tls_ca,
                            probe_timeout=PROBE_TIMEOUT_S)
    except mc.Unreachable:
        note(f"no matoptd answers at {settings.server}; starting a private matoptd ...")
        daemon = stack.enter_context(LocalDaemon())
        started = time.monotonic()
        client = daemon.start()
        note(f"private matoptd ready at {daemon.address} "
             f"({time.monotonic() - started:.0f} s)")
    stack.callback(client.close)
    return client


def _run(client: mc.Client, name: str) -> pb.Job:
    """Waits with a progress bar; Ctrl-C cancels the job rather than leaving it running."""
    progress = JobProgress()
    try:
        return mc.wait(client, name, progress)
    except KeyboardInterrupt:
        with contextlib.suppress(Exception):
            client.jobs.CancelJob(pb.CancelJobRequest(name=name), timeout=5)
        raise
    finally:
        progress.close()


@click.command()
@click.option("--out", "out_dir", default="./matopt-demo", show_default=True,
              type=click.Path(file_okay=False), help="directory for the results")
@click.option("--resolution", default=128, show_default=True, type=int,
              help="image width and height")
@click.option("--iterations", default=100, show_default=True, type=int,
              help="optimization steps")
@click.option("--spp", default=4, show_default=True, type=int,
              help="samples per pixel of each step")
@json_option
def demo(out_dir: str, resolution: int, iterations: int, spp: int, as_json: bool) -> None:
    """Run the whole loop on the built-in Cornell box.

    Renders a reference from the true wall colours, optimizes the walls from grey, exports
    the result to --out and compares recovered and true colours. Uses the daemon at --server
    if one answers, else starts a private one for its duration.
    """
    with contextlib.ExitStack() as stack:
        client = _client(stack)
        scene = workflow.create_scene(client, None, {"resx": str(resolution),
                                                     "resy": str(resolution)})
        note(f"created {scene.name} (built-in Cornell box, {resolution}x{resolution})")
        truth = {p.key: list(p.value) for p in client.scenes.ListSceneParameters(
            pb.ListSceneParametersRequest(name=scene.name)).parameters}
        missing = [k for k in KEYS if k not in truth]
        if missing:
            raise click.ClickException(f"{scene.name} has no parameter {', '.join(missing)}")

        note(f"rendering the reference image ({REFERENCE_SPP} spp) ...")
        images = client.scenes.RenderScene(pb.RenderSceneRequest(
            name=scene.name, spp=REFERENCE_SPP, sensors=[0])).images
        reference = next((i for i in images if i.sensor == 0), None)
        if reference is None or not reference.exr_blob:
            raise click.ClickException(f"rendering {scene.name} returned no image of sensor 0")

        spec = workflow.build_spec(
            scene.name, [pb.ParameterSpec(key=k, initial_value=START) for k in KEYS],
            workflow.JobSettings(iterations=iterations, spp=spp))
        job = workflow.start_job(client, spec, [workflow.ReferenceFile(
            reference.exr_blob, filename="reference.exr")])
        note(f"started {job.name}")
        outcome(_run(client, job.name))

        # The last iteration, not the lowest loss: at 4 spp each loss is mostly render noise,
        # and its minimum favours darker (less noisy) walls; the decaying learning rate has
        # let the last iterate settle on the optimum.
        done = export_job(client, job.name, Path(out_dir), "last")
        recovered = {v.key: list(v.value) for v in done.result.parameters}
        initial = {v.key: list(v.value) for v in done.result.initial_parameters}
        errors = {key: _max_error(recovered.get(key, []), truth[key]) for key in KEYS}
        if as_json:
            emit_json({
                "scene": scene.name, "job": job.name, "directory": out_dir,
                "iteration": done.result.iteration, "loss": short_float(done.result.loss),
                "maxAbsError": _finite(_max(errors.values())),
                "parameters": [{"key": key, "initial": short_floats(initial.get(key, START)),
                                "recovered": short_floats(recovered.get(key, [])),
                                "true": short_floats(truth[key]),
                                "maxAbsError": _finite(errors[key])} for key in KEYS]})
            return
        table(["PARAMETER", "INITIAL", "RECOVERED", "TRUE", "MAX ABS ERROR"],
              [[key, _vector(initial.get(key, START)), _vector(recovered.get(key, [])),
                _vector(truth[key]), number(errors[key])] for key in KEYS])
        click.echo(f"max abs error {number(_max(errors.values()))} (last iteration "
                   f"{done.result.iteration}, loss {number(done.result.loss)}); "
                   f"results in {out_dir}")


def _max_error(a: list[float], b: list[float]) -> float:
    """Largest component difference; NaN when a value is missing, so it cannot look good."""
    if not a or len(a) != len(b):
        return math.nan
    return max(abs(x - y) for x, y in zip(a, b))


def _max(values) -> float:
    values = list(values)
    return math.nan if any(math.isnan(v) for v in values) else max(values)


def _finite(value: float) -> float | None:
    """JSON has no NaN: a missing value is null."""
    return None if math.isnan(value) else short_float(value)


def _vector(values) -> str:
    return "(" + ", ".join(f"{v:.3f}" for v in values) + ")"
