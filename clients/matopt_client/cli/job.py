"""``matopt job ...``: start optimization jobs, follow them, control them, export results."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import click

from matopt_client import client as mc
from matopt_client.client import short_float
from matopt_client import workflow
from matopt_client.cli.output import (best, deleted, emit_json, fields, json_option, note,
                                      number, parameter_error, table, timestamp, uploading,
                                      warn)
from matopt_client.cli.params import (JOB, SCENE, LearningRate, Range, ReferenceImage, SppPhase,
                                      Values)
from matopt_client.cli.progress import JobProgress, describe, describe_state, follow, outcome
from matopt_client.cli.session import Group, connected
from matopt_client.export import WHICH, export_job
from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb

STATES = enums.short_names(pb.JobState)
# --preset plain: Mitsuba's plain Adam loop as the thesis ran it (one rate for every parameter
# without its own, constant, none of the engine's choices).
PLAIN_LEARNING_RATE = 0.03


@click.group(cls=Group)
def job() -> None:
    """Optimize a scene's parameters to match reference images."""


def parameter_specs(keys: Sequence[str], rates, ranges, inits, smooth=()
                    ) -> list[pb.ParameterSpec]:
    """One ParameterSpec per --param, with only the fields the user set.

    Unset ``optional`` fields stay absent so the daemon applies the parameter's own defaults;
    a --lr/--range/--init/--smooth for a key that is not a --param is a mistake on the
    command line.
    """
    specs = {key: pb.ParameterSpec(key=key) for key in keys}

    def spec(key: str, option: str) -> pb.ParameterSpec:
        if key not in specs:
            raise click.BadParameter(f"'{key}' is not one of the --param keys", param_hint=option)
        return specs[key]

    for key, rate in rates:
        if key is not None:
            spec(key, "--lr").learning_rate = rate
    for key, low, high in ranges:
        s = spec(key, "--range")
        if low is not None:
            s.min = low
        if high is not None:
            s.max = high
    for arg in inits:
        s = spec(arg.key, "--init")
        del s.initial_value[:]
        s.initial_value.extend(arg.values)
        if arg.npy is not None:
            s.initial_blob = arg.npy  # a local path until ``upload_values`` replaces it
    for key, weight in smooth:
        if key is None:
            raise click.BadParameter(f"'{weight}' names no parameter: give KEY=WEIGHT",
                                     param_hint="--smooth")
        spec(key, "--smooth").smoothness = weight
    return list(specs.values())


def check_npy(path: str, shape: Sequence[int], option: str) -> None:
    """A .npy file's shape against its parameter's: equal, or flat with as many components
    (Mitsuba's order). Fails naming the file and both shapes."""
    import numpy as np  # only when a .npy is given

    try:
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise click.BadParameter(f"'{path}' is not a readable .npy file: {exc}",
                                 param_hint=option) from None
    expected = tuple(shape) or (1,)
    size = int(np.prod(expected))
    if array.shape != expected and not (array.ndim == 1 and array.size == size):
        raise click.BadParameter(
            f"'{path}' has shape {list(array.shape)}, but the parameter has shape "
            f"{list(expected)} ({size} components)", param_hint=option)


def upload_values(client: mc.Client, scene: str, specs: Sequence[pb.ParameterSpec],
                  truths: Sequence[pb.ParameterValue]) -> None:
    """Checks each --init/--truth .npy file against its parameter's shape, then uploads it
    and names the blob in its place."""
    files = [(s, "initial_blob", "--init") for s in specs if s.initial_blob] + \
            [(t, "blob", "--truth") for t in truths if t.blob]
    if not files:
        return
    shapes = {p.key: list(p.shape) for p in client.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene)).parameters}
    for message, attribute, option in files:
        path = getattr(message, attribute)
        if not os.path.isfile(path):
            raise click.BadParameter(f"'{path}' is not a file", param_hint=option)
        if message.key in shapes:  # an unknown key is the daemon's to name
            check_npy(path, shapes[message.key], option)
        setattr(message, attribute, mc.blob_name(mc.upload_file(client, path, uploading)))


NO_MASK, ALPHA_MASK = "-", "@alpha"  # --mask values that name no file


def reference_files(refs: Sequence[tuple[int | None, str]],
                    masks: Sequence[str]) -> list[workflow.ReferenceFile]:
    """The --ref images with the --mask in the same position (a file, a blob, ``@alpha`` or
    ``-``), each local file checked before anything is uploaded."""
    if masks and len(masks) != len(refs):
        raise click.BadParameter(f"got {len(masks)} --mask for {len(refs)} --ref: give one per "
                                 f"--ref, in the same order ('{NO_MASK}' for none)",
                                 param_hint="--mask")
    out = [workflow.ReferenceFile(image=image, sensor=sensor,
                                  mask=None if mask in (NO_MASK, ALPHA_MASK) else mask,
                                  alpha_mask=mask == ALPHA_MASK)
           for (sensor, image), mask in zip(refs, list(masks) or [NO_MASK] * len(refs))]
    try:
        workflow.check_reference_files(out)
    except workflow.MissingFile as exc:
        raise click.BadParameter(str(exc), param_hint="--mask" if exc.mask else "--ref") from None
    return out


def checked_settings(client: mc.Client, settings: workflow.JobSettings) -> None:
    """The loss, schedule and sensor mode against what this daemon offers ('matopt info'),
    lower-cased; a wrong one is a usage error naming the choices."""
    offered = workflow.choices(client.info or client.server.GetServerInfo(
        pb.GetServerInfoRequest()))
    for name, allowed in (("loss", offered.losses), ("schedule", offered.schedules),
                          ("sensor_mode", offered.sensor_modes)):
        value = getattr(settings, name)
        if value is not None:
            try:
                setattr(settings, name, workflow.check_choice(name.replace("_", " "), value,
                                                              allowed))
            except ValueError as exc:
                raise click.BadParameter(str(exc), param_hint="--" + name.replace("_", "-"))


@job.command()
@click.argument("scene", type=SCENE)
@click.option("--ref", "refs", multiple=True, required=True, type=ReferenceImage(),
              help="reference image (PNG, JPEG, EXR) for the next sensor, or N=IMAGE for "
                   "sensor N; IMAGE may also be blobs/<sha256> (repeatable)")
@click.option("--mask", "masks", multiple=True, metavar="MASK",
              help="mask of the reference given by the --ref in the same position: an image "
                   "of its size (black = pixel left out, white = counted), blobs/<sha256>, "
                   f"'{ALPHA_MASK}' (the reference's own alpha channel) or '{NO_MASK}' (none); "
                   "give none, or one per --ref")
@click.option("--fit-exposure", is_flag=True,
              help="fit an RGB gain per reference (unknown exposure and white balance of "
                   "photographs), with the parameters")
@click.option("--param", "keys", multiple=True, required=True, metavar="KEY",
              help="a parameter to optimize, see 'matopt scene params' (repeatable)")
@click.option("--lr", "rates", multiple=True, type=LearningRate(),
              help="learning rate of one parameter (KEY=RATE), or of all without their own")
@click.option("--range", "ranges", multiple=True, type=Range(),
              help="legal range of a parameter; a bound may be left empty")
@click.option("--init", "inits", multiple=True, type=Values(npy=True),
              help="start value of a parameter instead of the scene's: KEY=v1,v2,... or "
                   "KEY=@values.npy (textures, grids)")
@click.option("--smooth", "smooth", multiple=True, type=LearningRate(),
              metavar="KEY=WEIGHT",
              help="smoothness weight of a texture or grid (e.g. 0.1): damps the noise of "
                   "texels few pixels see [default: 0, off]")
@click.option("--loss", metavar="NAME",
              help="image loss, one of 'matopt info' (mse, dual_buffer, mae, ...) "
                   "[daemon default: mse]")
@click.option("--schedule", metavar="NAME",
              help="learning-rate schedule, one of 'matopt info' (cosine, constant) "
                   "[daemon default: cosine]")
@click.option("--iterations", type=int, help="optimization steps [daemon default: 100]")
@click.option("--spp", type=int, help="samples per pixel of each step [daemon default: 16]")
@click.option("--spp-from", "spp_from", multiple=True, type=SppPhase(), metavar="ITER:SPP",
              help="from iteration ITER on, SPP samples per pixel instead of --spp, e.g. "
                   "'--spp 8 --spp-from 16:64' (repeatable; 'matopt job history' shows each "
                   "iteration's)")
@click.option("--large-steps", "large_steps", type=float, metavar="LAMBDA",
              help="lambda of the LargeSteps (Nicolet et al. 2021) that vertex positions take "
                   "(more for finer meshes); default: the mesh's vertices / 256, and "
                   "'--choice large_steps=off' steps each vertex by plain Adam")
@click.option("--starts", type=int, metavar="N",
              help="compare N starts (1 to 8): short probes from the given start, the "
                   "ranges' middles and colours' extremes, then the rest of the iterations "
                   "from the best; the result says where the images allow several answers "
                   "[daemon default: 1]")
@click.option("--min-error", type=float,
              help="stop once the loss is below this [daemon default: 0, off]")
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), help="random seed")
@click.option("--sensor-mode", metavar="NAME",
              help="one step from all sensors' gradients (accumulate), or one per sensor "
                   "(step_per_sensor), as 'matopt info' lists them [daemon default: accumulate]")
@click.option("--clamp", is_flag=True, help="clamp render and reference to [0, 1] (LDR)")
@click.option("--resolution", type=int,
              help="film height in pixels; widths follow each reference's aspect ratio")
@click.option("--truth", "truths", multiple=True, type=Values(npy=True),
              help="known true value, KEY=v1,v2,... or KEY=@values.npy: each iteration "
                   "records the error (RMSE, PSNR; 'matopt job history' shows it)")
@click.option("--image-error-every", type=int,
              help="every N iterations, the image RMSE at higher spp (off the clock)")
@click.option("--from", "from_job", metavar="JOB", type=JOB,
              help="start where JOB's result left the parameters (a restart)")
@click.option("--from-which", type=click.Choice(sorted(WHICH), case_sensitive=False),
              default="best", show_default=True, help="which result of --from")
@click.option("--choice", "choices", multiple=True, metavar="NAME=on|off",
              help="turn one of the engine's choices off (or on), e.g. eta_differences=off; "
                   "multires also takes nearest or linear, optionally :LEVELS (linear:3); "
                   "eta_differences also takes quarter or full (its renders' share of spp), "
                   "optionally :ALPHA (the width below which they apply; quarter:0.05); "
                   "'matopt job status' lists those in force, with why and cost (repeatable)")
@click.option("--preset", type=click.Choice(["plain"]),
              help=f"plain: Mitsuba's plain Adam loop (no engine choices, constant schedule, "
                   f"rate {PLAIN_LEARNING_RATE} for parameters without their own)")
@click.option("--wait", is_flag=True, help="follow the job with a progress bar until it ends")
@json_option
def start(scene: str, refs, masks, fit_exposure: bool, keys, rates, ranges, inits, smooth,
          loss: str | None, schedule: str | None,
          iterations: int | None, spp: int | None, spp_from, large_steps: float | None,
          starts: int | None, min_error: float | None, seed: int | None,
          sensor_mode: str | None, clamp: bool, resolution: int | None, truths,
          image_error_every: int | None, from_job: str | None, from_which: str,
          choices, preset: str | None, wait: bool, as_json: bool) -> None:
    """Start a job on SCENE; prints the job's name.

    The --param keys of SCENE are optimized until its renders match the --ref images. Options
    left out take the daemon's defaults (shown by 'matopt job status'). With --wait,
    the exit status is non-zero if the job fails or is cancelled.

    Photographs: --mask leaves background and blown-out pixels out of the loss, e.g.
    '--ref photo.png --mask photo_mask.png' or '--ref cutout.png --mask @alpha';
    --fit-exposure fits each photograph's exposure and white balance ('matopt job result'
    shows the gains).
    """
    settings = workflow.JobSettings(
        loss=loss, schedule=schedule, sensor_mode=sensor_mode, iterations=iterations, spp=spp,
        min_error=min_error, seed=seed,
        learning_rate=next((rate for key, rate in rates if key is None), None),
        clamp=clamp or None, film_height=resolution, image_error_every=image_error_every,
        fit_exposure=fit_exposure or None, spp_from=dict(spp_from) or None,
        large_steps_lambda=large_steps, starts=starts)
    parameters = parameter_specs(keys, rates, ranges, inits, smooth)
    truth = [pb.ParameterValue(key=t.key, value=t.values, blob=t.npy or "") for t in truths]
    references = reference_files(refs, masks)
    client = connected()
    checked_settings(client, settings)
    spec = workflow.build_spec(scene, parameters, settings, ground_truth=truth)
    for item in choices:
        name, _, value = item.partition("=")
        if not (name and value):
            raise click.BadParameter(f"'{item}' is not NAME=on or NAME=off",
                                     param_hint="--choice")
        spec.choices[name.strip()] = value.strip().lower()
    if preset == "plain":
        if "all" not in spec.choices:
            spec.choices["all"] = "off"
        if schedule is None:
            spec.schedule = pb.SCHEDULE_CONSTANT
        if not spec.HasField("learning_rate"):
            spec.learning_rate = PLAIN_LEARNING_RATE
    upload_values(client, scene, spec.parameters, spec.ground_truth)
    created = workflow.start_job(client, spec, references,
                                 (from_job, WHICH[from_which.lower()]) if from_job else None,
                                 uploading)
    note(f"{created.name}: {workflow.applied(created.spec)}")
    for line in created.notes:  # what the daemon saw fit to say at once: large parameters
        warn(line)
    if as_json and not wait:
        emit_json(created)
    elif not as_json:
        click.echo(created.name)
    if not wait:
        return
    final = wait_with_progress(client, created.name)
    if as_json:
        emit_json(final)
    outcome(final)


def wait_with_progress(client: mc.Client, name: str) -> pb.Job:
    """Follows the job with a progress line on stderr; returns it in its final state."""
    progress = JobProgress()
    try:
        return follow(client, name, progress)
    finally:
        progress.close()


@job.command("list")
@click.option("--state", type=click.Choice(STATES, case_sensitive=False),
              help="only jobs in this state")
@json_option
def list_jobs(state: str | None, as_json: bool) -> None:
    """List your jobs."""
    client = connected()
    request = pb.ListJobsRequest(state=enums.parse(pb.JobState, state) if state else 0)
    jobs = mc.list_all(client.jobs.ListJobs, request, "jobs")
    if as_json:
        emit_json(pb.ListJobsResponse(jobs=jobs))
        return
    table(["NAME", "STATE", "ITERATION", "LOSS", "BEST", "SCENE", "CREATED"],
          [[j.name, mc.state_name(j.state), f"{j.iteration}/{j.spec.iterations}",
            number(j.loss) if j.iteration else "",
            number(j.best_loss) if j.iteration and j.best_iteration >= 0 else "",
            j.spec.scene.removeprefix("scenes/"), timestamp(j.create_time)]
           for j in jobs])


@job.command()
@click.argument("name", metavar="JOB", type=JOB)
@json_option
def status(name: str, as_json: bool) -> None:
    """Show a job's state, progress and settings.

    The settings include the daemon's defaults for whatever the job was started without.
    """
    j = connected().jobs.GetJob(pb.GetJobRequest(name=name))
    if as_json:
        emit_json(j)
        return
    spec = j.spec
    fields({
        "name": j.name,
        "state": workflow.state_text(j),
        "error": j.error or None,
        "scene": spec.scene,
        "iteration": f"{j.iteration}/{spec.iterations}",
        "loss": number(j.loss) if j.iteration else "",
        "best loss": best(j),
        "elapsed": f"{j.elapsed_seconds:.1f} s",
        "parameters": ", ".join(p.key for p in spec.parameters),
        "best result": "values +- standard errors" if j.best_parameters else None,
        **{f"  {p.key}": workflow.verdict(p.value, p) for p in j.best_parameters},
        "references": ", ".join(workflow.reference_label(r)
                                for r in workflow.reference_files(spec.references)),
        "fit exposure": "yes (an RGB gain per reference)" if spec.fit_exposure else None,
        "settings": workflow.applied(spec),
        "integrator": j.integrator + (f" ({j.integrator_reason})" if j.integrator_reason else ""),
        "choices": "\n  ".join(
            f"{c.name}: {'on' if c.on else 'off'}, {c.seconds_per_iteration * 1000:.3g} ms per "
            f"iteration" + (f" (+{c.setup_seconds:.2g} s at start)" if c.setup_seconds >= 0.01
                            else "") + f": {c.why}" for c in j.choices) or None,
        "sensors rendered": workflow.sensor_indices(j.sensors_rendered),
        "skipped steps": j.skipped_steps,
        "clamped components": j.clamped_components,
        "notes": "\n  ".join(j.notes) or None,
        "non-finite gradients": j.nonfinite_gradient_steps,
        "resumed from": j.resumed_from or None,
        "owner": j.owner,
        "created": timestamp(j.create_time),
        "updated": timestamp(j.update_time),
    })


@job.command()
@click.argument("name", metavar="JOB", type=JOB)
@click.option("--which", type=click.Choice(sorted(WHICH), case_sensitive=False), default="best",
              show_default=True, help="the lowest-loss iteration, or the last one")
@click.option("--estimate", is_flag=True,
              help="for a paused job: estimate the standard errors of this iteration now "
                   "(about a tenth of the job's optimizing time on a worker)")
@json_option
def result(name: str, which: str, estimate: bool, as_json: bool) -> None:
    """Show a job's result: its iteration, loss, parameter values and exposure gains.

    Each value comes with its standard error (0.412 +- 0.003: how far the images let it be
    from the truth), one-sided at a bound, or 'not determined by these images' and why
    (then no number: the job's notes say what would decide it); an ended job's come with
    it, a paused job's with --estimate. Values of large parameters (textures, grids) are
    not printed: 'matopt job export' writes them. The gains (with --fit-exposure) are what
    each reference's render was multiplied by.
    """
    client = connected()
    if estimate and not as_json and client.jobs.GetJob(
            pb.GetJobRequest(name=name)).state == pb.JOB_STATE_PAUSED:
        note(f"estimating the standard errors of {name}'s {which.lower()} iteration on a "
             "worker, in turns with the jobs running there (up to a minute or two) ...")
    r = client.jobs.GetJobResult(pb.GetJobResultRequest(
        name=name, which=WHICH[which.lower()], estimate_standard_errors=estimate))
    if as_json:
        emit_json(r)
        return
    rows = {"job": r.job, "which": which.lower(), "iteration": r.iteration,
            "loss": number(r.loss)}
    rows.update({p.key: workflow.verdict(p.value, p) if not p.blob else f"{p.blob} (shape "
                 f"{list(p.shape)})" for p in r.parameters})
    rows.update(workflow.gain_fields(r.gains))
    rows["standard errors"] = "\n  ".join(r.standard_error_notes) or None
    fields(rows)


@job.command("watch")
@click.argument("name", metavar="JOB", type=JOB)
@click.option("--json", "as_json", is_flag=True,
              help="one JSON object per event and line (the JobEvent)")
def watch_job(name: str, as_json: bool) -> None:
    """Print a job's events until it ends.

    One line per event (state changes and iterations). The exit status is non-zero if the job
    fails or is cancelled.
    """
    total, shown = 0, ""

    def show(event: pb.JobEvent) -> None:
        nonlocal total, shown
        if as_json:
            emit_json(event, compact=True)
            return
        if event.HasField("job"):
            total = event.job.spec.iterations
            # The job also comes after each batch of iterations (for its best): a line only
            # when its state, phase or error reads differently from the last one printed.
            changed = describe_state(event.job)
            if changed == shown:
                return
            shown = changed
        click.echo(describe(event, total))

    outcome(follow(connected(), name, show))


def requested(j: pb.Job, target: int) -> str:
    """The state a pause or cancel leads to: ``jobs/x PAUSED``, or while the job finishes
    the iteration under way, ``jobs/x RUNNING, then PAUSED at its next iteration boundary``
    with what the daemon says happens until then."""
    if j.state == target:
        return f"{j.name} {mc.state_name(j.state)}"
    pending = next((n.removeprefix("end phase: ") for n in j.notes
                    if n.startswith("end phase: ")), None)
    return (f"{j.name} {mc.state_name(j.state)}, then {mc.state_name(target)} at its next "
            f"iteration boundary" + (f" ({pending})" if pending else "")
            + f"; 'matopt job watch {j.name}' follows it")


def _control(verb: str, rpc: str, request_type, target: int | None, doc: str) -> None:
    """pause/resume/cancel: the same command shape around a different RPC; ``target``: the
    state the request leads to (None: the state answered is the one it leads to)."""

    @job.command(verb, help=doc)
    @click.argument("name", metavar="JOB", type=JOB)
    @json_option
    def command(name: str, as_json: bool) -> None:
        j = getattr(connected().jobs, rpc)(request_type(name=name))
        if as_json:
            emit_json(j)
        elif target is None or j.state in mc.TERMINAL_STATES - {target}:
            click.echo(f"{j.name} {mc.state_name(j.state)}")
        else:
            click.echo(requested(j, target))


_control("pause", "PauseJob", pb.PauseJobRequest, pb.JOB_STATE_PAUSED,
         "Pause a job (at its next iteration).\n\nPrints the state the job is in and, while "
         "it finishes its iteration, the state it is going to (PAUSED).")
_control("resume", "ResumeJob", pb.ResumeJobRequest, None,
         "Resume a paused or interrupted job.")
_control("cancel", "CancelJob", pb.CancelJobRequest, pb.JOB_STATE_CANCELLED,
         "Cancel a job (at its next iteration).\n\nIts results so far are kept: a running "
         "job stops at its next iteration boundary, then renders its result images (one "
         "sensor at a time, other jobs running in between) and ends CANCELLED. Prints the "
         "state the job is in and, until it ends, what happens next.")


@job.command()
@click.argument("name", metavar="JOB", type=JOB)
@json_option
def delete(name: str, as_json: bool) -> None:
    """Delete a job and its results.

    The images and files of its results stay among your blobs: 'matopt blob rm --unused'
    deletes the blobs no scene or job of yours uses any more.
    """
    connected().jobs.DeleteJob(pb.DeleteJobRequest(name=name))
    deleted([name], as_json)


@job.command()
@click.argument("name", metavar="JOB", type=JOB)
@json_option
def history(name: str, as_json: bool) -> None:
    """Show the loss per iteration.

    With the optimizing time (paused and queued time excluded) at which each was reached and,
    when the job has ground truth (--truth), each parameter's error against it: RMSE, PSNR
    and, for textures and grids, the correlation with the truth per channel.
    """
    response = pb.GetJobHistoryResponse(iterations=mc.job_history(connected(), name))
    if as_json:
        emit_json(response)
        return
    keys = list(dict.fromkeys(e.key for r in response.iterations for e in r.errors))
    table(["ITERATION", "SECONDS", "SPP", "LOSS"] + [f"ERROR {k}" for k in keys],
          [[r.iteration, f"{r.seconds:.2f}", r.spp or "", number(r.loss)]
           + [next((parameter_error(e) for e in r.errors if e.key == k), "") for k in keys]
           for r in response.iterations])


def empty_folder(path: Path, force: bool) -> None:
    """Refuses an --out folder that holds anything (without --force): another job's files
    there would be replaced, or mixed with this one's, without a word."""
    if not force and path.is_dir() and any(path.iterdir()):
        raise click.BadParameter(
            f"folder '{path}' is not empty: its files would be replaced or mixed with this "
            "job's; give a new or empty folder, or --force to write into it", param_hint="--out")


@job.command("export")
@click.argument("name", metavar="JOB", type=JOB)
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="directory to write into (created if needed; must be empty)")
@click.option("--which", type=click.Choice(sorted(WHICH), case_sensitive=False), default="best",
              show_default=True, help="the lowest-loss iteration, or the last one")
@click.option("--force", is_flag=True,
              help="write into a folder that is not empty: files of the same names are "
                   "replaced, the others stay")
@json_option
def export(name: str, out_dir: str, which: str, force: bool, as_json: bool) -> None:
    """Write a job's results to a directory.

    parameters.json (values, initial values, shapes), the initial, optimized and reference
    images of each sensor (PNG and EXR), history.csv, and <key>.npy for large parameters.
    Prints the files written, one per line. A folder that is not empty is refused unless
    --force is given.
    """
    empty_folder(Path(out_dir), force)
    done = export_job(connected(), name, Path(out_dir), which.lower())
    if as_json:
        emit_json({"job": done.result.job or name, "which": which.lower(),
                   "iteration": done.result.iteration, "loss": short_float(done.result.loss),
                   "directory": str(done.directory), "files": [str(p) for p in done.files]})
        return
    for path in done.files:
        click.echo(str(path))
    note(f"{name}: {which} iteration {done.result.iteration}, "
         f"loss {number(done.result.loss)}")


from matopt_client.cli.report import report  # noqa: E402 - a module of its own (plots, matplotlib)

job.add_command(report)
