"""Exporting a job's outcome to a directory: parameter values, images and the loss history.

Lives in the library rather than the CLI so that ``matopt job export``, ``matopt demo`` and the
Qt app write the same files, which a user (or a script) can then rely on.
"""

from __future__ import annotations

import csv
import json
import math
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from matopt_client.client import (Client, download_blob, job_history, resource_name, short_float,
                           short_floats)
from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb

WHICH = {"best": pb.WHICH_BEST, "last": pb.WHICH_LAST}

_UNSAFE = re.compile(r"[^A-Za-z0-9._-]")


@dataclass
class Export:
    """What an export wrote, and the result it came from (so callers need not fetch it again)."""

    result: pb.JobResult
    directory: Path
    files: list[Path] = field(default_factory=list)


def image_filename(image: pb.Image, extension: str) -> str:
    """``sensor0_optimized.png``: sensor and role in the name, so a directory sorts by sensor;
    an optimized texture is named after its parameter key."""
    if image.parameter:
        return f"{_UNSAFE.sub('_', image.parameter)}.{extension}"
    role = image.role or "render"
    return f"sensor{image.sensor}_{role}.{extension}"


def write_vol(grid: np.ndarray, path: Path) -> Path:
    """Mitsuba's binary grid format (version 3, float32, X fastest, unit bounding box) of a
    (Z, Y, X, C) array, so that an optimized volume drops into a ``gridvolume``."""
    z, y, x, c = grid.shape
    header = (b"VOL" + bytes([3]) + struct.pack("<iiiii", 1, x, y, z, c)
              + struct.pack("<6f", 0, 0, 0, 1, 1, 1))
    path.write_bytes(header + np.ascontiguousarray(grid, dtype="<f4").tobytes())
    return path


def download_images(client: Client, images, directory: Path) -> list[Path]:
    """The PNG and EXR of every image, named by :func:`image_filename`."""
    written = []
    for image in images:
        for blob, extension in ((image.png_blob, "png"), (image.exr_blob, "exr")):
            if blob:
                path = directory / image_filename(image, extension)
                written.append(download_blob(client, blob, path))
    return written


def _values(client: Client, values, directory: Path, suffix: str,
            written: list[Path]) -> tuple[dict, dict]:
    """Flat value lists by key (or the .npy file name for large ones), and shapes by key."""
    out, shapes = {}, {}
    for v in values:
        if v.blob:
            path = directory / f"{_UNSAFE.sub('_', v.key)}{suffix}.npy"
            written.append(download_blob(client, v.blob, path))
            out[v.key] = path.name
            if len(v.shape) == 4:  # a volume grid: also as .vol
                written.append(write_vol(np.load(path).reshape(list(v.shape)),
                                         path.with_suffix(".vol")))
        else:
            out[v.key] = short_floats(v.value)
            if len(v.value) > 3:  # arrays (vertex colours, small textures) also as .npy
                path = directory / f"{_UNSAFE.sub('_', v.key)}{suffix}.npy"
                values = np.asarray(v.value, dtype=np.float32)
                np.save(path, values.reshape(list(v.shape)) if v.shape else values)
                written.append(path)
        shapes[v.key] = list(v.shape)
    return out, shapes


def _estimated(result: pb.JobResult) -> dict[str, tuple[list, list, list[str], list[str]]]:
    """(values, standard errors, intervals as "two_sided", "at_lower_bound", ..., and why
    each one "not_determined" is: "" for the others) of each value and gain ("gain of
    <reference>") that has a verdict."""
    out = {}
    named = [(v.key, v.value, v) for v in result.parameters] + \
        [(f"gain of {g.reference or f'sensor {g.sensor}'}", g.rgb, g) for g in result.gains]
    for key, values, v in named:
        if len(v.standard_error):
            out[key] = (list(values), list(v.standard_error),
                        [enums.short_name(pb.Interval, i).lower() for i in v.interval],
                        list(v.interval_reason) or [""] * len(v.standard_error))
    return out


def export_job(client: Client, job_name: str, directory: str | Path, which: str = "best") -> Export:
    """Writes parameters.json, the initial/optimized/reference/error images, optimized
    textures, the optimized scene (``scene/``) and history.csv.

    ``parameters.json`` holds flat value lists (shapes apart, under "shapes"), and with
    fit_exposure the RGB gain of each reference (under "gains"); a parameter
    too large to travel inline is written as ``<key>.npy`` (``<key>_initial.npy`` for its
    initial value) and named in the JSON instead of its values. Standard errors, per
    component, are under "standard_errors" (null: not determined) with their "intervals"
    and, for those not determined, why ("reasons"), and in ``parameters.csv`` (parameter,
    component, value, standard_error, interval, reason).
    """
    name = resource_name("jobs", job_name)
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    result = client.jobs.GetJobResult(pb.GetJobResultRequest(name=name, which=WHICH[which]))
    export = Export(result, out)

    parameters, shapes = _values(client, result.parameters, out, "", export.files)
    initial, initial_shapes = _values(client, result.initial_parameters, out, "_initial",
                                      export.files)
    document = {
        "job": result.job or name,
        "which": which,
        "iteration": result.iteration,
        "loss": short_float(result.loss),
        "parameters": parameters,
        "initial": initial,
        "shapes": {**initial_shapes, **shapes},
    }
    if result.gains:  # fit_exposure: render x gain ~ reference, per reference
        document["gains"] = {g.reference or f"sensor {g.sensor}": short_floats(g.rgb)
                             for g in result.gains}
    estimated = _estimated(result)
    if estimated:  # one standard error per component (null: not determined) and its reading
        document["standard_errors"] = {k: [None if math.isinf(e) else short_float(e)
                                           for e in errors] for k, (_, errors, _, _) in
                                       estimated.items()}
        document["intervals"] = {k: readings for k, (_, _, readings, _) in estimated.items()}
        reasons = {k: why for k, (_, _, _, why) in estimated.items() if any(why)}
        if reasons:
            document["reasons"] = reasons
    path = out / "parameters.json"
    path.write_text(json.dumps(document, indent=2) + "\n")
    export.files.append(path)
    if estimated:
        path = out / "parameters.csv"
        with open(path, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["parameter", "component", "value", "standard_error", "interval",
                             "reason"])
            for key, (values, errors, readings, why) in estimated.items():
                for i, row in enumerate(zip(values, errors, readings, why)):
                    writer.writerow([key, i, repr(short_float(row[0])),
                                     repr(short_float(row[1])), row[2], row[3]])
        export.files.append(path)

    export.files += download_images(client, result.images, out)
    # The optimized scene, laid out as its bundle under scene/: load scene/<scene_file>.
    for f in result.scene_files:
        export.files.append(download_blob(client, f"blobs/{f.sha256}", out / "scene" / f.path))

    history = job_history(client, name)
    path = out / "history.csv"
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["iteration", "seconds", "loss"])
        for record in history:
            writer.writerow([record.iteration, f"{record.seconds:.6g}",
                             repr(short_float(record.loss))])
    export.files.append(path)
    return export
