"""Mitsuba's own volume tutorial as a job: the daemon's defaults against the tutorial's loop.

``inverse_rendering/volume_optimization.ipynb`` of mitsuba-tutorials (``--tutorials-repo``, a
checkout; its scenes/volume.vol is read from there, never committed): a cube of heterogeneous
medium (``scale`` 40, albedo 0.75) whose ``sigma_t`` the references take from volume.vol
(44x45x53, mean 0.108), seen by 5 cameras at 64x64 around it under a constant environment,
prbvolpath. The job's scene holds a 16^3 grid of 0.002 in its place. The tutorial's first
stage, the one a user runs first: 20 iterations, each a render at 8 spp, a loss and an Adam
step (0.02, clipped to [1e-6, 1]) per camera in turn. References at 512 spp (the tutorial's).

Per seed, four runs:
- ``tutorial``: the notebook's loop as written (bench process, Mitsuba directly);
- ``daemon, the tutorial's steps``: the job with the tutorial's rate and bound, constant
  rate, every choice off: the daemon doing what the notebook does (conformance);
- ``daemon``: the defaults, given the parameter, its start and the tutorial's camera order
  (``sensor_mode`` step_per_sensor), the same 20 iterations;
- ``tutorial, equal time``: the notebook's loop for as long as the defaults' job optimized.
A medium's renders cost more the denser it gets, so a run that moves the grid toward its
truth pays for it per iteration: equal time is the fair judge. Reported: the grid's RMSE
against the truth resampled to its 16^3 cells, its mean, iterations and seconds (median and
spread over the seeds). Target: the defaults' RMSE no worse than the tutorial's at equal
time.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path

import numpy as np

import common
import plain
from common import Result, Settings, Target
from matopt_api.v1 import matopt_pb2 as pb
from scenes import vol

RES, VIEWS, SPP, REF_SPP, ITERATIONS, SEEDS = 64, 5, 8, 512, 20, (0, 1, 2)
SIDE, START, RATE = 16, 0.002, 0.02
EQUAL_TIME_CAP = 10
KEY = "object.interior_medium.sigma_t.data"
VOLUME = "scenes/volume.vol"
EQUAL_TIME = "tutorial, equal time"


def _sensors() -> str:
    out = []
    for i in range(VIEWS):
        angle = 180.0 / VIEWS * i - 90.0
        out.append(f"""
    <sensor type="perspective"><float name="fov" value="45"/>
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/>
            <rotate y="1" angle="{angle}"/></transform>
        <film type="hdrfilm"><integer name="width" value="{RES}"/>
            <integer name="height" value="{RES}"/><rfilter type="tent"/></film>
    </sensor>""")
    return "".join(out)


def scene_xml(grid: str, reference: bool) -> str:
    """The notebook's scene: the reference's grid rotated and centred as it places volume.vol,
    the job's spanning [-1, 1]^3."""
    place = ('<translate value="-0.5"/><scale value="2"/><rotate x="1" angle="-90"/>'
             if reference else '<scale value="2"/><translate value="-1"/>')
    return f"""<scene version="3.0.0">
    <integrator type="prbvolpath"/>
    {_sensors()}
    <emitter type="constant"/>
    <shape type="cube" id="object">
        <bsdf type="null"/>
        <medium type="heterogeneous" name="interior">
            <volume type="gridvolume" name="sigma_t">
                <string name="filename" value="{grid}"/>
                <transform name="to_world">{place}</transform>
            </volume>
            <float name="scale" value="40"/>
        </medium>
    </shape>
</scene>
"""


def read_vol(path: Path) -> np.ndarray:
    """A .vol grid as a (Z, Y, X, C) array."""
    data = path.read_bytes()
    x, y, z, c = struct.unpack("<iiii", data[8:24])
    return np.frombuffer(data[48:], np.float32).reshape(z, y, x, c)


def truth_cells(volume: np.ndarray) -> np.ndarray:
    """volume.vol resampled (trilinearly) at the centres of the job's 16^3 cells, (Z, Y, X).

    The job's grid maps its unit cube q to w = 2q - 1; the reference's maps p to
    w = R_x(-90)(2p - 1), so p = (q_x, 1 - q_z, q_y)."""
    q = (np.arange(SIDE) + 0.5) / SIDE
    qz, qy, qx = np.meshgrid(q, q, q, indexing="ij")
    p = np.stack([qx, 1 - qz, qy], axis=-1)  # x, y, z in the reference's unit cube
    grid = volume[..., 0]
    shape = np.array(grid.shape[::-1])  # x, y, z resolutions
    f = np.clip(p * shape - 0.5, 0, shape - 1)  # texel centres at (i + 0.5) / n
    i0 = np.floor(f).astype(int)
    i1 = np.minimum(i0 + 1, shape - 1)
    t = f - i0
    out = np.zeros(p.shape[:-1])
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                ix = np.where(dx, i1[..., 0], i0[..., 0])
                iy = np.where(dy, i1[..., 1], i0[..., 1])
                iz = np.where(dz, i1[..., 2], i0[..., 2])
                w = ((t[..., 0] if dx else 1 - t[..., 0]) * (t[..., 1] if dy else 1 - t[..., 1])
                     * (t[..., 2] if dz else 1 - t[..., 2]))
                out += w * grid[iz, iy, ix]
    return out


def tutorial_loop(xml: Path, references: dict[int, Path], seed: int, variant: str,
                  seconds: float = 0.0) -> tuple[np.ndarray, float, int, float]:
    """The notebook's first stage as it is written: a step per camera, clipped; with
    ``seconds``, iterations until that much time has passed (at most EQUAL_TIME_CAP times
    as many). The grid, the seconds taken (scene load in, as a job's), the iterations, and
    the seconds again as its wall (a job's differs: its end comes after its last iteration)."""
    mi = plain.mitsuba(variant)
    import drjit as dr

    began = time.perf_counter()
    scene = mi.load_file(str(xml))
    refs = plain.read_references(mi, references)
    params = mi.traverse(scene)
    opt = mi.ad.Adam(lr=RATE)
    opt[KEY] = params[KEY]
    params.update(opt)
    sensors = scene.sensors()
    done = 0
    for it in plain.iterations(ITERATIONS, began, seconds, EQUAL_TIME_CAP):
        for s in range(VIEWS):
            image = mi.render(scene, params, sensor=sensors[s], spp=SPP, seed=seed * 1000 + it)
            loss = dr.mean(dr.square(image - refs[s]), axis=None)
            dr.backward(loss)
            opt.step()
            opt[KEY] = dr.clip(opt[KEY], 1e-6, 1.0)
            params.update(opt)
        done = it + 1
    grid = np.array(opt[KEY], dtype=np.float32)
    taken = time.perf_counter() - began
    return grid, taken, done, taken


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    repo = settings.tutorials_repo
    if repo is None or not (repo / VOLUME).exists():
        return Result("tutorials", "Mitsuba's volume tutorial", [], lines=[
            f"Skipped: no mitsuba-tutorials checkout with {VOLUME} (`--tutorials-repo DIR`)."])
    client = server.client
    seeds = SEEDS[:1] if settings.quick else SEEDS
    folder = settings.work / "tutorials"
    folder.mkdir(parents=True, exist_ok=True)
    volume = read_vol(repo / VOLUME)
    (folder / "volume.vol").write_bytes((repo / VOLUME).read_bytes())
    (folder / "start.vol").write_bytes(vol(np.full((SIDE,) * 3 + (1,), START, np.float32)))
    (folder / "reference.xml").write_text(scene_xml("volume.vol", True))
    xml = folder / "job.xml"
    xml.write_text(scene_xml("start.vol", False))
    truth = truth_cells(volume)

    refs, paths = common.every_reference(client, folder / "reference.xml", REF_SPP)
    scene = common.bundle_scene(client, xml)

    def daemon(seed: int, preset: bool) -> tuple[np.ndarray, float, int, float]:
        param = pb.ParameterSpec(key=KEY)
        if preset:  # the notebook's steps: its rate and bound
            param.learning_rate, param.max = RATE, 1.0
        spec = pb.JobSpec(scene=scene.name, iterations=ITERATIONS, spp=SPP, min_error=0.0,
                          seed=seed, sensor_mode=pb.SENSOR_MODE_STEP_PER_SENSOR,
                          parameters=[param], references=[
                              pb.Reference(blob=r.exr_blob, sensor=r.sensor) for r in refs])
        if preset:  # ... at a constant rate, no choice
            spec.schedule = pb.SCHEDULE_CONSTANT
            spec.choices.update({"all": "off"})
        done = common.run_job(client, spec)
        common.require_success(done, "tutorials")
        grid = common.last_array(client, done, folder)
        return grid, done.history[-1].seconds, len(done.history), done.wall

    methods = {"tutorial": lambda s: tutorial_loop(xml, paths, s, server.variant),
               "daemon, the tutorial's steps": lambda s: daemon(s, True),
               "daemon": lambda s: daemon(s, False),
               EQUAL_TIME: lambda s: tutorial_loop(xml, paths, s, server.variant,
                                                   rows[-1]["seconds"])}
    rows: list[dict] = []
    for seed in seeds:
        for name, fn in methods.items():
            grid, seconds, iterations, wall = fn(seed)
            got = np.asarray(grid, np.float32).reshape(truth.shape)
            rows.append({"seed": seed, "method": name, "seconds": seconds,
                         "iterations": iterations, "wall": wall,
                         "rmse": float(np.sqrt(np.mean((got - truth) ** 2))),
                         "mean": float(got.mean())})
    csv = common.write_csv(settings.out / "tutorials.csv", rows)
    of = common.by_method(rows, list(methods))
    rmse, mean, seconds, walls, counts = ({n: of[n][k] for n in methods} for k in (
        "rmse", "mean", "seconds", "wall", "iterations"))
    met = common.median(rmse["daemon"]) <= common.median(rmse[EQUAL_TIME])
    lines = [f"{len(seeds)} seed(s), {ITERATIONS} iterations x {VIEWS} cameras at {SPP} spp, "
             f"{RES}x{RES}, a {SIDE}^3 grid from {START}; the truth (volume.vol) resampled to "
             f"the grid's cells: mean {truth.mean():.4f}, RMSE of the start "
             f"{np.sqrt(np.mean((START - truth) ** 2)):.4f}. Seconds: optimizing time (a "
             "job's to its last iteration, the loop's with its scene load); wall: a job's "
             "CreateJob to its end (its standard errors and 64-spp result renders in). "
             f"{time.perf_counter() - began:.0f} s in all.", "",
             "| method | grid RMSE at the end | grid mean at the end | iterations | seconds "
             "| wall |", "|---|---|---|---|---|---|"]
    lines += [f"| {n} | {common.spread(rmse[n], '{:.4f}')} | {common.spread(mean[n], '{:.4f}')} "
              f"| {common.median(counts[n]):.0f} | {common.spread(seconds[n], '{:.1f}')} "
              f"| {common.spread(walls[n], '{:.1f}')} |" for n in methods]
    return Result("tutorials", "Mitsuba's volume tutorial", [
        Target("Mitsuba's volume tutorial (16^3 sigma_t grid from 0.002): RMSE at the end, "
               "the daemon's defaults vs the tutorial's loop at equal time (median over "
               "seeds); the defaults' grid mean / the truth's",
               f"{common.median(rmse['daemon']):.4f} vs {common.median(rmse[EQUAL_TIME]):.4f} "
               f"(the tutorial's 20 iterations: {common.median(rmse['tutorial']):.4f}); "
               f"{common.median(mean['daemon']) / float(truth.mean()):.2f}", met),
    ], lines=lines, files=[csv])
