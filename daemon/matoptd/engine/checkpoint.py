"""A job's checkpoint: everything needed to continue exactly, on any worker, written and read
by one codec from its declaration (the dataclasses below), so that a field added to the loop
or a choice is a field added here, not a position in an array.

The bytes are an ``.npz``: a JSON manifest of the tree, in which each numpy array stands as
``{"@": n}`` for the array ``a{n}`` beside it (dtypes kept: Adam's step count is uint32, a
path's values float64). Reading follows the dataclasses' type hints. Checkpoints written
before this layout (positional ``meta`` arrays) are read too: a daemon upgraded with paused
jobs resumes them.
"""

from __future__ import annotations

import dataclasses
import io
import json
import re
import types
import typing
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import parameters
from .records import Best, ParamRecord, Progress


@dataclass
class VariableState:
    value: np.ndarray   # u, flat
    t: np.ndarray       # Adam's step count(s)
    m: np.ndarray       # ... first and second moments
    v: np.ndarray
    held: list[int] = field(default_factory=list)


@dataclass
class ChoiceState:
    seconds: float
    setup_seconds: float
    state: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class Checkpoint:
    progress: Progress
    variables: dict[str, VariableState]  # in the loop's order of its records
    choices: dict[str, ChoiceState]


class CheckpointError(ValueError):
    """A checkpoint that does not restore this job (another job's, or damaged)."""


def save(opt, records: dict[str, ParamRecord], choices: list, progress: Progress
         ) -> Checkpoint:
    """The loop's state: Adam's variables and moments by record, each choice's own state and
    cost, and the progress."""
    variables = {}
    for key, r in records.items():
        value, _, _, (t, m, v, _) = opt.state[key]
        variables[key] = VariableState(
            parameters.flat(value), np.asarray(t, dtype=np.uint32),
            np.asarray(m, dtype=np.float32), np.asarray(v, dtype=np.float32), list(r.held))
    return Checkpoint(progress, variables, {
        c.name: ChoiceState(c.seconds, c.setup_seconds,
                            {k: np.asarray(v) for k, v in c.state().items()})
        for c in choices})


def restore(saved: Checkpoint, opt, records: dict[str, ParamRecord], choices: list
            ) -> Progress:
    """Adam and the records as saved (the choices' states came back through their setup);
    each record's ``current`` is the last iteration's value. The progress to go on from."""
    if list(saved.variables) != list(records):
        raise CheckpointError("checkpoint holds other parameters (or exposure gains) than "
                              "the job")
    for c in choices:
        if c.name in saved.choices:
            c.seconds = saved.choices[c.name].seconds
            c.setup_seconds = saved.choices[c.name].setup_seconds
    last = saved.progress.last
    for key, state in saved.variables.items():
        # the variable's layout is the choices' (restored with their state at setup)
        opt[key] = parameters.assign(opt[key], state.value)
        value, promoted, lr, (t, m, v, vmax) = opt.state[key]
        opt.state[key] = (value, promoted, lr,
                          (type(t)(state.t), type(m)(state.m), type(v)(state.v), vmax))
        r = records[key]
        r.held = list(state.held)
        r.current = last.gains.get(r.sensor) if r.is_gain else last.values.get(key)
    return saved.progress


def dumps(checkpoint: Checkpoint) -> bytes:
    arrays: list[np.ndarray] = []

    def put(x: Any) -> Any:
        if isinstance(x, np.ndarray):
            arrays.append(x)
            return {"@": len(arrays) - 1}
        if dataclasses.is_dataclass(x):
            return {f.name: put(getattr(x, f.name)) for f in dataclasses.fields(x)}
        if isinstance(x, dict):
            return {str(k): put(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [put(v) for v in x]
        return x.item() if isinstance(x, np.generic) else x

    manifest = json.dumps(put(checkpoint))
    buf = io.BytesIO()
    np.savez(buf, manifest=np.array(manifest), **{f"a{n}": a for n, a in enumerate(arrays)})
    return buf.getvalue()


def loads(data: bytes) -> Checkpoint:
    try:
        z = np.load(io.BytesIO(data), allow_pickle=False)
        if "manifest" not in z.files:
            return _legacy(z)
        return _decode(Checkpoint, json.loads(str(z["manifest"])), z)
    except CheckpointError:
        raise
    except (ValueError, KeyError, TypeError, OSError) as exc:
        raise CheckpointError(f"not a checkpoint ({exc})") from None


def _decode(hint: Any, v: Any, z) -> Any:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if isinstance(v, dict) and set(v) == {"@"}:
        return z[f"a{v['@']}"]
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        return None if v is None else _decode(inner[0], v, z)
    if origin is list:
        return [_decode(args[0], x, z) for x in v]
    if origin is dict:
        return {args[0](k): _decode(args[1], x, z) for k, x in v.items()}
    if dataclasses.is_dataclass(hint):
        hints = typing.get_type_hints(hint)
        return hint(**{k: _decode(hints[k], x, z) for k, x in v.items() if k in hints})
    if hint in (int, float):
        return hint(v)
    return v


_GAIN = re.compile(r"gain(\d+)$")  # the legacy layout's Adam keys of exposure gains


def _legacy(z) -> Checkpoint:
    """A checkpoint of the positional layout: ``meta`` = (iteration, elapsed, best iteration,
    best loss, non-finite steps, skipped steps, clamped, last iteration, last loss)."""
    keys = [str(k) for k in z["keys"]]
    (it, elapsed, best_it, best_loss, nonfinite, skipped, clamped, last_it,
     last_loss) = z["meta"].tolist()
    variables = {k: VariableState(z[f"value{n}"], z[f"t{n}"], z[f"m{n}"], z[f"v{n}"],
                                  z[f"held{n}"].tolist() if f"held{n}" in z.files else [])
                 for n, k in enumerate(keys)}

    def kept(prefix: str, iteration: float, loss: float) -> Best:
        held = {k: z[f"{prefix}{n}"] for n, k in enumerate(keys) if f"{prefix}{n}" in z.files}
        if not held:
            return Best()
        return Best(int(iteration), float(loss),
                    {k: v for k, v in held.items() if not _GAIN.match(k)},
                    {int(m[1]): v for k, v in held.items() if (m := _GAIN.match(k))})

    choices: dict[str, ChoiceState] = {}
    for name in z.files:
        if name.startswith("cost:"):
            seconds, setup = z[name].tolist()
            choices[name[5:]] = ChoiceState(seconds, setup)
    for name in z.files:
        if name.startswith("choice:"):
            _, choice, part = name.split(":", 2)
            choices.setdefault(choice, ChoiceState(0.0, 0.0)).state[part] = z[name]
    progress = Progress(int(it), float(elapsed), int(nonfinite), int(skipped), int(clamped),
                        z["recent"].tolist(), kept("best", best_it, best_loss),
                        kept("last", last_it, last_loss))
    return Checkpoint(progress, variables, choices)
