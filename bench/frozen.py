"""Frozen iterations: the daemon's iteration with the ``frozen`` choice on (render, loss and
backward pass recorded once with dr.freeze and replayed), with it off, and a plain Mitsuba
loop, at equal work.

The job: overhead's (the Cornell box's red and green walls from grey, MSE, Adam 0.03
constant, 4 spp, prb at the scene's depth 8, the same seeds on all three sides) at 32x32,
64x64 and 128x96. Each size runs three rounds after a warm-up of each side (kernels
compiled); within a round the three sides take turns, their order rotated from round to
round. Per-iteration time is steady state from the daemon's history (iteration 0 out; the
frozen job's second recording, at iteration 1, in). Ratios are per round, then the median.
"""

from __future__ import annotations

import time
import uuid

import common
import plain
from common import Result, Settings, Target
from matopt_api.v1 import matopt_pb2 as pb

SIZES = [(32, 32), (64, 64), (128, 96)]
SPP = 4


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    iterations, rounds = (20, 3) if settings.quick else (50, 3)
    client = server.client
    rows: list[dict] = []
    targets: list[Target] = []
    lines = [f"Cornell box walls from grey, {SPP} spp, {iterations} iterations, Adam 0.03 "
             f"constant, MSE, prb depth 8 on all sides, the same seeds; {rounds} rounds "
             "after a warm-up of each side, order rotated; ms per iteration (median) and "
             "ratios per round (median)."]
    for width, height in SIZES:
        scene = client.scenes.CreateScene(pb.CreateSceneRequest(
            overrides={"resx": str(width), "resy": str(height)}, request_id=str(uuid.uuid4())))
        ref_blob, ref_path = common.reference(client, scene, 64, settings.work)
        baseline = plain.PlainSpec(common.CORNELL_XML, ref_path,
                                   {k: common.GREY for k in common.WALLS}, iterations, SPP,
                                   "prb", 8, overrides={"resx": str(width), "resy": str(height)})
        times: dict[str, list[float]] = {"frozen": [], "unfrozen": [], "plain": []}
        losses: dict[str, list[float]] = {"frozen": [], "unfrozen": [], "plain": []}

        def job(frozen: str, r: int) -> None:
            spec = common.wall_spec(scene, ref_blob, iterations=iterations, spp=SPP, seed=0)
            spec.choices["frozen"] = frozen
            done = common.run_job(client, spec, server=server)
            common.require_success(done, "frozen")
            method = "frozen" if frozen == "on" else "unfrozen"
            record(method, r, common.per_iteration(done.seconds), done.history[-1].loss)

        def loop(r: int) -> None:
            its = plain.run(baseline, server.variant)
            record("plain", r, common.per_iteration([it.seconds for it in its]), its[-1].loss)

        def record(method: str, r: int, seconds: float, loss: float) -> None:
            rows.append({"size": f"{width}x{height}", "round": r, "method": method,
                         "seconds_per_iteration": seconds, "loss_last": loss})
            if r >= 0:
                times[method].append(seconds)
                losses[method].append(loss)

        sides = [lambda r: job("on", r), lambda r: job("off", r), loop]
        for side in sides:
            side(-1)  # warm-up
        for r in range(rounds):
            for side in sides[r % 3:] + sides[:r % 3]:
                side(r)
        frozen_plain = common.median([f / p for f, p in zip(times["frozen"], times["plain"])])
        unfrozen_plain = common.median([u / p for u, p in zip(times["unfrozen"],
                                                               times["plain"])])
        frozen_unfrozen = common.median([f / u for f, u in zip(times["frozen"],
                                                               times["unfrozen"])])
        same = all(abs(a - b) <= 1e-4 * abs(b) for a, b in zip(losses["frozen"],
                                                               losses["unfrozen"]))
        targets.append(Target(f"{width}x{height}: frozen / plain loop", f"{frozen_plain:.2f} "
                              f"(unfrozen / plain {unfrozen_plain:.2f}, frozen / unfrozen "
                              f"{frozen_unfrozen:.2f})", frozen_plain < 1.0))
        ms = {m: common.median(t) * 1000 for m, t in times.items()}
        lines.append(f"- {width}x{height}: frozen {ms['frozen']:.1f} ms, unfrozen "
                     f"{ms['unfrozen']:.1f} ms, plain loop {ms['plain']:.1f} ms per iteration; "
                     f"frozen / plain {frozen_plain:.2f}, unfrozen / plain {unfrozen_plain:.2f}, "
                     f"frozen / unfrozen {frozen_unfrozen:.2f}; last losses frozen = unfrozen: "
                     f"{'yes' if same else 'no'}")
    csv = common.write_csv(settings.out / "frozen.csv", rows)
    return Result("frozen", "Frozen iterations against unfrozen and a plain loop", targets,
                  lines, [csv], time.perf_counter() - began)
