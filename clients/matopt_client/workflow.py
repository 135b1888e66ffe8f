"""The steps every client takes to run a job, shared by the CLI and the Qt app.

Creating a scene from its main XML, uploading reference images with their masks, reading
``<default>`` overrides typed as ``KEY=VALUE``, building the JobSpec from plain settings, and
the choices the daemon accepts (from its ServerInfo, never from a copy here). Keeping these in
one place means the two clients cannot disagree on what a setting means. ``client.py`` below
it holds the connection and the blob transfers; the clients above it only present.

What is "best" is the daemon's to say (Job.best_iteration, JobResult with WHICH_BEST): the
clients show those fields and never recompute them (for dual_buffer the daemon compares a
windowed mean, not the noisy single losses).
"""

from __future__ import annotations

import math
import os
import re
import uuid
from dataclasses import dataclass, field
from typing import Iterable, Sequence

from matopt_client import client as mc
from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb


# ---------------------------------------------------------------------------------------------
# Choices the daemon announces
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Choices:
    """The names a job setting may take on this daemon ("mse", "cosine", "accumulate")."""

    losses: tuple[str, ...]
    schedules: tuple[str, ...]
    sensor_modes: tuple[str, ...]
    loss_titles: dict[str, str] = field(default_factory=dict)  # the daemon's line per loss


def choices(info: pb.ServerInfo) -> Choices:
    """The daemon's lists, from its GetServerInfo answer.

    A list a daemon leaves empty (one older than the field) falls back to this client's copy
    of the API's enum, which holds what every v1 daemon accepts.
    """
    def names(announced: Sequence[str], enum) -> tuple[str, ...]:
        return tuple(announced) or tuple(enums.short_names(enum))

    return Choices(losses=names(info.losses, pb.Loss),
                   schedules=names(info.schedules, pb.Schedule),
                   sensor_modes=names(info.sensor_modes, pb.SensorMode),
                   loss_titles=dict(info.loss_titles))


def check_choice(setting: str, value: str, allowed: Sequence[str]) -> str:
    """``value`` in lower case if the daemon offers it; ValueError naming the setting, the
    value and the choices otherwise."""
    name = value.strip().lower()
    if name not in allowed:
        raise ValueError(f"unknown {setting} '{value}': this daemon offers "
                         + ", ".join(allowed))
    return name


# ---------------------------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------------------------


_ITEM_START = re.compile(r"\s+|,\s*(?=[A-Za-z_][\w.-]*=)")  # a comma only before the next NAME=


def split_overrides(text: str) -> list[str]:
    """``"resx=64, resy=64 albedo=0.5,0.5,0.5"`` -> the three items: spaces separate items,
    and so does a comma followed by the next ``NAME=`` (a value may hold commas)."""
    return [item for item in _ITEM_START.split(text.strip()) if item]


def parse_overrides(items: Iterable[str]) -> dict[str, str]:
    """``["resx=64", "spp=4"]`` -> {"resx": "64", "spp": "4"}: the scene's XML ``<default>``
    values. ValueError naming the first item that is not ``NAME=VALUE``."""
    out: dict[str, str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ValueError(f"'{item}' is not of the form NAME=VALUE")
        out[name.strip()] = value
    return out


def create_scene(client: mc.Client, main_xml: str | os.PathLike | None,
                 overrides: dict[str, str] | None = None, display_name: str = "",
                 root: str | os.PathLike | None = None,
                 on_upload: mc.UploadProgress | None = None) -> pb.Scene:
    """Uploads the bundle (the files the daemon lacks; none for the built-in Cornell box,
    ``main_xml`` None) and creates the scene.

    A fresh request_id per call lets the daemon recognise a retried request as the same one.
    No deadline: loading a large scene may take minutes.
    """
    overrides = dict(overrides or {})
    request = pb.CreateSceneRequest(overrides=overrides, request_id=str(uuid.uuid4()),
                                    display_name=display_name)
    if main_xml:
        main_file, files = mc.upload_bundle(client, os.fspath(main_xml), overrides, on_upload,
                                            root)
        request.main_file = main_file
        request.files.extend(files)
    return client.scenes.CreateScene(request)


# ---------------------------------------------------------------------------------------------
# References
# ---------------------------------------------------------------------------------------------


@dataclass
class ReferenceFile:
    """A reference image and its mask, each a local file or a blob already on the daemon."""

    image: str  # a local path, or "blobs/<sha256>"
    sensor: int | None = None  # None: the references map to the sensors in order
    mask: str | None = None  # a local path or "blobs/<sha256>" (black = pixel left out)
    alpha_mask: bool = False  # the image's own alpha channel masks it
    filename: str = ""  # shown in messages; default: the local file's name
    mask_filename: str = ""

    @property
    def on_server(self) -> bool:
        return is_blob(self.image)


def is_blob(text: str) -> bool:
    """A blob name rather than a local file (a file of that name wins, as a user means it)."""
    return text.startswith("blobs/") and not os.path.exists(text)


class MissingFile(ValueError):
    """A reference image or mask that is not a file; ``mask`` says which of the two."""

    def __init__(self, path: str, mask: bool) -> None:
        super().__init__(f"{'mask' if mask else 'reference image'} '{path}' is not a file")
        self.path, self.mask = path, mask


def check_reference_files(refs: Sequence[ReferenceFile]) -> None:
    """Every local image and mask exists; MissingFile naming the first that does not,
    before anything is uploaded."""
    for ref in refs:
        for path, mask in ((ref.image, False), (ref.mask, True)):
            if path and not is_blob(path) and not os.path.isfile(path):
                raise MissingFile(path, mask)


def upload_references(client: mc.Client, refs: Sequence[ReferenceFile],
                      on_upload: mc.UploadProgress | None = None) -> list[pb.Reference]:
    """The References for a JobSpec; local images and masks are uploaded together (content
    the daemon has is not sent again), blobs are used as they are."""
    check_reference_files(refs)
    files = [r.image for r in refs] + [r.mask for r in refs if r.mask]
    local = list(dict.fromkeys(f for f in files if not is_blob(f)))
    # Nothing to upload, nothing called: a restart from blobs makes no upload request.
    digests = dict(zip(local, mc.upload_files(client, local, on_upload))) if local else {}

    def blob(path: str, filename: str) -> tuple[str, str]:
        if is_blob(path):
            return path, filename
        return mc.blob_name(digests[path]), filename or os.path.basename(path)

    out = []
    for ref in refs:
        name, filename = blob(ref.image, ref.filename)
        message = pb.Reference(blob=name, filename=filename, alpha_mask=ref.alpha_mask)
        if ref.mask:
            message.mask_blob, message.mask_filename = blob(ref.mask, ref.mask_filename)
        if ref.sensor is not None:
            message.sensor = ref.sensor
        out.append(message)
    return out


def reference_label(ref: ReferenceFile) -> str:
    """``photo.png (mask photo_mask.png)``: a reference's file and what masks it."""
    masks = [f"mask {ref.mask_filename or ref.mask}"] if ref.mask else []
    masks += ["its alpha"] if ref.alpha_mask else []
    return (ref.filename or ref.image) + (f" ({', '.join(masks)})" if masks else "")


def reference_files(references: Iterable[pb.Reference]) -> list[ReferenceFile]:
    """An earlier job's references as blobs on the daemon (a restart uploads nothing)."""
    return [ReferenceFile(image=r.blob, sensor=r.sensor if r.HasField("sensor") else None,
                          mask=r.mask_blob or None, alpha_mask=r.alpha_mask,
                          filename=r.filename, mask_filename=r.mask_filename)
            for r in references]


# ---------------------------------------------------------------------------------------------
# Job specs
# ---------------------------------------------------------------------------------------------


@dataclass
class JobSettings:
    """A job's settings besides scene, parameters and references. None leaves a setting to
    the daemon's default (or to the earlier job's, for a restart), which the Job then shows
    filled in."""

    loss: str | None = None  # a name of Choices.losses
    schedule: str | None = None  # a name of Choices.schedules
    sensor_mode: str | None = None  # a name of Choices.sensor_modes
    iterations: int | None = None
    spp: int | None = None
    min_error: float | None = None
    seed: int | None = None
    learning_rate: float | None = None  # for parameters without their own
    clamp: bool | None = None
    film_height: int | None = None
    image_error_every: int | None = None
    fit_exposure: bool | None = None
    spp_from: dict[int, int] | None = None  # first iteration -> spp from there on
    large_steps_lambda: float | None = None  # LargeSteps for vertex positions
    starts: int | None = None  # starts compared by short probes (1: the given one only)


def build_spec(scene: str, parameters: Sequence[pb.ParameterSpec], settings: JobSettings,
               references: Sequence[pb.Reference] = (),
               ground_truth: Sequence[pb.ParameterValue] = (),
               base: pb.JobSpec | None = None) -> pb.JobSpec:
    """The JobSpec of the given settings; what is None stays unset for the daemon to fill.

    ``base`` (an earlier job's spec, for a restart) supplies what the settings leave out, so
    a restart keeps e.g. its seed; its parameters and references are replaced. ValueError
    names an unknown loss, schedule or sensor mode with the choices.
    """
    spec = pb.JobSpec()
    if base is not None:
        spec.CopyFrom(base)
        spec.ClearField("parameters")
        spec.ClearField("references")
    spec.scene = scene
    spec.parameters.extend(parameters)
    spec.references.extend(references)
    if ground_truth:
        del spec.ground_truth[:]
        spec.ground_truth.extend(ground_truth)
    s = settings
    enums_given = {"loss": (pb.Loss, s.loss), "schedule": (pb.Schedule, s.schedule),
                   "sensor_mode": (pb.SensorMode, s.sensor_mode)}
    for name, (enum, value) in enums_given.items():
        if value is not None:
            setattr(spec, name, enums.parse(enum, value))
    plain = {"iterations": s.iterations, "spp": s.spp, "min_error": s.min_error,
             "seed": s.seed, "learning_rate": s.learning_rate, "clamp": s.clamp,
             "film_height": s.film_height, "image_error_every": s.image_error_every,
             "fit_exposure": s.fit_exposure, "large_steps_lambda": s.large_steps_lambda,
             "starts": s.starts}
    for name, value in plain.items():
        if value is not None:
            setattr(spec, name, value)
    if s.spp_from is not None:
        spec.spp_from.clear()
        spec.spp_from.update(s.spp_from)
    return spec


def choice_name(enum, value: int) -> str | None:
    """``dual_buffer`` for LOSS_DUAL_BUFFER, as ``--loss`` and ServerInfo spell it; None for
    a value left unset."""
    return enums.short_name(enum, value).lower() if value else None


def settings_of(spec: pb.JobSpec) -> JobSettings:
    """The settings of a (filled-in) spec: what a client shows of an earlier job."""
    def optional(name: str):
        return getattr(spec, name) if spec.HasField(name) else None

    return JobSettings(
        loss=choice_name(pb.Loss, spec.loss), schedule=choice_name(pb.Schedule, spec.schedule),
        sensor_mode=choice_name(pb.SensorMode, spec.sensor_mode),
        iterations=optional("iterations"), spp=optional("spp"),
        min_error=optional("min_error"), seed=spec.seed or None,
        learning_rate=optional("learning_rate"), clamp=spec.clamp,
        film_height=spec.film_height or None, image_error_every=spec.image_error_every or None,
        fit_exposure=spec.fit_exposure, spp_from=dict(sorted(spec.spp_from.items())) or None,
        large_steps_lambda=spec.large_steps_lambda or None, starts=optional("starts"))


def applied(spec: pb.JobSpec) -> str:
    """The settings a job runs with, as the daemon filled them in (Job.spec), in one line:
    ``loss mse, schedule cosine, 100 iterations at 16 spp, min error 0, seed 0``. The
    daemon's answer is where a client learns its defaults; none are kept here."""
    s = settings_of(spec)
    words = [f"{name.replace('_', ' ')} {value}" for name, value in
             (("loss", s.loss), ("schedule", s.schedule), ("sensors", s.sensor_mode))
             if value]
    if s.iterations is not None:
        words.append(f"{s.iterations} iterations" + (f" at {s.spp} spp" if s.spp else "")
                     + "".join(f", {n} spp from iteration {i}"
                               for i, n in (s.spp_from or {}).items()))
    if s.min_error is not None:
        words.append(f"min error {number(s.min_error)}")
    if s.learning_rate is not None:
        words.append(f"learning rate {number(s.learning_rate)}")
    words += [f"seed {spec.seed}"] + (["clamped to [0, 1]"] if s.clamp else []) \
        + ([f"film height {s.film_height} px"] if s.film_height else []) \
        + (["exposure fitted"] if s.fit_exposure else []) \
        + ([f"large steps, lambda {number(s.large_steps_lambda)}"] if s.large_steps_lambda
           else []) \
        + ([f"{s.starts} starts compared"] if s.starts and s.starts > 1 else [])
    return ", ".join(words)


def start_job(client: mc.Client, spec: pb.JobSpec, refs: Sequence[ReferenceFile],
              initial_from: tuple[str, int] | None = None,
              on_upload: mc.UploadProgress | None = None,
              timeout: float | None = None) -> pb.Job:
    """Uploads the references into ``spec`` and creates the job.

    ``initial_from`` (job name, pb.Which) starts the parameters the spec gives no start value
    where that job's result left them (large ones included, without an upload).
    """
    spec.references.extend(upload_references(client, refs, on_upload))
    request = pb.CreateJobRequest(spec=spec, request_id=str(uuid.uuid4()))
    if initial_from is not None:
        request.initial_from_job, request.initial_from_which = initial_from
    return client.jobs.CreateJob(request, timeout=timeout)


# ---------------------------------------------------------------------------------------------
# Progress
# ---------------------------------------------------------------------------------------------


def best(job: pb.Job) -> tuple[int, float] | None:
    """(iteration, loss) of the job's best iteration as the daemon reports it; None before
    the first."""
    if job.iteration <= 0 or job.best_iteration < 0:
        return None
    return job.best_iteration, job.best_loss


# Job.stop_reason in words, where the state does not already say it ("SUCCEEDED after 30
# iterations", "CANCELLED").
STOP_REASONS = {"iterations": "", "cancelled": "", "failed": "",
                "min_error": "the loss fell below min error"}


def stop_reason(job: pb.Job) -> str:
    """Why a job ended, in words; "" where its state and iteration count say it all."""
    return STOP_REASONS.get(job.stop_reason, job.stop_reason)


def state_text(job: pb.Job) -> str:
    """``SUCCEEDED (the loss fell below min error)``: the state, with why it ended."""
    reason = stop_reason(job)
    return mc.state_name(job.state) + (f" ({reason})" if reason else "")


def sensor_indices(indices: Iterable[int]) -> str:
    """``#0, #2``: sensor indices that no one reads as a count ("sensors: 0")."""
    return ", ".join(f"#{i}" for i in indices)


# ---------------------------------------------------------------------------------------------
# Numbers as people read them
# ---------------------------------------------------------------------------------------------


def number(value: float) -> str:
    """A float32 value as people read it: 0.57, 1.2e-05, inf."""
    if math.isnan(value):
        return "nan"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return f"{mc.short_float(value):.6g}"


def floats(values: Iterable[float]) -> str:
    """``0.6, 0.5, 0.4``: a short vector (a parameter's value, a gain) to 4 digits."""
    return ", ".join(f"{v:.4g}" for v in values)


def estimated(values: Sequence[float], errors: Sequence[float] = (),
              intervals: Sequence[int] = (), reasons: Sequence[str] = ()) -> str:
    """``0.412 +- 0.003, 0 (at its bound, +0.02), 0.13 (not determined by these images: why)``:
    values with their verdicts as the result reads them (ParameterValue.interval and
    interval_reason); the values alone when there are none."""
    if not len(errors):
        return floats(values)
    out = []
    for v, e, interval, why in zip(values, errors, list(intervals) or [0] * len(values),
                                   list(reasons) or [""] * len(values)):
        if interval == pb.INTERVAL_NOT_DETERMINED or math.isinf(e):
            out.append(f"{v:.4g} (not determined by these images" + (f": {why})" if why
                                                                     else ")"))
        elif interval == pb.INTERVAL_AT_LOWER_BOUND:
            out.append(f"{v:.4g} (at its bound, +{e:.2g})")
        elif interval == pb.INTERVAL_AT_UPPER_BOUND:
            out.append(f"{v:.4g} (at its bound, -{e:.2g})")
        else:
            out.append(f"{v:.4g} +- {e:.2g}")
    return ", ".join(out)


def parameter_error(e: pb.ParameterError) -> str:
    """A ParameterError as people read it: RMSE, PSNR and, for textures and grids, the
    correlation with the truth per channel ("r 0.98/0.97/0.99")."""
    text = f"rmse {number(e.rmse)}, psnr {e.psnr:.1f} dB" if math.isfinite(e.psnr) else \
        f"rmse {number(e.rmse)}, exact"
    if len(e.correlation):
        text += ", r " + "/".join("nan" if math.isnan(c) else f"{c:.3f}" for c in e.correlation)
    return text


def gain_reference(gain: pb.ReferenceGain) -> str:
    """Which reference a fitted gain is for: its file name, else its sensor (``sensor #1``)."""
    return gain.reference or f"sensor #{gain.sensor}"


def gain_fields(gains: Iterable[pb.ReferenceGain]) -> dict[str, str]:
    """``{"gain of dim.exr": "0.6, 0.5, 0.4"}``: the RGB gain of each reference
    (JobSpec.fit_exposure), render x gain ~ reference."""
    return {f"gain of {gain_reference(g)}": verdict(g.rgb, g) for g in gains}


def verdict(values: Sequence[float], v: pb.ParameterValue | pb.ReferenceGain) -> str:
    """A value's (or gain's) components with their verdicts (``estimated``)."""
    return estimated(values, v.standard_error, v.interval, v.interval_reason)
