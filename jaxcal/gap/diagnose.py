"""`diagnose(robot, data)`: which unmodelled effect causes the sim-to-real gap, where it lies, how far it shrinks.

Method (DESIGN "The sim-to-real gap diagnosis"; issue 7):
1. Baseline: geometry (base set, seed 001 App. III) and device frame fitted by LM on each of k
   training folds and on all data (one vmapped solve; folds keep repeated poses together). Closed
   loops start from the nominal geometry with the device frame registered rigidly onto the readings,
   and their baseline LM stops after CLOSED_BASELINE_STEPS (early stopping: see docs/gap.md).
2. Which: every candidate effect, and every joint-restricted variant of a joint effect, is fitted
   jointly with the geometry by a Gauss-Newton step from each fold's baseline (effects are small
   next to the geometry, so one step is the joint least-squares fit to first order). Columns the
   geometry or device frame absorb exactly (relative norm after projection < 1e-6) are reported
   as not separable. Score = held-out log-likelihood gain n/2 ln(SSE_0/SSE_c) minus the number of
   parameters added; significance by the F-test of the nested fit on all data, Bonferroni over
   candidates; BIC reported too. Greedy forward selection adds effects while one is significant.
3. How far: the selected model is refitted by nonlinear LM on every fold, with a Tikhonov prior
   that holds the geometry and device frame near that fold's baseline (the geometry fitted without
   the effects; mu = PRIOR_MU per typical size, relative to one reading at the baseline RMS), started
   from the Gauss-Newton step of the same regularised objective. A refit that still diverges is
   flagged in `Diagnosis.diverged` and replaced by its baseline (its held-out samples are left out
   of before / after / structure; it never sets the noise floor): non-finite; a parameter leaving the sane box (a link
   moved or turned by more than BOX m or rad from the baseline, a gain off by more than BOX, an
   effect deflecting a joint or the frame by more than BOX rad or m); or an RMS (held-out for a
   fold) more than DIVERGED_RATIO x the baseline's. Then held-out RMS before and after, the noise
   floor (repeated poses, else the residual of the fit with its degrees of freedom) and
   shrink = (before^2 - after^2) / (before^2 - floor^2), the fraction of the gap closed.
4. Verdict: "none" when no candidate is significant and the held-out residual has no structure;
   "unexplained" when structure remains (where.decompose, Bonferroni over features) that the
   selected effects do not capture; else the first selected effect.
"""

from __future__ import annotations

import dataclasses
import json
import time

import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.stats

from jaxcal.fit.base import base_set
from jaxcal.fit.data import Dataset
from jaxcal.gap import fit as gf
from jaxcal.gap import where as wh
from jaxcal.gap.baseline import baseline_fits
from jaxcal.gap.effects import EFFECTS, GLOBAL_EFFECTS, NEEDS, gap_model

SEPARABLE_TOL = 1e-6
MAX_EFFECT_COLUMNS = 18  # effect columns the selected model may add (max_effects x at most 6)
# Refit control (step 3). mu = 1: a departure of one typical size (1 cm, 10 mrad) from the baseline geometry
# costs as much as one reading at the baseline RMS; well-measured directions (curvature >> 1) are not biased,
# directions the training fold leaves nearly free are held at the baseline instead of running off.
# Closed loops get no prior: their base set (pivot tolerance core.BASE_TOL) is the conditioning control, and on the Delta the
# prior kept the geometry from moving with the effect (backlash refit 0.061 mm held out vs 0.039 mm linearised).
PRIOR_MU = 1.0
# Closed loops: the baseline LM stops after this many steps. Beyond ~40 it walked, on the Delta, along weakly
# determined geometric directions into geometries where held-out samples no longer close (5 of 100 blind cases).
CLOSED_BASELINE_STEPS = 40
BOX = 0.1  # sane box of a refit around its baseline or nominal start: 0.1 m or rad of geometry or effect deflection, 10 % of a gain
DIVERGED_RATIO = 3.0  # a refit whose (held-out) RMS exceeds this multiple of the baseline's diverged


@dataclasses.dataclass
class Candidate:
    """One row of the ranking: an effect (restricted to joints) fitted jointly with the geometry."""

    effect: str
    joints: tuple[str, ...]
    heldout_rms_before: float  # mm (position part of the readings)
    heldout_rms_after: float
    score: float
    bic: float
    p_value: float
    n_params: int
    separable: bool = True
    absorbed: tuple[str, ...] = ()  # parameters the geometry / device frame absorb exactly
    note: str = ""
    columns: tuple[int, ...] = dataclasses.field(default=(), repr=False)

    def to_dict(self):
        d = dataclasses.asdict(self)
        d.pop("columns")
        return {k: (v if not isinstance(v, float) or np.isfinite(v) else None) for k, v in d.items()}


@dataclasses.dataclass
class Diagnosis:
    """Outcome of `diagnose`. RMS values are held-out (k-fold) position RMS in mm."""

    robot_name: str
    device_kind: str
    verdict: str
    joints: tuple[str, ...]
    ranking: list
    shrink: float
    where: dict
    heldout_rms_before: float
    heldout_rms_after: float
    noise_floor: float
    noise_source: str
    selected: list  # [(effect, joints)] in the order of the greedy selection
    parameters: dict  # identified effect parameters of the selected model (all data)
    structure_p: float  # p-value of the remaining structure after the selected model (Bonferroni)
    not_candidates: dict  # effect -> why it was not a candidate
    n_samples: int
    folds: int
    timings: dict
    diverged: list = dataclasses.field(default_factory=list)  # [{"fit": "fold b" | "all data", "reason": ...}] refits flagged
    mass_model: str = ""  # masses loading the gravity effects (compliance, link_bending, gravity-load features)
    _plot_data: dict = dataclasses.field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        """JSON-able summary (no arrays)."""
        return json.loads(json.dumps({
            "robot": self.robot_name, "device": self.device_kind, "verdict": self.verdict, "joints": list(self.joints),
            "shrink": self.shrink, "heldout_rms_before_mm": self.heldout_rms_before,
            "heldout_rms_after_mm": self.heldout_rms_after, "noise_floor_mm": self.noise_floor,
            "noise_source": self.noise_source, "structure_p": self.structure_p,
            "selected": [{"effect": e, "joints": list(j)} for e, j in self.selected],
            "parameters": self.parameters, "ranking": [c.to_dict() for c in self.ranking],
            "where": self.where, "not_candidates": self.not_candidates, "n_samples": self.n_samples,
            "folds": self.folds, "timings_s": self.timings, "diverged": self.diverged,
            "mass_model": self.mass_model,
        }, default=float))

    def report(self) -> str:
        lines = [f"gap diagnosis of {self.robot_name} from {self.n_samples} {self.device_kind} samples ({self.folds}-fold held out)"]
        j = f" at {', '.join(self.joints)}" if self.joints else ""
        lines.append(f"verdict: {self.verdict}{j}")
        lines.append(f"held-out RMS {self.heldout_rms_before:.4g} -> {self.heldout_rms_after:.4g} mm, shrink {100 * self.shrink:.1f} %"
                     f" of the held-out mean square; noise floor {self.noise_floor:.4g} mm ({self.noise_source}),"
                     f" remainder {self.heldout_rms_after / max(self.noise_floor, 1e-300):.2f} x floor")
        if self.selected:
            lines.append("selected (greedy): " + "; ".join(f"{e}{'@' + ','.join(js) if js else ''}" for e, js in self.selected))
        lines.append(f"structure left after the selected model: p = {self.structure_p:.3g}")
        for d in self.diverged:
            left = "; its held-out samples are left out of the scores" if d["fit"] != "all data" else ""
            lines.append(f"refit diverged ({d['fit']}): {d['reason']}; replaced by the fit without the effects{left}")
        lines.append("")
        lines.append("which (ranking; linearised joint fits, held-out):")
        lines.append(f"  {'effect':<14}{'joints':<12}{'k':>3}{'RMS before':>12}{'after':>10}{'score':>10}{'BIC':>12}{'p':>10}")
        for c in self.ranking[:15]:
            if not c.separable:
                continue
            lines.append(f"  {c.effect:<14}{','.join(c.joints):<12}{c.n_params:>3}{c.heldout_rms_before:>12.4g}"
                         f"{c.heldout_rms_after:>10.4g}{c.score:>10.1f}{c.bic:>12.1f}{c.p_value:>10.2g}")
        ns = [c for c in self.ranking if not c.separable]
        if ns:
            lines.append("not separable (absorbed exactly by the geometry or the device frame): "
                         + ", ".join(f"{c.effect}{'@' + ','.join(c.joints) if c.joints else ''}" for c in ns))
        part = sorted({a for c in self.ranking if c.separable for a in c.absorbed})
        if part:
            lines.append("absorbed parameters (not separable): " + ", ".join(part))
        for e, why in self.not_candidates.items():
            lines.append(f"not a candidate: {e} ({why})")
        lines.append(f"gravity loads (compliance, link_bending): {self.mass_model}")
        lines.append("")
        axes = ", ".join(f"{k} {v:.4g}" for k, v in self.where["axis_rms"].items())
        lines.append(f"where (baseline held-out residual): RMS per axis {axes}")
        lines.append(f"  {'feature':<40}{'share':>8}{'p':>11}")
        for f in self.where["features"][:10]:
            lines.append(f"  {f['name']:<40}{100 * f['share']:>7.1f}%{f['p_value']:>11.2g}")
        return "\n".join(lines)

    def plot(self, folder) -> list[str]:
        from jaxcal.gap.plots import plot_diagnosis

        return plot_diagnosis(self, folder)


def shrink_fraction(before, after, floor):
    """Fraction of the held-out gap closed: (before^2 - after^2) / (before^2 - floor^2), clipped to [0, 1];
    the gap is the held-out mean square above the noise floor (position RMS values)."""
    gap = before**2 - floor**2
    return float(np.clip((before**2 - after**2) / gap, 0.0, 1.0)) if gap > 0 else 0.0


def _groups(q):
    """Group id of each sample: identical joint readings (repeated poses) share a group."""
    _, inv = np.unique(np.round(q, 9), axis=0, return_inverse=True)
    return inv.reshape(-1)


def _fold_of(groups, k, seed):
    ids = np.random.default_rng(seed).permutation(groups.max() + 1)
    return np.argsort(ids)[groups] % k


def _noise_floor_repeats(data, groups):
    """Position noise RMS (3-D, m) from repeated poses, or None."""
    counts = np.bincount(groups)
    if np.sum(counts[counts >= 2] - 1) < 6:
        return None
    p = data.device.points(data.y)
    ss, dof = 0.0, 0
    for g in np.flatnonzero(counts >= 2):
        pg = p[groups == g]
        ss += np.sum((pg - pg.mean(0)) ** 2)
        dof += len(pg) - 1
    return float(np.sqrt(ss / dof))


def _joint_motion(model, J, q, npad, m):
    """Unit direction (N, m, n) of each joint's motion in the weighted residual space, from the effect
    columns of J: d pred/d q_j = sin q_j J_gear.s1 + cos q_j J_gear.c1 (revolute), J_gain / q_j (prismatic)."""
    n = q.shape[0]
    out = np.zeros((n, m, q.shape[1]))
    for j in range(q.shape[1]):
        if model.revolute[j]:
            s1, c1 = model.index("gear", (j,))[:2]
            col = (np.sin(q[:, j])[:, None] * J[:, s1].reshape(npad, m)[:n] + np.cos(q[:, j])[:, None] * J[:, c1].reshape(npad, m)[:n])
        else:
            g = model.index("encoder_gain", (j,))[0]
            safe = np.where(np.abs(q[:, j]) > 1e-6, q[:, j], np.inf)
            col = J[:, g].reshape(npad, m)[:n] / safe[:, None]
        out[:, :, j] = col / np.maximum(np.linalg.norm(col, axis=1, keepdims=True), 1e-300)
    return out


def _prior_step(J, r, cols, rows, scale, mu):
    """First Gauss-Newton step, in typical sizes z (x = x_ref + scale z), of the refit's objective (fit.solve_folds):
    argmin_z ||r + J_cols (scale z)||^2 / s^2 + sum_i mu_i z_i^2 on the rows `rows`, s^2 their mean square residual."""
    s = max(float(np.sqrt(np.mean(r[rows] ** 2))), 1e-300)
    A = np.vstack([J[np.ix_(rows, cols)] * scale[cols] / s, np.diag(np.sqrt(mu))])
    b = np.concatenate([-r[rows] / s, np.zeros(len(cols))])
    nrm = np.maximum(np.linalg.norm(A, axis=0), 1e-300)
    return np.linalg.lstsq(A / nrm, b, rcond=None)[0] / nrm


def box_limits(model, moment_norm) -> np.ndarray:
    """Largest sane change of each parameter from the baseline: BOX (m, rad, relative) for the geometry and for
    effects that offset a joint or the frame directly; BOX / max |M_j| (kg m) for compliance and bending at joint
    j, so that their deflection c |M_j| stays within BOX rad over the samples."""
    lim = np.full(model.n_params, BOX)
    for i, (effect, j) in enumerate(zip(model.effect_of, model.joint_of)):
        if effect in ("compliance", "link_bending"):
            peak = float(np.max(moment_norm[:, j]))
            lim[model.n_geometry + i] = BOX / peak if peak > 0 else np.inf
    return lim


def _divergence(x_fit, x_base, x_start, r_fit, r_base, rows, cols, limits, names, heldout):
    """Why a refit diverged ("" if it did not): non-finite, a parameter outside its box (`box_limits`) around both
    the baseline and the baseline's start (the nominal model; a refit may undo what the baseline's geometry
    absorbed of a large effect: on the Delta a backlash of 2 mrad moved a link angle 0.13 rad in the baseline,
    and the refit moved it back), or a position RMS on `rows` (held-out, or the fitted samples) above
    DIVERGED_RATIO x the baseline's."""
    after = float(np.sqrt(np.mean(r_fit[rows, :3] ** 2)))
    before = float(np.sqrt(np.mean(r_base[rows, :3] ** 2)))
    if not (np.all(np.isfinite(x_fit)) and np.isfinite(after)):
        return "non-finite parameters or residuals"
    dz = np.minimum(np.abs(x_fit[cols] - x_base[cols]), np.abs(x_fit[cols] - x_start[cols])) / limits[cols]
    if dz.max() > 1.0:
        i = int(np.argmax(dz))
        step = abs(x_fit[cols[i]] - x_base[cols[i]])
        return (f"{names[cols[i]]} moved {step:.3g} from the baseline and {abs(x_fit[cols[i]] - x_start[cols[i]]):.3g} "
                f"from the nominal start (sane box +-{limits[cols[i]]:.3g})")
    if after > DIVERGED_RATIO * before:
        return f"{'held-out' if heldout else 'fit'} RMS {after / before:.3g} x that of the baseline (limit {DIVERGED_RATIO:g})"
    return ""


def _lstsq_step(J, r, cols, rows):
    """Gauss-Newton step on the columns `cols` using the rows `rows`: argmin ||r + J d||."""
    A = J[np.ix_(rows, cols)]
    nrm = np.maximum(np.linalg.norm(A, axis=0), 1e-300)
    d = np.linalg.lstsq(A / nrm, -r[rows], rcond=None)[0] / nrm
    return d


def _lower_cost_start(x_lin, x_base, q, y, cov, w, model):
    """Per fold, the (regularised) Gauss-Newton start where it lowers that fold's training cost, else the
    baseline: on the Delta a Gauss-Newton step along nearly flat geometric directions can land far outside the
    linear range (training cost up 1e4-fold), and the LM may stall there."""
    def cost(x):
        r = np.asarray(gf.residual_batch(jnp.asarray(x), q, y, cov, jnp.ones(w.shape[1:]), model=model))
        return np.sum((r * w) ** 2, axis=(1, 2))

    better = cost(x_lin) <= cost(x_base)
    return np.where(better[:, None], x_lin, x_base)


class _Linear:
    """Linearised joint fits around each fold's baseline: held-out SSE and full-data RSS."""

    def __init__(self, r, J, fold_rows, valid_rows, pos_rows, k):
        self.r, self.J, self.fold_rows, self.valid_rows, self.pos_rows, self.k = r, J, fold_rows, valid_rows, pos_rows, k

    def evaluate(self, cols):
        cols = np.asarray(cols, int)
        sse, sse_pos = 0.0, 0.0
        for b in range(self.k):
            train = self.valid_rows & (self.fold_rows != b)
            test = self.valid_rows & (self.fold_rows == b)
            d = _lstsq_step(self.J[b], self.r[b], cols, np.flatnonzero(train))
            h = self.r[b] + self.J[b][:, cols] @ d
            sse += float(np.sum(h[test] ** 2))
            sse_pos += float(np.sum(h[test & self.pos_rows] ** 2))
        full = np.flatnonzero(self.valid_rows)
        d = _lstsq_step(self.J[self.k], self.r[self.k], cols, full)
        rss = float(np.sum((self.r[self.k] + self.J[self.k][:, cols] @ d)[full] ** 2))
        return sse, sse_pos, rss


def diagnose(robot, data: Dataset, *, folds: int = 5, alpha: float = 0.01, max_effects: int = 3, effects=EFFECTS,
             seed: int = 0, max_steps: int = 200) -> Diagnosis:
    """Diagnose the sim-to-real gap of `robot` on `data` (position or pose device); see the module docstring."""
    t0 = time.perf_counter()
    device = data.device
    if device.marker_reading not in ("point", "frame"):
        raise ValueError(f"gap diagnosis needs a position or pose device, got {device.kind!r}")
    if data.q.shape[1] != robot.n_inputs:
        raise ValueError(f"data has {data.q.shape[1]} joint columns, robot {robot.name!r} has {robot.n_inputs} inputs")
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; expected some of {EFFECTS}")
    model = gap_model(robot, device)
    n = len(data)
    if n < 12:
        raise ValueError(f"gap diagnosis needs at least 12 samples, got {n}")
    C, present = gf.covariate_matrix(model, data.covariates, n)
    m = len(device.residual_components)
    npad = gf.padded_size(n)
    q = np.tile(robot.home_np, (npad, 1))
    q[:n] = data.q
    y = np.repeat(data.y[:1], npad, axis=0)
    y[:n] = data.y
    cov = np.zeros((npad, C.shape[1]))
    cov[:n] = C
    valid = np.zeros(npad, bool)
    valid[:n] = True
    groups = _groups(data.q)
    fold = -np.ones(npad, int)
    fold[:n] = _fold_of(groups, folds, seed)
    pos_comp = np.array([c == "length" for c in device.residual_components])

    comp_sigma = np.where(pos_comp, 1e-3, 1e-3)
    P = model.n_params
    x_nom = model.nominal()
    scale = model.x_scale()
    qj, yj, cj = jnp.asarray(q), jnp.asarray(y), jnp.asarray(cov)

    def fold_weights(sig):
        w = np.zeros((folds + 1, npad, m))
        for b in range(folds + 1):
            use = valid & (fold != b) if b < folds else valid
            w[b] = use[:, None] / sig[None, :]
        return w

    def prior_weights(cols, mu):
        """mu per z column: on geometry and device-frame columns (and the unused padding), not on effects."""
        out = np.full(K_active, mu)
        out[:len(cols)] = np.where(np.asarray(cols) < model.n_geometry, mu, 0.0)
        return out

    def solve(x_refs, cols, sig, z_starts=None, mu=0.0, steps=max_steps):
        S = jnp.asarray(gf.selection(cols, P, scale, K_active))
        z_starts = np.zeros((folds + 1, K_active)) if z_starts is None else z_starts
        args = dict(ref=jnp.asarray(x_refs), w=jnp.asarray(fold_weights(sig)), S=S, mu=jnp.asarray(prior_weights(cols, mu)),
                    q=qj, y=yj, cov=cj)
        xs, ok, n_steps = gf.solve_folds(jnp.asarray(x_refs), jnp.asarray(z_starts), args, model=model, max_steps=steps)
        return np.array(xs), np.asarray(ok), int(np.max(n_steps))

    # 1. Baseline: `identify` on every training fold and on all data (the calibration core).
    base_steps = max_steps if robot.closure is None else min(max_steps, CLOSED_BASELINE_STEPS)
    t_solve = time.perf_counter()
    train = [fold[:n] != b for b in range(folds)] + [np.ones(n, bool)]
    cals = baseline_fits(robot, data, train, sigma_position=comp_sigma[0], sigma_orientation=comp_sigma[-1],
                         max_steps=base_steps)
    ng = model.n_geometry
    xs = np.tile(x_nom, (folds + 1, 1))
    x0s = xs.copy()  # each baseline's start: nominal robot, device frame registered and fitted
    for b, cal in enumerate(cals):
        xs[b, :ng], x0s[b, :ng] = cal.x, cal.x_frames
    ok_base = np.array([c.converged and c.frames_converged for c in cals])
    steps_base = max(c.iterations for c in cals)
    G = cals[folds].estimated
    K_active = gf.active_size(len(G) + MAX_EFFECT_COLUMNS)
    w_all = jnp.asarray(valid[:, None] / comp_sigma[None, :])
    if not pos_comp.all():  # weight position and orientation by their residual RMS at the baseline
        rb = np.asarray(gf.residual_batch(jnp.asarray(xs[folds:]), qj, yj, cj, jnp.ones((npad, m)), model=model))[0][valid]
        comp_sigma = np.where(pos_comp, np.sqrt(np.mean(rb[:, pos_comp] ** 2)), np.sqrt(np.mean(rb[:, ~pos_comp] ** 2)))
        comp_sigma = np.maximum(comp_sigma, 1e-9)
        w_all = jnp.asarray(valid[:, None] / comp_sigma[None, :])
    solve_s = time.perf_counter() - t_solve

    t_lin = time.perf_counter()
    r, J = gf.jacobians(jnp.asarray(xs), qj, yj, cj, w_all, model=model)
    r, J = np.asarray(r), np.asarray(J)
    fold_rows = np.repeat(fold, m)
    valid_rows = np.repeat(valid, m)
    pos_rows = np.tile(pos_comp, npad)
    lin = _Linear(r, J, fold_rows, valid_rows, pos_rows, folds)
    pos_scale = comp_sigma[0] * 1e3  # weighted position units -> mm

    def rms_mm(sse_pos):
        return float(np.sqrt(sse_pos / n)) * pos_scale

    # Candidates and their separability (projection on the geometry columns, all data).
    Jall = J[folds][valid_rows]
    Qg = scipy.linalg.qr(Jall[:, G], mode="economic")[0]
    cands, not_candidates = [], {}
    for eff in effects:
        need = NEEDS.get(eff)
        if need is not None and need not in present:
            not_candidates[eff] = f"needs the {'temperature or time' if need == 'thermal' else need} covariate"
            continue
        if not model.index(eff).size:
            not_candidates[eff] = "not in the effect library of this robot"
            continue
        variants = [()] if eff in GLOBAL_EFFECTS else [(j,) for j in model.joints_with(eff)]
        for js in variants:
            cols = model.index(eff, js if js else None)
            E = Jall[:, cols]
            En = np.linalg.norm(E, axis=0)
            Et = E - Qg @ (Qg.T @ E)
            rel = np.linalg.norm(Et, axis=0) / np.maximum(En, 1e-300)
            keep = np.flatnonzero((En > 0) & (rel > SEPARABLE_TOL))
            if keep.size:
                bs = base_set(Et[:, keep] / np.linalg.norm(Et[:, keep], axis=0), np.ones(keep.size))
                keep = keep[np.sort(bs.independent)]
            absorbed = tuple(model.names[cols[i]] for i in range(len(cols)) if i not in set(keep) and En[i] > 0)
            note = "" if keep.size else ("no effect on these readings" if not np.any(En > 0)
                                         else "absorbed by the geometry / device frame")
            cands.append(dict(effect=eff, js=js, cols=cols[keep], absorbed=absorbed, note=note))

    n_rows = int(valid_rows.sum())
    n_sep = max(sum(1 for c in cands if len(c["cols"])), 1)
    jn = robot.joint_names
    selected, base_cols = [], list(G)
    ranking = None
    base_eval = lin.evaluate(base_cols)
    held_rms_before_lin = rms_mm(base_eval[1])
    for _round in range(max_effects):
        sse0, _, rss0 = lin.evaluate(base_cols)
        rows = []
        for c in cands:
            if not len(c["cols"]) or any(c is s for s in selected):
                rows.append((c, None))
                continue
            cols = base_cols + list(c["cols"])
            sse, sse_pos, rss = lin.evaluate(cols)
            k = len(c["cols"])
            dof = n_rows - len(cols)
            F = ((rss0 - rss) / k) / max(rss / dof, 1e-300)
            pval = float(scipy.stats.f.sf(F, k, dof)) if dof > 0 else 1.0
            score = 0.5 * n_rows * np.log(sse0 / max(sse, 1e-300)) - k
            bic = n_rows * np.log(rss / n_rows) + len(cols) * np.log(n_rows)
            rows.append((c, dict(sse=sse, sse_pos=sse_pos, score=score, p=pval, bic=bic, k=k)))
        if ranking is None:
            ranking = []
            for c, s in rows:
                names = tuple(jn[j] for j in c["js"])
                if s is None:
                    ranking.append(Candidate(c["effect"], names, held_rms_before_lin, np.nan, -np.inf, np.nan, 1.0, 0, False,
                                             c["absorbed"], c["note"]))
                else:
                    ranking.append(Candidate(c["effect"], names, held_rms_before_lin, rms_mm(s["sse_pos"]), float(s["score"]),
                                             float(s["bic"]), s["p"], s["k"], True, c["absorbed"], "",
                                             tuple(int(i) for i in c["cols"])))
            ranking.sort(key=lambda c: -c.score)
        ok = [(c, s) for c, s in rows if s is not None and s["p"] < alpha / n_sep and s["sse"] < sse0 and s["score"] > 0]
        if not ok:
            break
        best, _ = max(ok, key=lambda cs: cs[1]["score"])
        selected.append(best)
        base_cols = base_cols + list(best["cols"])
    lin_s = time.perf_counter() - t_lin

    # How far: nonlinear refit of the selected model on every fold, regularised toward the fold's baseline.
    t_fin = time.perf_counter()
    w_unit = jnp.asarray(valid[:, None] / comp_sigma[None, :])
    r_base = np.asarray(gf.residual_batch(jnp.asarray(xs), qj, yj, cj, w_unit, model=model))
    diverged = []
    if selected:  # start from the regularised Gauss-Newton step of every fold
        prior_mu = PRIOR_MU if robot.closure is None else 0.0
        mu = prior_weights(base_cols, prior_mu)[:len(base_cols)]
        z_start = np.zeros((folds + 1, K_active))
        for b in range(folds + 1):
            train = np.flatnonzero(valid_rows & (fold_rows != b)) if b < folds else np.flatnonzero(valid_rows)
            z_start[b, :len(base_cols)] = _prior_step(J[b], r[b], base_cols, train, scale, mu)
        x_try = xs.copy()
        x_try[:, base_cols] += scale[base_cols] * z_start[:, :len(base_cols)]
        keep = _lower_cost_start(x_try, xs, qj, yj, cj, fold_weights(comp_sigma), model) == x_try
        z_start[~np.all(keep, axis=1)] = 0.0  # that fold starts from its baseline
        xs_final, ok_final, steps_final = solve(xs, base_cols, comp_sigma, z_start, prior_mu)
        r_fin = np.array(gf.residual_batch(jnp.asarray(xs_final), qj, yj, cj, w_unit, model=model))
        limits = box_limits(model, np.asarray(gf.moment_norms(jnp.asarray(xs[folds]), qj, model=model))[:n])
        for b in range(folds + 1):
            rows = (valid & (fold == b)) if b < folds else valid
            why = _divergence(xs_final[b], xs[b], x0s[b], r_fin[b], r_base[b], rows, np.asarray(base_cols), limits, model.names,
                              b < folds)
            if why:
                diverged.append({"fit": f"fold {b + 1}" if b < folds else "all data", "reason": why})
                xs_final[b], r_fin[b] = xs[b], r_base[b]
    else:
        xs_final, ok_final, steps_final, r_fin = xs, ok_base, 0, r_base
    all_data_diverged = any(d["fit"] == "all data" for d in diverged)

    def out_of_fold(rr):
        out = np.zeros((n, m))
        for b in range(folds):
            sel = fold[:n] == b
            out[sel] = rr[b][:n][sel]
        return out

    oof_base, oof_fin = out_of_fold(r_base), out_of_fold(r_fin)
    # A diverged fold's held-out samples are left out of before / after / structure (scored on the other folds).
    bad = [int(d["fit"].split()[1]) - 1 for d in diverged if d["fit"] != "all data"]
    scored = ~np.isin(fold[:n], bad)
    scored = scored if scored.any() else np.ones(n, bool)  # every fold diverged: the baseline everywhere
    before = float(np.sqrt(np.mean(np.sum(oof_base[scored, :3] ** 2, axis=1)))) * pos_scale
    after = float(np.sqrt(np.mean(np.sum(oof_fin[scored, :3] ** 2, axis=1)))) * pos_scale

    floor = _noise_floor_repeats(data, groups)
    if floor is not None:
        noise_floor, noise_source = floor * 1e3, "repeated poses"
    else:
        rf = r_fin[folds][:n, :3]
        dof = max(n * m - len(G if all_data_diverged else base_cols), 1)
        noise_floor = float(np.sqrt(np.sum(rf**2) / n * (n * m) / dof)) * pos_scale
        noise_source = "fit residual with its degrees of freedom" + (" (baseline: the refit diverged)" if all_data_diverged else "")

    shrink = shrink_fraction(before, after, noise_floor) if selected else 0.0

    # Where: baseline out-of-fold residual against features; structure left after the selected model.
    loads, tips = gf.loads_and_tips(jnp.asarray(xs[folds]), qj, cj, model=model)
    loads, tips = np.asarray(loads)[:n], np.asarray(tips)[:n]
    bases = wh.feature_bases(data.q, model.revolute, jn, loads, tips, data.covariates)
    labels = ["x", "y", "z", "rx", "ry", "rz"][:m]
    motion = _joint_motion(model, J[folds], data.q, npad, m)
    directions = {f"joint angle {jn[j]}": motion[:, :, j] for j in range(robot.n_inputs)}
    feats_base = wh.decompose(oof_base, bases, tips, directions, seed=seed)
    feats_fin = wh.decompose(oof_fin[scored], {k: v[scored] for k, v in bases.items()}, tips[scored],
                             {k: v[scored] for k, v in directions.items()}, seed=seed)
    structure_p = float(min(1.0, min(f.p_value for f in feats_fin) * len(feats_fin))) if feats_fin else 1.0
    axis = wh.axis_rms(oof_base * comp_sigma[None, :] * 1e3, [f"{a} ({'mm' if i < 3 else 'mrad'})" for i, a in enumerate(labels)])
    where = {"axis_rms": axis,
             "features": [dataclasses.asdict(f) for f in feats_base],
             "features_after": [dataclasses.asdict(f) for f in feats_fin]}

    if structure_p < alpha:
        verdict, joints = "unexplained", ()
    elif not selected:
        verdict, joints = "none", ()
    else:
        verdict = selected[0]["effect"]
        joints = tuple(jn[j] for s in selected if s["effect"] == verdict for j in s["js"])
    params = {}
    for s in ([] if all_data_diverged else selected):
        for i in s["cols"]:
            params[model.names[i]] = float(xs_final[folds][i])
    steps = {"baseline": steps_base, "final": steps_final,
             "converged": bool(np.all(ok_base) and np.all(ok_final))}
    timings = {"lm_steps": steps, "solve_s": solve_s, "linear_s": lin_s, "final_s": time.perf_counter() - t_fin,
               "total_s": time.perf_counter() - t0}
    plot_data = {"q": data.q, "motion": motion, "tips": tips, "oof_base": oof_base * comp_sigma * 1e3,
                 "oof_final": oof_fin * comp_sigma * 1e3,
                 "joint_names": jn, "revolute": model.revolute, "labels": labels}
    return Diagnosis(robot.name, device.kind, verdict, joints, ranking, shrink, where, before, after, noise_floor, noise_source,
                     [(s["effect"], tuple(jn[j] for j in s["js"])) for s in selected], params, structure_p, not_candidates,
                     n, folds, timings, diverged=diverged, mass_model=model.mass_model,
                     _plot_data=plot_data)
