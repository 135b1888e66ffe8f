"""The baseline: a plain Mitsuba script, the loop of Mitsuba's own inverse-rendering tutorial.

    scene = mi.load_file(xml, **overrides); params = mi.traverse(scene); params.keep(keys)
    opt = mi.ad.Adam(lr=0.03); opt[key] = start; params.update(opt)
    for i in range(n):
        image = mi.render(scene, params, spp=spp, seed=i, integrator=integrator)
        loss = mean((image - reference)^2)           # MSE
        record loss and parameter values             # the tutorial prints both
        dr.backward(loss); opt.step(); opt[key] = dr.clip(opt[key], lo, hi); params.update(opt)

The one change from the tutorial: the integrator is the daemon's choice for the same scene
(``prb`` or ``prbvolpath`` with the scene's max_depth) instead of the scene's ``path``, so both
sides render the same way and the comparison measures the daemon, not the integrator; with
``integrator=""`` the script renders with the scene's own, as it stands (bench/real_scenes.py
sets it through the scene's ``$integrator`` default, as a user of the thesis's scenes would).

Also a script: ``python bench/plain.py --first-iteration ...`` is a fresh process that imports
Mitsuba, sets the variant, loads the scene and runs one iteration, printing when each part
ended, for the warm-start case; it imports nothing but Mitsuba, as a user's script would.
``python bench/plain.py --loop SPEC.json`` runs the loop for each of the spec's seeds and
prints, per seed, a JSON line with theta_i of every iteration (tests/test_conformance.py
compares a job of the daemon's ``plain`` preset with it, in a process of its own).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field
from pathlib import Path


# A daemon job of seed s renders iteration i with seed s * DAEMON_SEED_STRIDE + i (one sensor;
# daemon/matoptd/engine/renders.py): the loop given that seed draws the same samples.
DAEMON_SEED_STRIDE = 1_000_003


@dataclass
class PlainSpec:
    xml: Path
    reference: Path                          # linear EXR of sensor 0
    start: dict[str, list[float]]            # key -> initial flat value
    iterations: int
    spp: int
    integrator: str = "prb"         # "": the scene's own (a user's script as it stands)
    max_depth: int = 8
    overrides: dict[str, str] = field(default_factory=dict)
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)  # default [0, 1]
    rates: dict[str, float] = field(default_factory=dict)                 # default: rate
    rate: float = 0.03
    seed: int = 0
    # further sensors' references (sensor index -> linear EXR): the loss is the mean over all
    more_references: dict[int, Path] = field(default_factory=dict)
    seconds: float = 0.0  # > 0: stop after the iteration that reaches this time
    integrator_props: dict[str, object] = field(default_factory=dict)  # e.g. hide_emitters


@dataclass
class PlainIteration:
    iteration: int
    seconds: float                 # since the loop began, scene loading included
    cpu: float                     # CPU seconds of this process (all threads), likewise
    loss: float
    values: dict[str, list[float]]  # theta_i: the values that produced ``loss``


def mitsuba(variant: str):
    """Mitsuba with the daemon's variant (so a GPU daemon is compared with a GPU script).

    Dr.Jit reads DRJIT_LIBLLVM_PATH when first imported; the daemon points it at a libLLVM
    >= 16, and so must the script, or it may abort on LLVM 14/15.
    """
    import os
    if "DRJIT_LIBLLVM_PATH" not in os.environ and variant.startswith("llvm"):
        from matoptd.workers.devices import find_libllvm
        found = find_libllvm()
        if found:
            os.environ["DRJIT_LIBLLVM_PATH"] = found
    import mitsuba as mi
    mi.set_variant(variant)
    return mi


def read_references(mi, paths: dict[int, Path]) -> dict:
    """Each sensor's reference as a loop compares renders with it: the EXR's RGB."""
    import numpy as np
    return {s: mi.TensorXf(np.array(mi.Bitmap(str(p)), dtype=np.float32)[..., :3])
            for s, p in paths.items()}


def iterations(count: int, began: float, seconds: float = 0.0, cap: int = 10):
    """0, 1, ...: ``count`` iterations; with ``seconds``, as many as begin within that time
    of ``began`` (at most ``cap`` times ``count``), for a loop run at equal time."""
    for it in range(count * cap if seconds else count):
        if seconds and time.perf_counter() - began >= seconds:
            return
        yield it


def run(spec: PlainSpec, variant: str) -> list[PlainIteration]:
    """The tutorial loop; the clock starts before the scene is loaded, as the daemon's does."""
    mi = mitsuba(variant)
    import drjit as dr
    import numpy as np

    began, cpu = time.perf_counter(), time.process_time()
    scene = mi.load_file(str(spec.xml), **spec.overrides)
    integrator = (mi.load_dict({"type": spec.integrator, "max_depth": spec.max_depth,
                                **spec.integrator_props})
                  if spec.integrator else scene.integrator())
    references = read_references(mi, {0: spec.reference, **spec.more_references})
    params = mi.traverse(scene)
    params.keep(list(spec.start))
    opt = mi.ad.Adam(lr=spec.rate)
    for key, start in spec.start.items():
        if dr.is_tensor_v(params[key]):  # a texture or grid: its shape, from a flat start
            opt[key] = type(params[key])(np.asarray(start, np.float32).reshape(params[key].shape))
        else:
            opt[key] = dr.unravel(type(params[key]), mi.Float(start))
        if key in spec.rates:
            opt.set_learning_rate({key: spec.rates[key]})
    params.update(opt)

    out = []
    for i in range(spec.iterations):
        loss = 0
        for sensor, reference in references.items():
            image = mi.render(scene, params, sensor=sensor, spp=spec.spp,
                              seed=spec.seed + i * len(references) + sensor,
                              integrator=integrator)
            loss += dr.mean(dr.square(image[..., :3] - reference), axis=None)
        loss /= len(references)
        values = {k: np.asarray(dr.ravel(dr.detach(opt[k])), dtype=np.float32).tolist()
                  for k in spec.start}
        loss_value = float(loss.array[0])
        over = spec.seconds > 0 and time.perf_counter() - began >= spec.seconds
        if i + 1 < spec.iterations and not over:  # the daemon, too, takes no step after the last render
            dr.backward(loss)
            opt.step()
            for key in spec.start:
                lo, hi = spec.ranges.get(key, (0.0, 1.0))
                opt[key] = dr.clip(opt[key], lo, hi)
            params.update(opt)
        out.append(PlainIteration(i, time.perf_counter() - began, time.process_time() - cpu,
                                  loss_value, values))
        if over:
            break
    return out


def first_iteration(variant: str, xml: Path, reference: Path, overrides: dict[str, str],
                    keys: list[str], start: list[float], spp: int, integrator: str,
                    max_depth: int) -> dict[str, float]:
    """What a fresh process pays until its first iteration (render, loss, backward, step) has
    ended: wall-clock epochs, so the parent can add the interpreter's own start."""
    t = {"started": time.time()}
    import drjit as dr
    import mitsuba as mi
    t["imported"] = time.time()
    mi.set_variant(variant)
    t["variant_set"] = time.time()
    scene = mi.load_file(str(xml), **overrides)
    integ = mi.load_dict({"type": integrator, "max_depth": max_depth})
    ref = mi.TensorXf(mi.Bitmap(str(reference)))
    params = mi.traverse(scene)
    params.keep(keys)
    t["loaded"] = time.time()
    opt = mi.ad.Adam(lr=0.03)
    for key in keys:
        opt[key] = dr.unravel(type(params[key]), mi.Float(start))
    params.update(opt)
    image = mi.render(scene, params, spp=spp, seed=0, integrator=integ)
    loss = dr.mean(dr.square(image[..., :3] - ref[..., :3]), axis=None)
    float(loss.array[0])
    t["loss_known"] = time.time()
    dr.backward(loss)  # a whole first iteration, as the daemon's iteration 0 of a longer job
    opt.step()
    for key in keys:
        opt[key] = dr.clip(opt[key], 0.0, 1.0)
    params.update(opt)
    # Launched, not waited for: the LLVM backend runs kernels asynchronously, and the daemon
    # too reports an iteration once its loss is known and its step is traced.
    dr.eval(*(opt[key] for key in keys))
    t["first_iteration"] = time.time()
    return t


def loop(path: Path) -> None:
    """The loop for each seed of a JSON spec (PlainSpec's fields, paths as strings, ``seeds``
    and ``variant``); a JSON line per seed: {"seed": s, "values": [theta_0, theta_1, ...]}."""
    spec = json.loads(path.read_text())
    seeds, variant = spec.pop("seeds"), spec.pop("variant")
    spec["xml"], spec["reference"] = Path(spec["xml"]), Path(spec["reference"])
    spec["more_references"] = {int(k): Path(v) for k, v in
                               spec.get("more_references", {}).items()}
    spec["ranges"] = {k: tuple(v) for k, v in spec.get("ranges", {}).items()}
    for seed in seeds:
        its = run(PlainSpec(**{**spec, "seed": seed}), variant)
        print(json.dumps({"seed": seed, "values": [it.values for it in its]}), flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description="fresh-process first iteration (warm_start case), "
                                            "or the plain loop on a spec (--loop)")
    p.add_argument("--loop", type=Path, metavar="SPEC.json")
    p.add_argument("--first-iteration", action="store_true")
    p.add_argument("--variant")
    p.add_argument("--xml", type=Path)
    p.add_argument("--reference", type=Path)
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--key", action="append")
    p.add_argument("--start", type=float, nargs="+")
    p.add_argument("--spp", type=int, default=4)
    p.add_argument("--integrator", default="prb")
    p.add_argument("--max-depth", type=int, default=8)
    a = p.parse_args()
    if a.loop:
        loop(a.loop)
        return
    overrides = dict(s.split("=", 1) for s in a.set)
    print(json.dumps(first_iteration(a.variant, a.xml, a.reference, overrides, a.key, a.start,
                                     a.spp, a.integrator, a.max_depth)))


if __name__ == "__main__":
    main()
