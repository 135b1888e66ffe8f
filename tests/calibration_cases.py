"""Are the standard errors calibrated? Procedural scenes with known truth, one kind of parameter
each (reflectances, a roughness, a dielectric's eta, a medium's albedo and sigma_t, and a
roughness optimized beside a texture, which can take up part of what it shows): per seed,
a reference rendered from the truth with noise of its own, a job started near the truth with
the daemon's defaults, and for each recovered component whether the truth lies within two of
its standard errors (on the open side for one at a bound). Calibrated, that holds about 95% of
the time; asked: 85-99% per kind. ``tests/test_calibration.py`` runs a few seeds,
``bench/calibration.py`` sixty.

Jobs start near the truth (within ``spread``, relative) so that they end converged: the
standard error describes the noise of a converged estimate (and the remaining distance of one
still converging that its gradients show), not a job stopped far from its optimum, which its
notes flag ("still moving").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from matopt_client import client as mc
from matopt_api.v1 import matopt_pb2 as pb

from scenes import create_scene, exr
from stiff import glass, medium_ball, principled_ball

KINDS = ("reflectance", "roughness", "eta", "medium albedo", "sigma_t",
         "roughness beside a texture")


@dataclass
class Case:
    name: str
    xml: str | None                 # None: the built-in Cornell box
    kinds: dict[str, str]           # key -> one of KINDS
    iterations: int = 60
    spp: int = 16
    reference_spp: int = 128
    spread: float = 0.05            # start: truth * e^U(-spread, spread), clipped to the range
    res: int = 32                   # the Cornell box's film (the others' XML has its own)
    files: dict[str, bytes] = field(default_factory=dict)  # beside the XML
    beside: tuple[str, ...] = ()    # optimized too from the scene's values, not judged


def textured_ball(res: int = 32) -> tuple[str, dict[str, bytes]]:
    """A principled ball whose base colour is a 4x4 texture (a brighter and a darker half, so
    that its left-right ramp is not flat), and its roughness; with the files it reads."""
    texels = np.full((4, 4, 3), 0.6, dtype=np.float32)
    texels[:, :2] = (0.7, 0.35, 0.2)
    texels[::2, ::2] *= 0.8
    texture = ('<texture type="bitmap" name="base_color"><string name="filename" '
               'value="albedo.exr"/><string name="filter_type" value="nearest"/></texture>')
    return principled_ball(0.3, res, texture), {"albedo.exr": exr(texels)}


TEXTURED = textured_ball(32)
CASES = [
    Case("Cornell box walls", None, {"red.reflectance.value": "reflectance",
                                     "green.reflectance.value": "reflectance"}),
    Case("principled ball", principled_ball(0.3, 32),
         {"ball.bsdf.base_color.value": "reflectance", "ball.bsdf.roughness.value": "roughness"}),
    Case("rough glass ball", glass(1.5, 0.2, 32), {"ball.bsdf.eta": "eta"}),
    Case("homogeneous medium", medium_ball(1.0, 0.8, 16, 32),
         {"cloud.interior_medium.albedo.value.value": "medium albedo",
          "cloud.interior_medium.sigma_t.value.value": "sigma_t"}),
    Case("textured ball", TEXTURED[0], {"ball.bsdf.roughness.value": "roughness beside a texture"},
         files=TEXTURED[1], beside=("ball.bsdf.base_color.data",)),
]


@dataclass
class Component:
    """One recovered component against its truth."""

    case: str
    kind: str
    key: str
    index: int
    truth: float
    value: float
    error: float            # its standard error
    interval: int           # pb.Interval
    seed: int

    @property
    def z(self) -> float:
        """(value - truth) / standard error."""
        return (self.value - self.truth) / self.error

    @property
    def covered(self) -> bool:
        """The truth within two standard errors; at a bound or floor, anywhere up to two
        standard errors away on the open side or beyond the bound (a roughness at the floor
        it is shown at stands for every smoother one, which looks the same)."""
        d = self.truth - self.value
        if self.interval == pb.INTERVAL_AT_LOWER_BOUND:
            return d <= 2 * self.error
        if self.interval == pb.INTERVAL_AT_UPPER_BOUND:
            return -2 * self.error <= d
        return abs(d) <= 2 * self.error


@dataclass
class Run:
    components: list[Component]
    job: pb.Job
    seconds: float                       # the job's optimizing time


def scene_of(stubs, case: Case) -> pb.Scene:
    if case.xml is None:
        return stubs.scenes.CreateScene(pb.CreateSceneRequest(
            overrides={"resx": str(case.res), "resy": str(case.res)}))
    return create_scene(stubs, {"case.xml": case.xml.encode(), **case.files}, "case.xml")


def run(stubs, case: Case, scene: pb.Scene, seed: int) -> Run:
    """One seed: a reference of its own (RenderScene at reference_spp with this seed), a
    start near the truth, the job, and its LAST result's components against the truth."""
    listed = {p.key: p for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name)).parameters}
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(
        name=scene.name, spp=case.reference_spp, sensors=[0], seed=1000 + seed)).images[0]
    rng = np.random.default_rng(seed)
    spec = pb.JobSpec(scene=scene.name, iterations=case.iterations, spp=case.spp, seed=seed,
                      min_error=0, references=[pb.Reference(blob=ref.exr_blob)])
    for key in case.kinds:
        p = listed[key]
        truth = np.array(p.value)
        start = np.clip(truth * np.exp(rng.uniform(-case.spread, case.spread, truth.size)),
                        p.min, p.max)
        spec.parameters.add(key=key, initial_value=start.tolist())
    for key in case.beside:
        spec.parameters.add(key=key)
    job = mc.wait(stubs, stubs.jobs.CreateJob(pb.CreateJobRequest(spec=spec)).name)
    name = job.name
    if job.state != pb.JOB_STATE_SUCCEEDED:
        raise AssertionError(f"{case.name} seed {seed}: {job.error}")
    result = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=name, which=pb.WHICH_LAST))
    components = []
    for p in (p for p in result.parameters if p.key in case.kinds):
        truth = listed[p.key].value
        for i, (v, e, interval) in enumerate(zip(p.value, p.standard_error, p.interval)):
            components.append(Component(case.name, case.kinds[p.key], p.key, i, truth[i], v, e,
                                        interval, seed))
    return Run(components, job, job.elapsed_seconds)


@dataclass
class Coverage:
    covered: int
    total: int
    rms_z: float            # 1 when calibrated (z = error / standard error)
    undetermined: int

    @property
    def fraction(self) -> float:
        return self.covered / self.total if self.total else math.nan


def coverage(components: list[Component]) -> dict[str, Coverage]:
    """Per kind: how often the truth lay within two standard errors, over the components
    that have one (those not determined are counted apart)."""
    out = {}
    for kind in dict.fromkeys(c.kind for c in components):
        mine = [c for c in components if c.kind == kind and math.isfinite(c.error)]
        z = np.array([c.z for c in mine])
        out[kind] = Coverage(sum(c.covered for c in mine), len(mine),
                             float(np.sqrt(np.mean(z ** 2))) if z.size else math.nan,
                             sum(c.kind == kind and not math.isfinite(c.error)
                                 for c in components))
    return out
