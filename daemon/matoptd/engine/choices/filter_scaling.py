"""A sensor's reconstruction filter scaled with a film that JobSettings.film_height resizes.

A filter's size is in pixels: rendered at half the height of the references' scene, a
Gaussian covers twice the share of the image, renders blur more than the references, and the
loss has a floor no parameter reaches. Each gaussian (stddev) or tent (radius) filter is
scaled by the ratio of the heights (the arithmetic, without Mitsuba: engine/film_filter.py)
and the scene loaded again from its rewritten XML; box filters need nothing, and filters of
fixed size (mitchell, catmullrom, lanczos) get a warning note. This happens at load, before
the loop exists: ``prepare_scene`` is its hook.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import mitsuba as mi

from .. import film_filter
from .base import Choice


@dataclass
class Loading:
    """What preparing a job's scene needs: its main XML (laid out in the worker's cache) and
    a way to load another XML in its place; notes collect what was done."""

    main: Path
    reload: Callable[[Path], mi.Scene]
    notes: list[str] = field(default_factory=list)


class FilterScaling(Choice):
    name = "filter_scaling"

    def prepare_scene(self, loaded: mi.Scene, loading: Loading) -> mi.Scene:
        """The scene again, with the filter of each sensor whose film height the job's
        film_height changes scaled by the same ratio; a filter Mitsuba does not let be sized
        is left as it is, with a note."""
        height = self.settings.film_height
        if not height:
            return loaded
        sizes: dict[str, film_filter.Scaled] = {}
        said = []
        for index in sorted({r.sensor for r in self.settings.references}):
            sensor = loaded.sensors()[index]
            ratio = height / int(sensor.film().crop_size()[1])
            rfilter = sensor.film().rfilter()
            name = str(rfilter).split("[")[0]
            plugin = film_filter.PLUGINS.get(name, name)
            scaled = film_filter.scale(plugin, rfilter.radius(), ratio)
            if ratio == 1 or plugin == "box":  # a box filter is one pixel at any size
                continue
            self.applies = True
            if scaled is None:
                loading.notes.append(
                    f"warning: sensor {index} renders at {ratio:g}x the scene's film height, but "
                    f"its {plugin} reconstruction filter has a fixed radius of "
                    f"{rfilter.radius():g} px, which Mitsuba does not let be scaled: renders "
                    "blur differently from references made at the scene's size; use a gaussian "
                    "or tent filter, or references at this resolution")
            elif self.on:
                sizes[sensor.id()] = scaled
                said.append(f"sensor {index}: {plugin} reconstruction filter {scaled.property} "
                            f"scaled from {scaled.before:g} to {scaled.after:g} px ({ratio:g}x, "
                            "with the film height), so renders blur as at the scene's size")
        self.why = ("; ".join(said) if self.on else
                    "reconstruction filters kept at their size in pixels on resized films")
        loading.notes += said
        if not sizes:
            return loaded
        xml, missing = film_filter.rewrite(loading.main.read_bytes(), sizes)
        for sensor_id in missing:
            loading.notes.append(f"warning: the film of sensor '{sensor_id}' is not written in "
                                 "the main XML, so its reconstruction filter was not scaled "
                                 "with the film")
        if len(missing) == len(sizes):
            return loaded
        path = loading.main.parent / f".filters-{hashlib.sha256(xml).hexdigest()[:16]}.xml"
        if not path.exists():
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".write-")
            with os.fdopen(fd, "wb") as f:
                f.write(xml)
            os.replace(tmp, path)
        del loaded
        return loading.reload(path)

    def setup(self, ctx, records, state) -> None:
        pass  # decided at load (prepare_scene)
