"""What a worker's engine does once, before its first call: Mitsuba imported on its variant,
its plugins loaded, and one gradient iteration on a tiny scene, so that LLVM or CUDA is
initialised and the kernels every job needs are compiled (or read from the disk cache) before
a user waits on them."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi

from . import scene, variant

CORNELL_BOX = Path(__file__).parent / "cornell_box.xml"


def prepare(variant_name: str, threads: int) -> dict:
    """Sets the variant (``variant_name``, else the best that works), loads the plugins and
    warms the kernels; returns what the daemon shows of the worker."""
    began = time.perf_counter()
    if threads and not variant_name.startswith("cuda"):
        # Never fewer than 2: with a pool of one thread, Mitsuba's OpenEXR reader and
        # writer wait forever. On one core the two take turns.
        dr.set_thread_count(max(2, threads))
    name, device = variant.select(variant_name)
    scene.preload_plugins()
    warm_up()
    return {"variant": name, "device": device, "pid": os.getpid(),
            "host": socket.gethostname(), "threads": threads or dr.thread_count(),
            "seconds": time.perf_counter() - began}


def warm_up() -> None:
    """One gradient iteration on a 16x16 Cornell box."""
    loaded = mi.load_file(str(CORNELL_BOX), resx=16, resy=16)
    params = mi.traverse(loaded)
    key = "red.reflectance.value"
    dr.enable_grad(params[key])
    params.update()
    image = mi.render(loaded, params, spp=1, integrator=mi.load_dict({"type": "prb"}))
    loss = dr.mean(dr.square(image), axis=None)
    dr.backward(loss)
    dr.eval(dr.grad(params[key]))
