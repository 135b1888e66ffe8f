"""Admission control: what a request will cost, estimated before it reaches a worker, and the
limits that keep one user's request from starving everyone else's.

A render call costs its samples (film pixels x samples per pixel): a wavefront renderer's time
and memory both grow with them. A job renders, every iteration, each sensor that has a
reference, at the film size that reference asks for (``engine_api.reference_film``), twice
for ``dual_buffer``, and every ``image_error_every`` iterations once more at
``image_error_spp``; its results render at ``engine_api.result_spp``, which never exceeds the
samples admitted here. RenderScene renders each chosen sensor at its film size. A reference
image costs its decoded size, read from its header before anything decodes it.

Two kinds of refusal:
- INVALID_ARGUMENT for what can never be rendered: a film larger than ``--max-film-side``, a
  render call of 2^32 samples or more (Mitsuba refuses those), an image that is not one;
- RESOURCE_EXHAUSTED for budgets that protect the other users: samples per render call, film
  memory per request, reference size, a user's jobs and scene tasks in flight. Scene tasks
  in flight are the one limit that lifts by itself within seconds (``errors.Busy``): the
  answer says when to come back, and clients retry it; the others are not retried.
Each message names the value, the limit and the ``matoptd`` flag that sets it.
"""

from __future__ import annotations

import collections
import contextlib
import random
import time
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable, Iterator

from matopt_api.costs import format_size

from .. import engine_api as api
from ..engine.losses import LOSSES
from ..errors import Busy, InvalidArgument, ResourceExhausted
from ..settings import JobSettings
from .image_headers import BadHeader, ImageHeader, read_header

MITSUBA_MAX_SAMPLES = 1 << 32  # Mitsuba refuses a render call of this many samples or more
FILM_BYTES_PER_PIXEL = 16      # a film's float32 RGBA


@dataclass(frozen=True)
class Limits:
    """What one request, or one user, may ask of the shared workers. The defaults suit a
    shared workstation: 2^26 samples is 4096x4096 at 4 spp or 1024x1024 at 64 spp."""

    max_samples: int = 1 << 26            # film pixels x spp of one render call
    max_film_side: int = 8192             # pixels, width or height
    max_film_memory: int = 4 << 30        # bytes of all films one request renders
    max_reference_pixels: int = 1 << 26   # of one reference image
    max_reference_memory: int = 2 << 30   # bytes to decode one reference image
    max_jobs_per_user: int = 16           # queued or running
    max_tasks_per_user: int = 4           # scene loads, renders, reference checks in flight

    def __post_init__(self) -> None:
        for f in fields(self):
            if getattr(self, f.name) < 1:
                raise ValueError(f"{flag(f.name)} must be >= 1, got {getattr(self, f.name)}")


def flag(limit: str) -> str:
    """The matoptd flag that sets a limit: max_film_side -> --max-film-side."""
    return "--" + limit.replace("_", "-")


def _over(limit: str, limits: Limits, unit: str = "") -> str:
    return f"the limit is {_n(getattr(limits, limit))}{unit} (matoptd {flag(limit)})"


def _n(value: int) -> str:
    return f"{value:,}"


# -- estimates -------------------------------------------------------------------------------

@dataclass(frozen=True)
class Render:
    """One kind of render call of a request: a sensor at a film size and spp."""

    sensor: int
    width: int
    height: int
    spp: int
    spp_field: str = "spp"   # the request field that sets spp, for messages
    film_from: str = ""      # why the film has this size, for messages
    per_iteration: int = 1   # calls per job iteration (dual_buffer: 2; 0: not every one)

    @property
    def samples(self) -> int:
        return self.width * self.height * self.spp


@dataclass
class Estimate:
    renders: list[Render] = field(default_factory=list)

    @property
    def films(self) -> dict[int, Render]:
        """Each sensor's film (the first render of it says why it has that size)."""
        out: dict[int, Render] = {}
        for r in self.renders:
            out.setdefault(r.sensor, r)
        return out

    @property
    def film_bytes(self) -> int:
        return sum(r.width * r.height * FILM_BYTES_PER_PIXEL for r in self.films.values())

    @property
    def samples_per_iteration(self) -> int:
        return sum(r.samples * r.per_iteration for r in self.renders)

    @property
    def summary(self) -> str:
        """For the log: what the request asks of a worker."""
        films = ", ".join(f"sensor {s} {r.width}x{r.height}" for s, r in self.films.items())
        return (f"{films}; {_n(self.samples_per_iteration)} samples per iteration, largest "
                f"render call {_n(max((r.samples for r in self.renders), default=0))} samples, "
                f"films {format_size(self.film_bytes)}")


def job_estimate(settings: JobSettings, films: dict[int, tuple[int, int]],
                 references: dict[int, ImageHeader]) -> Estimate:
    """The render calls of a job whose settings were validated: ``films`` are the scene's
    sensors' own film sizes, ``references`` the headers of its reference images by sensor."""
    out = Estimate()
    for ref in settings.references:
        header = references[ref.sensor]
        width, height = api.reference_film(settings.film_height or films[ref.sensor][1],
                                           header.width, header.height)
        why = (f"film_height {settings.film_height}" if settings.film_height else
               f"the scene's film height {height}")
        why += f" and reference '{ref.name}' ({header.width}x{header.height} px)"
        spp, field = max([(settings.spp, "spp"), *((n, f"spp_from {i}:{n}")
                                                    for i, n in settings.spp_from.items())])
        out.renders.append(Render(ref.sensor, width, height, spp, field, why,
                                  LOSSES[settings.loss].renders))
        if settings.image_error_every:
            out.renders.append(Render(ref.sensor, width, height, settings.image_error_spp,
                                      "image_error_spp", why, 0))
    return out


def render_estimate(request: api.RenderRequest, films: dict[int, tuple[int, int]]
                    ) -> Estimate:
    """The render calls of RenderScene; sensors that do not exist are left to the engine,
    which names them."""
    chosen = request.sensors or sorted(films)
    return Estimate([Render(s, *films[s], request.spp, "spp", "the scene's film")
                     for s in chosen if s in films])


# -- checks ----------------------------------------------------------------------------------

def check(estimate: Estimate, limits: Limits) -> None:
    """Refuses a request whose renders can never run, or would take more than its share."""
    for r in estimate.films.values():
        if max(r.width, r.height) > limits.max_film_side:
            raise InvalidArgument(
                f"sensor {r.sensor} would render a {r.width}x{r.height} px film (from "
                f"{r.film_from}): at most {_n(limits.max_film_side)} px on a side "
                f"(matoptd {flag('max_film_side')})")
    for r in estimate.renders:
        what = (f"{r.spp_field} {_n(r.spp)} on sensor {r.sensor}'s {r.width}x{r.height} px "
                f"film is {_n(r.samples)} samples in one render call")
        if r.samples >= MITSUBA_MAX_SAMPLES:
            raise InvalidArgument(f"{what}: Mitsuba renders fewer than 2^32 = "
                                  f"{_n(MITSUBA_MAX_SAMPLES)} in one call")
        if r.samples > limits.max_samples:
            raise ResourceExhausted(f"{what}; {_over('max_samples', limits)}: lower "
                                    f"{r.spp_field} or film_height")
    if estimate.film_bytes > limits.max_film_memory:
        raise ResourceExhausted(
            f"the films of {len(estimate.films)} sensor(s) take {format_size(estimate.film_bytes)} "
            f"({_n(estimate.film_bytes)} bytes); {_over('max_film_memory', limits, ' bytes')}")


def reference_header(path: Path, name: str, limits: Limits, role: str = "reference image"
                     ) -> ImageHeader:
    """The header of a reference image (or of its mask: ``role``), refused when it is not an
    image or too large."""
    try:
        with open(path, "rb") as f:
            header = read_header(f, name, role)
    except BadHeader as exc:
        raise InvalidArgument(str(exc)) from None
    what = (f"{role} '{name}' is a {header.width}x{header.height} px "
            f"{header.format} file")
    if header.pixels > limits.max_reference_pixels:
        raise ResourceExhausted(f"{what}: {_n(header.pixels)} px; "
                                f"{_over('max_reference_pixels', limits, ' px')}")
    if header.decoded_bytes > limits.max_reference_memory:
        raise ResourceExhausted(f"{what} of {header.channels} channel(s) that takes "
                                f"{format_size(header.decoded_bytes)} to decode; "
                                f"{_over('max_reference_memory', limits, ' bytes')}")
    return header


def admit_job(settings: JobSettings, films: dict[int, tuple[int, int]],
              blob_file: Callable[[str], Path], limits: Limits) -> Estimate:
    """Reads every reference's header (``blob_file``: digest -> file), and its mask's, which
    must be of the reference's size, and checks the job."""
    headers = {r.sensor: reference_header(blob_file(r.sha256), r.name, limits)
               for r in settings.references}
    for r in settings.references:
        if not r.mask_sha256:
            continue
        mask = reference_header(blob_file(r.mask_sha256), r.mask_name, limits, "mask")
        ref = headers[r.sensor]
        if (mask.width, mask.height) != (ref.width, ref.height):
            raise InvalidArgument(f"mask '{r.mask_name}' is {mask.width}x{mask.height} px, but "
                                  f"its reference image '{r.name}' is {ref.width}x{ref.height} "
                                  "px: a mask must have the reference's size")
    estimate = job_estimate(settings, films, headers)
    check(estimate, limits)
    return estimate


def admit_render(request: api.RenderRequest, films: dict[int, tuple[int, int]],
                 limits: Limits) -> Estimate:
    estimate = render_estimate(request, films)
    check(estimate, limits)
    return estimate


def check_jobs(user: str, active: int, limits: Limits) -> None:
    """``active``: the user's queued and running jobs, before this one."""
    if active >= limits.max_jobs_per_user:
        raise ResourceExhausted(
            f"user '{user}' has {_n(active)} queued or running jobs; "
            f"{_over('max_jobs_per_user', limits)}: wait for one to finish, or pause or "
            "cancel one")


class TaskSlots:
    """Scene tasks in flight per user. A task (a scene load, a render, a reference check)
    goes to a worker before any job's next iteration, so one user's burst of them would hold
    back every job and every other user's task. Over the limit, a request is told to come back
    (``Busy``) after about as long as a task has lately held its slot, spread at random so
    that a burst's retries do not all arrive at once."""

    RETRY_S = (0.5, 30.0)  # the least and the most a caller is told to wait (a first time)

    def __init__(self, limits: Limits, clock: Callable[[], float] = time.monotonic,
                 spread: Callable[[], float] = random.random) -> None:
        self.limits, self.clock, self.spread = limits, clock, spread
        self.held: collections.Counter[str] = collections.Counter()
        self.typical = 1.0  # seconds a task holds its slot (a moving average)

    def retry_after(self) -> float:
        lo, hi = self.RETRY_S
        return min(hi, max(lo, self.typical * (0.5 + self.spread())))

    @contextlib.contextmanager
    def hold(self, user: str) -> Iterator[None]:
        if self.held[user] >= self.limits.max_tasks_per_user:
            wait = self.retry_after()
            raise Busy(
                f"user '{user}' already has {self.held[user]} scene request(s) (CreateScene, "
                f"RenderScene, CreateJob) in progress; {_over('max_tasks_per_user', self.limits)}"
                ": try again in a few seconds (clients retry by themselves)", wait)
        self.held[user] += 1
        began = self.clock()
        try:
            yield
        finally:
            self.typical = 0.7 * self.typical + 0.3 * (self.clock() - began)
            self.held[user] -= 1
            if not self.held[user]:
                del self.held[user]
