"""How closely a job's images decide the gated parameters: the floor under defaults_matrix.

A cell of bench/defaults_matrix.py is judged against a gate (Table 2: 1%, Table 4: 2%). Whether
a gate is the optimizer's to meet or beyond what the images say is a question of the images
alone, answered here with Mitsuba and no daemon. At the truth theta*, a least-squares fit to an
image I of S samples per pixel moves by

    d theta = (J^T J)^-1 J^T e,     Cov = (J^T J)^-1 (J^T Sigma_S J) (J^T J)^-1

(e the image's noise, Sigma_S its covariance, J = dI/dtheta): the spread of the best any
estimator minimizing the job's loss can do with those samples, to first order. For a job the
samples are its iterations' (iterations x spp) and the reference's (REF_SPP), whose noise
adds: Sigma = Sigma_1 (1 / (iterations spp) + 1 / REF_SPP) per sample.

J: central differences of renders sharing their samples (the scene's own primal integrator,
STEPS apart), twice with independent samples (A, B); J^T J from the products across the two,
so J's own noise does not inflate it (a product of one estimate with itself came out 3-18 times
larger for sigma_t, alpha and eta at 512 spp). J^T Sigma J: NOISE_RENDERS renders at the job's
spp at the truth, their deviations from their mean projected on both estimates, likewise
across, block by block (BLOCK): the noise correlated within a block, as the scenes' Gaussian
filter makes neighbouring pixels, and not across.
The principled roughness at Table 2's truth shows alpha at its floor (0.001), where the image
does not change with it: it is taken as known.

A job of the daemon or the plain loop never sees J: it steps on back-propagated gradients,
whose noise adds each path's derivative noise to the image's. Per component, the variance of
AD_RENDERS such gradients of sum (I - R)^2 at the truth (the scene's own AD integrator at the
cell's spp; R the mean of the noise renders) over the images' own, 4 J^T Sigma J, says how many
renders' worth of noise one gradient carries; the job's spread with each component's part so
inflated is what a job that steps on them can expect at best. An integrator's detached
derivative (eta near the specular limit) makes its gradient biased too, which this does not
count.

Reported per cell: each gated parameter's spread (one standard deviation, relative to the
truth) from one render and from the job's renders, and the median over Gaussian draws of the
worst gated error of such a fit: the least error a job of the cell's budget can expect, beside
the table's gate and the defaults' median in the matrix (docs/benchmarks.md).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

import common
import plain
import real_scenes as rs
from common import Result, Settings, Target
from defaults_matrix import cells

NEEDS_DAEMON = False
BIAS_RENDERS = 4            # pairs at the cut and the file's own depth, JSPP each, same samples
JSPP = 512                  # samples per pixel of each side of J's differences
NOISE_RENDERS = 48          # renders at the job's spp for J^T Sigma J
AD_RENDERS = 48             # back-propagated gradients at the job's spp for C_g
ITERATIONS = 100            # a job's, as in the matrix
DRAWS = 20_000              # Gaussian draws for the median worst error
# Render noise is correlated within a few pixels (the scenes' Gaussian filter): J^T Sigma J
# is summed over blocks of BLOCK x BLOCK pixels, the noise correlated within them. On Table 2
# at max_depth 8 blocks of 16 agreed with the whole image's projection within 15% (4: 20-25%;
# one pixel alone, Sigma's diagonal: 1.7-5.4 times too little).
BLOCK = 16
# Differences' half steps: wide enough that a path's changed free flights and refractions do
# not bury the difference in noise (sigma_t at 0.008 did, at 0.04 it did not), small enough
# that the image stays linear over them.
STEPS = {"alpha": 0.005, "albedo": 0.01, "sigma_t": 0.04, "eta": 0.01, "base_color": 0.01,
         "spec_trans": 0.01}
PRIMAL = {"prb": "path", "prbvolpath": "volpath"}  # the same image without AD's bookkeeping


def _short(key: str) -> str:
    return key.split(".")[1]


def components(table: rs.Table) -> list[tuple[str, int]]:
    """(key, channel) of every component fitted: the table's truth but a width at its floor."""
    return [(k, c) for k, v in table.truth.items() if not k.endswith("roughness.value")
            for c in range(len(v))]


def show(mi, params, values: dict[str, list[float]]) -> None:
    """Sets the scene's parameters to ``values`` (a scalar, a colour, or eta's plain float)."""
    for key, v in values.items():
        params[key] = (v[0] if key.endswith("eta") else mi.Float(v[0]) if len(v) == 1
                       else mi.Color3f(*v))
    params.update()


class Images:
    """The table's scene at its truth, at one depth, rendered at chosen values and samples."""

    def __init__(self, mi, table: rs.Table, xml: Path, depth: int, film: tuple[int, int]):
        self.mi, self.table = mi, table
        self.xml, self.depth, self.film, self.ad = xml, depth, film, None
        self.scene = mi.load_file(str(xml), integrator=PRIMAL[table.integrator],
                                  max_depth=depth, resx=film[0], resy=film[1])
        self.params = mi.traverse(self.scene)

    def render(self, values: dict[str, list[float]], spp: int, seed: int) -> np.ndarray:
        mi = self.mi
        show(mi, self.params, values)
        return np.array(mi.render(self.scene, spp=spp, seed=seed), dtype=np.float64).ravel()

    def gradients(self, spp: int, reference: np.ndarray, seeds: range) -> np.ndarray:
        """Back-propagated gradients of sum (I - R)^2 at the truth, one row per seed, a
        column per component, from the scene's own AD integrator."""
        import drjit as dr
        mi = self.mi
        if self.ad is None:
            self.ad = self.mi.load_file(str(self.xml), integrator=self.table.integrator,
                                        max_depth=self.depth, resx=self.film[0],
                                        resy=self.film[1])
        params = mi.traverse(self.ad)
        comps = components(self.table)
        keys = list(dict.fromkeys(k for k, _ in comps))
        ref = mi.TensorXf(reference.astype(np.float32).reshape(self.film[1], self.film[0], 3))
        rows = []
        for seed in seeds:
            for key in keys:
                v = self.table.truth[key]
                params[key] = mi.Float(v[0]) if len(v) == 1 else mi.Color3f(*v)
                dr.enable_grad(params[key])
            params.update()
            image = mi.render(self.ad, params, spp=spp, seed=seed)
            dr.backward(dr.sum(dr.square(image - ref), axis=None))
            grads = {k: np.array(dr.ravel(dr.grad(params[k])), np.float64).ravel() for k in keys}
            rows.append([grads[k][c] for k, c in comps])
        return np.array(rows)

    def jacobian(self, seed: int) -> np.ndarray:
        """J's columns by central differences, each pair of sides on the same samples."""
        columns = []
        for i, (key, c) in enumerate(components(self.table)):
            h = STEPS[_short(key)]
            up = {k: list(v) for k, v in self.table.truth.items()}
            down = {k: list(v) for k, v in self.table.truth.items()}
            up[key][c] += h
            down[key][c] -= h
            s = seed + 7 * i
            columns.append((self.render(up, JSPP, s) - self.render(down, JSPP, s)) / (2 * h))
        return np.stack(columns, 1)


def meat(ja: np.ndarray, jb: np.ndarray, noise: np.ndarray, blocks: np.ndarray
         ) -> np.ndarray:
    """J^T Sigma J for one render whose deviations from the mean are the rows of ``noise``,
    summed over ``blocks`` (a block id per pixel-channel), the noise taken as correlated
    within a block and not across: projected on the whole image, the products of J's noise
    with the renders' left its diagonal negative on Table 4 at max_depth 64."""
    out = np.zeros((ja.shape[1], ja.shape[1]))
    for b in np.unique(blocks):
        rows = blocks == b
        ga, gb = noise[:, rows] @ ja[rows], noise[:, rows] @ jb[rows]
        out += 0.5 * (ga.T @ gb + gb.T @ ga) / len(noise)
    return out


def bread(ja: np.ndarray, jb: np.ndarray) -> np.ndarray:
    """J^T J from the products across J's two estimates, so J's own noise does not inflate it."""
    return 0.5 * (ja.T @ jb + jb.T @ ja)


def spread(ja: np.ndarray, jb: np.ndarray, images_meat: np.ndarray) -> np.ndarray:
    """Cov of the least-squares fit to one render, J^T Sigma J given: the sandwich, its
    bread from products across J's two estimates."""
    h = np.linalg.inv(bread(ja, jb))
    return h @ images_meat @ h


def back_propagated(grads: np.ndarray, images_meat: np.ndarray) -> np.ndarray:
    """Per component, the variance of a back-propagated gradient of sum (I - R)^2 (rows of
    ``grads``) over that of the images' own, 4 J^T Sigma J: how many renders' worth of noise
    one such gradient carries."""
    own = 4 * np.diag(images_meat)
    with np.errstate(divide="ignore", invalid="ignore"):  # not settled: nan
        return np.where(own > 0, np.var(grads, axis=0, ddof=1) / own, np.nan)


def _ratio(x: float) -> str:
    return "not settled" if not np.isfinite(x) else f"{x:.1f}x"


def _pct(x: float) -> str:
    return "not settled" if not np.isfinite(x) else f"{100 * x:.2f}%"


def _ad(spread_: float, ratio: float) -> str:
    return ("not settled" if not (np.isfinite(ratio) and np.isfinite(spread_))
            else f"{100 * spread_:.2f}% ({ratio:.1f}x)")


def image_blocks(film: tuple[int, int], size: int = BLOCK) -> np.ndarray:
    """The block id of each pixel-channel of a film's image (rows, then columns, then RGB)."""
    w, h = film
    ids = (np.arange(h)[:, None] // size) * (-(-w // size)) + np.arange(w)[None, :] // size
    return np.repeat(ids.ravel(), 3)


def worst_median(cov: np.ndarray, truth: np.ndarray, gated: np.ndarray, seed: int = 0) -> float:
    """Median over Gaussian draws of the fit of the worst gated parameter's relative error
    (a colour's as defaults_matrix takes it: rms over its channels)."""
    rng = np.random.default_rng(seed)
    w, v = np.linalg.eigh(cov)
    draws = rng.standard_normal((DRAWS, len(w))) @ (v * np.sqrt(np.maximum(w, 0))).T
    errors = []
    for members in gated:
        d, t = draws[:, members], truth[members]
        errors.append(np.sqrt(np.mean(d ** 2, 1)) / np.sqrt(np.mean(t ** 2)))
    return float(np.median(np.max(np.stack(errors, 1), 1)))


def cut_bias(images: Images, whole: Images, ja: np.ndarray, jb: np.ndarray) -> np.ndarray:
    """The fit's bias from rendering at a cut depth against references at the whole depth:
    -(J^T J)^-1 J^T b, b = I_cut - I_whole at the truth. On shared samples the two differ
    only by the paths past the cut, so b is nearly free of noise."""
    truth = images.table.truth
    b = np.mean([images.render(truth, JSPP, 30_000 + i) - whole.render(truth, JSPP, 30_000 + i)
                 for i in range(BIAS_RENDERS)], 0)
    return -np.linalg.solve(bread(ja, jb), 0.5 * (ja + jb).T @ b)


def job_cut(mi, table: rs.Table, xml: Path, spp: int, film: tuple[int, int]) -> int:
    """The depth a job at ``spp`` renders the scene file at: the daemon's ``depth`` choice's
    test with the integrator the daemon chooses and its samples (the scene loaded as the
    matrix's jobs load it), at the file's values (the truth) and at the table's start, the
    larger. So the rows are the job's configuration, not one copied from its notes."""
    import drjit as dr
    from matoptd.engine import integrator  # the engine's own, as a job makes it (variant set)
    from matoptd.engine.choices.depth import larger_cut, least_depth
    scene = mi.load_file(str(xml), integrator=table.integrator, resx=film[0], resy=film[1])
    chosen = integrator.choose(scene, list(table.start))
    params = mi.traverse(scene)
    ones = {0: np.ones((film[1], film[0], 3))}

    def at(values: dict[str, list[float]]):
        def renders(d: int, seed: int) -> dict[int, np.ndarray]:
            show(mi, params, values)
            with dr.suspend_grad():
                image = mi.render(scene, spp=spp, seed=seed,
                                  integrator=integrator.make(chosen, d))
            return {0: np.array(image, np.float32)[..., :3]}
        return lambda least: least_depth(renders, ones, ITERATIONS, table.depth, least)
    return larger_cut(at(table.truth), at(table.start), table.depth)[0]


def measure(mi, table: rs.Table, xml: Path, depth: int, spps: list[int],
            film: tuple[int, int], whole_depth: int | None = None) -> list[dict]:
    """The cell's rows; ``whole_depth``: the scene file's own depth when ``depth`` is its cut."""
    images = Images(mi, table, xml, depth, film)
    comps = components(table)
    truth = np.array([table.truth[k][c] for k, c in comps])
    gated = [np.array([i for i, (k, _) in enumerate(comps) if k == g]) for g in table.targets]
    began = time.perf_counter()
    ja, jb = images.jacobian(1000), images.jacobian(5000)
    j_seconds = time.perf_counter() - began
    bias = (None if whole_depth is None else
            cut_bias(images, Images(mi, table, xml, whole_depth, film), ja, jb))
    rows = []
    for spp in spps:
        renders = np.stack([images.render(table.truth, spp, 90_000 + i)
                            for i in range(NOISE_RENDERS)])
        noise = (renders - renders.mean(0)) * np.sqrt(NOISE_RENDERS / (NOISE_RENDERS - 1))
        m = meat(ja, jb, noise, image_blocks(film))
        one = spread(ja, jb, m)
        # one render's spp samples; the job's ITERATIONS * spp and the reference's add
        job = one * (1 / ITERATIONS + spp / rs.REF_SPP)
        grads = images.gradients(spp, renders.mean(0), range(70_000, 70_000 + AD_RENDERS))
        ratio = back_propagated(grads, m)
        # each component's part of the fit as noisy as its AD gradient (unsettled: nan)
        inflate = np.sqrt(np.maximum(ratio, 1.0))
        ad = inflate[:, None] * one * inflate[None, :] / ITERATIONS + one * spp / rs.REF_SPP
        row = {"table": table.name, "max_depth": depth, "spp": spp, "gate": table.gate,
               "j_seconds": round(j_seconds, 1)}
        for key in dict.fromkeys(k for k, _ in comps):  # every fitted one, gated or not
            members = [i for i, (k, _) in enumerate(comps) if k == key]
            row[f"{_short(key)}, AD / images"] = float(np.mean(ratio[members]))
        for g, members in zip(table.targets, gated):
            scale = np.sqrt(np.mean(truth[members] ** 2))
            for label, cov in (("one render", one), ("job", job), ("job, AD", ad)):
                var = np.diag(cov)[members]  # negative where J^T J did not settle: nan
                row[f"{_short(g)}, {label}"] = (float(np.sqrt(np.mean(var)) / scale)
                                                if np.all(var > 0) else float("nan"))
            if bias is not None:  # rms over a colour's channels, as its spread
                row[f"{_short(g)}, cut bias"] = float(np.sqrt(np.mean(bias[members] ** 2))
                                                        / scale)
        # no worst of the AD part: a gradient that carries no information (eta's) leaves the
        # parameter where its start and its steps' wander do, which no spread describes
        for label, cov in (("one render", one), ("job", job)):
            row[f"worst, {label}"] = worst_median(cov, truth, gated)
        rows.append(row)
        print(f"bench: information {table.name} depth {depth} spp {spp}: "
              + ", ".join(f"{k} {v:.1f}x" if k.endswith("AD / images") else f"{k} {100 * v:.2f}%"
                          for k, v in row.items()
                          if isinstance(v, float) and k not in ("gate", "j_seconds")),
              flush=True)
    return rows


def run(settings: Settings, server: object) -> Result:
    result = Result("information", "What a job's images decide: the floor under the matrix")
    if settings.thesis_repo is None:
        result.targets.append(rs.NO_REPO)
        return result
    variant = settings.variant or "llvm_ad_rgb"
    mi = plain.mitsuba(variant)
    film = settings.film or ((64, 48) if settings.quick else (128, 96))
    chosen = cells(settings)
    rows: list[dict] = []
    cut_lines: list[str] = []
    for name, depth in dict.fromkeys((t.name, d) for t, d, _ in chosen):
        table = next(t for t, _, _ in chosen if t.name == name)
        xml = rs.loadable(settings.thesis_repo / table.path, settings.thesis_repo,
                          settings.work / "information" / f"{table.name}.xml")
        spps = [s for t, d, s in chosen if (t.name, d) == (name, depth)]
        if depth > 0:
            rows += measure(mi, table, xml, depth, spps, film)
            continue
        cuts: dict[int, list[int]] = {}  # the file as it stands, cut as a job at each spp cuts it
        for spp in spps:
            cuts.setdefault(job_cut(mi, table, xml, spp, film), []).append(spp)
        for cut, at in cuts.items():
            rows += measure(mi, table, xml, cut, at, film, table.depth)
            cut_lines.append(f"{table.name}'s file cut to {cut} at spp "
                             f"{', '.join(map(str, at))}")
    result.lines.append(
        f"{variant}, film {film[0]}x{film[1]}; J by central differences at {JSPP} spp a side, "
        f"twice; the noise of {NOISE_RENDERS} renders at each spp at the truth; a job: "
        f"{ITERATIONS} iterations at the cell's spp and a {rs.REF_SPP}-spp reference. "
        "Spread: one standard deviation of the least-squares fit, relative to the truth "
        "(a colour's rms over its channels); worst: the median over draws of the fit of the "
        "worst gated parameter's error, as the matrix takes it. The job's AD gradients: the job's "
        "spread with each component's part as noisy as its back-propagated gradient, whose "
        f"variance over the images' own ({AD_RENDERS} gradients at the truth) is in brackets; "
        "not settled: the images' own variance, or the fit's, came out negative. "
        + ("; ".join(cut_lines) + " (the daemon's `depth` choice's test, least_depth, "
           "with a job's integrator and samples, at the truth and the start)" if cut_lines
           else "No cell at a scene file's own depth")
        + f"; the cut's bias: the fit's, rendering at the cut against references at the file's "
        f"own depth (-(J^T J)^-1 J^T b, b the difference of {BIAS_RENDERS} pairs of renders at "
        "the truth on shared samples); none where the depth is set.")
    result.lines.append("")
    result.lines.append("| table | max_depth | spp | gate | spread, one render | spread, the job's "
                        "renders | worst, one render | worst, the job's renders | spread, the "
                        "job's AD gradients (their variance over the images') | the cut's bias |")
    result.lines.append("|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        table = next(t for t in rs.TABLES if t.name == row["table"])
        names = [_short(g) for g in table.targets]
        ratios = ", ".join(f"{k[:-len(', AD / images')]} {_ratio(v)}" for k, v in row.items()
                           if k.endswith("AD / images"))
        result.lines.append(
            f"| {row['table']} | {row['max_depth']} | {row['spp']} | {100 * row['gate']:.0f}% | "
            + ", ".join(f"{n} {_pct(row[f'{n}, one render'])}" for n in names) + " | "
            + ", ".join(f"{n} {_pct(row[f'{n}, job'])}" for n in names) + " | "
            + f"{100 * row['worst, one render']:.2f}% | {100 * row['worst, job']:.2f}% | "
            + ", ".join(f"{n} {_ad(row[f'{n}, job, AD'], row[f'{n}, AD / images'])}"
                        for n in names) + " | "
            + (", ".join(f"{n} {100 * row[f'{n}, cut bias']:.2f}%" for n in names)
               if f"{names[0]}, cut bias" in row else "none") + " |")
        result.targets.append(Target(
            f"{row['table']} max_depth {row['max_depth']} spp {row['spp']}: the median worst "
            "gated error of a least-squares fit to the job's renders (context: the floor under "
            "the matrix's cell)",
            f"{100 * row['worst, job']:.2f}% (one render's: {100 * row['worst, one render']:.2f}%;"
            f" gate {100 * row['gate']:.0f}%)", None))
        result.targets.append(Target(
            f"{row['table']} max_depth {row['max_depth']} spp {row['spp']}: a back-propagated "
            "gradient's variance over the images' own, per fitted parameter (context: the "
            "renders' worth a job that steps on it loses)", ratios, None))
    result.files.append(common.write_csv(settings.out / "information.csv", rows))
    return result
