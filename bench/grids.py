"""Grids: a medium's extinction grid whose truth lies 50x above a small start, the daemon's
defaults against Mitsuba's plain loop, over 3 seeds.

The scene (procedural): a cube of heterogeneous medium (albedo 0.8, ``scale`` 10) whose
``sigma_t`` is an 8x8x8 grid, seen by 4 cameras at 32x32, lit by a white environment that
the cameras do not see (``hide_emitters``): what they see is the light the medium scatters.
The scene's ``volpath`` at max_depth 6 (the daemon renders prbvolpath with it, and so does
the loop). The truth is a smooth pattern of mean 0.1 (0.05 to 0.15); every run starts at 0.002
everywhere, 60 iterations at 8 spp, references at 128 spp. Three runs per seed:
- ``plain``: bench/plain.py's loop as Mitsuba's volume example runs it: Adam 0.02 on the
  grid's values, constant rate, clipped to [0, 1];
- ``daemon, rate 0.01``: the daemon with the rate its defaults gave such a grid before
  (textures' 0.01; log-space steps, so 1% of the value a step: 50x needs ~390 of them);
- ``daemon``: the daemon's defaults as they are, nothing but the parameter and its start.
Reported per run: the grid's RMSE against the truth and its mean at the end (median and
spread over the seeds). The target: the defaults end with the grid's mean within 10% of the
truth's, and its RMSE no worse than the plain loop's median.
"""

from __future__ import annotations

import time

import numpy as np

import common
import plain
from common import Result, Settings, Target
from matopt_client import client as mc
from matopt_api.v1 import matopt_pb2 as pb
from scenes import cameras, vol

RES, VIEWS, SPP, REF_SPP, ITERATIONS, SEEDS = 32, 4, 8, 128, 60, (0, 1, 2)
START, SIDE = 0.002, 8


def scene_xml() -> str:
    return f"""<scene version="3.0.0">
    <integrator type="volpath"><integer name="max_depth" value="6"/>
        <boolean name="hide_emitters" value="true"/></integrator>
    {cameras(RES, VIEWS)}
    <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
    <shape type="cube" id="box">
        <transform name="to_world"><scale value="0.8"/></transform>
        <bsdf type="null"/>
        <medium type="heterogeneous" name="interior">
            <rgb name="albedo" value="0.8"/>
            <volume type="gridvolume" name="sigma_t">
                <string name="filename" value="sigma.vol"/>
            </volume>
            <float name="scale" value="10"/>
        </medium>
    </shape>
</scene>
"""


def truth_grid() -> np.ndarray:
    z, y, x = np.meshgrid(*(np.linspace(0, np.pi, SIDE),) * 3, indexing="ij")
    return (0.1 + 0.05 * np.sin(x) * np.cos(y) * np.cos(0.5 * z))[..., None].astype(np.float32)


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    client = server.client
    seeds = SEEDS[:1] if settings.quick else SEEDS
    iterations = 15 if settings.quick else ITERATIONS
    folder = settings.work / "grids"
    folder.mkdir(parents=True, exist_ok=True)
    truth = truth_grid()
    (folder / "sigma.vol").write_bytes(vol(truth))
    xml = folder / "grids.xml"
    xml.write_text(scene_xml())
    scene = common.bundle_scene(client, xml)
    key = next(p.key for p in client.scenes.ListSceneParameters(pb.ListSceneParametersRequest(
        name=scene.name)).parameters if p.key.endswith("sigma_t.data"))
    refs = client.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=REF_SPP,
                                                           seed=12345)).images
    paths = {}
    for image in refs:
        paths[image.sensor] = folder / f"ref{image.sensor}.exr"
        mc.download_blob(client, image.exr_blob, paths[image.sensor])
    start = [START] * truth.size
    np.save(folder / "start.npy", np.full(truth.shape, START, np.float32))
    start_blob = f"blobs/{mc.upload_file(client, folder / 'start.npy')}"

    def daemon(seed: int, rate: float | None) -> np.ndarray:
        param = pb.ParameterSpec(key=key, initial_blob=start_blob)
        if rate is not None:
            param.learning_rate = rate
        run_ = common.run_job(client, pb.JobSpec(
            scene=scene.name, iterations=iterations, spp=SPP, min_error=0.0, seed=seed,
            references=[pb.Reference(blob=r.exr_blob, sensor=r.sensor) for r in refs],
            parameters=[param]))
        common.require_success(run_, "grids")
        return common.last_array(client, run_, folder)

    def loop(seed: int) -> np.ndarray:
        its = plain.run(plain.PlainSpec(
            xml, paths[0], {key: start}, iterations, SPP, "prbvolpath", 6, rate=0.02,
            seed=seed, more_references={s: p for s, p in paths.items() if s},
            integrator_props={"hide_emitters": True}), server.variant)
        return np.asarray(its[-1].values[key], np.float32)

    methods = {"plain": loop, "daemon, rate 0.01": lambda s: daemon(s, 0.01),
               "daemon": lambda s: daemon(s, None)}
    rows = []
    for seed in seeds:
        for name, fn in methods.items():
            got = np.asarray(fn(seed), np.float32).ravel()
            rows.append({"seed": seed, "method": name,
                         "rmse": float(np.sqrt(np.mean((got - truth.ravel()) ** 2))),
                         "mean": float(got.mean())})
    csv = common.write_csv(settings.out / "grids.csv", rows)
    of = {name: [r for r in rows if r["method"] == name] for name in methods}
    rmse = {n: [r["rmse"] for r in rs] for n, rs in of.items()}
    mean = {n: [r["mean"] for r in rs] for n, rs in of.items()}
    reached = common.median(mean["daemon"]) / float(truth.mean())
    met = abs(reached - 1) <= 0.1 and common.median(rmse["daemon"]) <= common.median(
        rmse["plain"])
    lines = [f"{len(seeds)} seed(s), {iterations} iterations at {SPP} spp, {VIEWS} views at "
             f"{RES}x{RES}; truth mean {truth.mean():.3f}, start {START}; "
             f"{time.perf_counter() - began:.0f} s", "",
             "| method | grid RMSE at the end | grid mean at the end |", "|---|---|---|"]
    lines += [f"| {n} | {common.spread(rmse[n], '{:.4f}')} | {common.spread(mean[n], '{:.4f}')} |"
              for n in methods]
    return Result("grids", "Grids from far below their truth", [
        Target("a sigma_t grid from 50x below its truth: RMSE at the end, the daemon's "
               "defaults vs the plain loop (median over seeds); its mean / the truth's",
               f"{common.median(rmse['daemon']):.4f} vs {common.median(rmse['plain']):.4f}; "
               f"{reached:.2f} (before: rate 0.01, "
               f"{common.median(mean['daemon, rate 0.01']) / float(truth.mean()):.2f})", met),
    ], lines=lines, files=[csv])

