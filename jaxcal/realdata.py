"""Built-in real measurement data: TALOS left arm, UR10, TIAGo (FIGAROH's examples, Apache-2.0).

    import jaxcal as jc
    real = jc.realdata.load("talos")          # RealData: .robot, .data, .description, .figaroh
    fit = jc.identify(real.robot, real.data)
    cv = jc.realdata.cross_validate(real, "full", folds=5)

The files (and their URDFs) were measured and published by the authors of the FIGAROH toolbox
(github.com/thanhndv212/figaroh-examples; Thanh Nguyen, CNRS, Toward SAS); they are copied
unchanged, with their licence, under `jaxcal/robots/data/real/` (see README.md there).

- "talos": 61 mocap positions of one marker on the left gripper; chain base_link ->
  gripper_left_base_link (torso 2 + arm 7 joints); device "position".
- "ur10": 23 full marker poses (position m; orientation as URDF-style fixed-axis rpy, rad);
  chain world -> wrist_3_link; device "pose".
- "tiago": 34 static postures with four marker points (points 3 and 4 are the same point; the
  three distinct ones are rigid to 3e-8 m, i.e. derived from one rigid-body pose). They are read
  as one pose per sample: origin at point 1, axes from the triad (Gram-Schmidt of p2 - p1 and
  p3 - p1); chain base_footprint -> wrist_ft_tool_link (torso lift + arm 7 joints); device "pose".

Settings for `calibration_free` / `cross_validate` (always with the unknown device frame and
marker fitted too): "frames" (nothing of the robot: the fair "before"), "offsets" (joint
offsets), "full" (every geometric parameter; `identify` estimates the base set by plain least squares,
no bias term: FIGAROH's full setting), "prior"
(every geometric parameter with the bias term mu ||(a - a0)/0.01||^2 of seed 004 eq 3.12; mu
chosen by inner cross-validation on the training folds only), "prior+weights" (the same with the
orientation weight of pose data chosen by the inner cross-validation too); "full+compliance" and
"prior+compliance" add a joint compliance under gravity per revolute joint (`with_compliance`);
"nested" picks one of `engineer_variants` (parameter set, mu, orientation weight, compliance, robust
loss) per outer fold by inner cross-validation on its training folds (`nested_cross_validate`).
A "+markers" suffix (TIAGo) fits the three marker points, each with its own offset (`with_markers`).
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import os
import time

import numpy as np

from jaxcal import robots
from jaxcal.fit.data import DataError, Dataset
from jaxcal.fit.identify import identify
from jaxcal.robots.real_datasets import DATA_DIR, REAL_DATASETS
from jaxcal.robots.urdf import compliance_inputs, rpy_matrix, with_gravity_compliance

# FIGAROH 1.0.2 on the same files, 5-fold cross-validated position RMS (mm) of the per-sample 3-D
# error, from data/real/README.md: frames only, full parameters, best variant.
FIGAROH = {
    "talos": {"frames": 5.45, "full": 0.85, "best": 0.74, "best_variant": "full + joint compliance"},
    "ur10": {"frames": 4.25, "full": 4.12, "best": 3.95, "best_variant": "prior-regularised, CV-tuned",
             "frames_deg": 0.63, "full_deg": 0.50},
    "tiago": {"frames": 4.54, "full": 6.03, "best": 4.30, "best_variant": "three marker points"},
}

# Orientation residual weight 1/sigma (rad), fixed a priori: UR10 1 mrad per mm as for a tracked marker
# frame; TIAGo's orientation comes from a triad of ~0.1 m, so 1 mm of point noise is ~10 mrad.
SIGMA_ORIENTATION = {"talos": 1e-3, "ur10": 1e-3, "tiago": 1e-2}
MU_GRID = tuple(10.0 ** k for k in range(-3, 3))
# "full" runs plain least squares on the base set (FIGAROH's full-parameter setting); identify's default would add
# its bias schedule where the estimate is noise-dominated (TALOS: held-out 0.875 mm instead of 0.853, measured
# 2026-11-26), and without it LM needs up to ~600 steps on TALOS folds
FULL_MAX_STEPS = 1000
SIGMA_FACTORS = (0.1, 0.3, 1.0)  # orientation weights tried by the inner CV of "prior" (pose data)
SETTINGS = ("frames", "offsets", "full", "prior", "prior+weights", "full+compliance", "prior+compliance", "nested")


@dataclasses.dataclass(frozen=True)
class RealData:
    """A built-in real dataset: the URDF chain as a robot, the measurements, and FIGAROH's figures."""

    name: str
    robot: object
    data: Dataset
    description: str
    figaroh: dict
    extra: dict = dataclasses.field(default_factory=dict)


def available() -> tuple[str, ...]:
    return tuple(REAL_DATASETS)


def read_columns(path: str, columns) -> np.ndarray:
    """The named columns of a CSV file with a header, as floats; errors name the line and column."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise DataError(f"{path}: empty file")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in columns if c not in header]
    if missing:
        raise DataError(f"{path}: missing column(s) {missing}; header has {header}")
    idx = [header.index(c) for c in columns]
    out = []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != len(header):
            raise DataError(f"{path}, line {lineno}: {len(row)} fields, header has {len(header)}")
        try:
            values = [float(row[i]) for i in idx]
        except ValueError:
            bad = next(c for c, i in zip(columns, idx) if not _is_number(row[i]))
            raise DataError(f"{path}, line {lineno}, column {bad!r}: not a number: {row[header.index(bad)]!r}") from None
        if not np.all(np.isfinite(values)):
            raise DataError(f"{path}, line {lineno}: non-finite value")
        out.append(values)
    return np.array(out, float).reshape(-1, len(columns))


def _is_number(text) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def triad_frame(p1, p2, p3) -> np.ndarray:
    """Rotation (N, 3, 3) of three points: x along p2 - p1, z normal to the triad, y = z x x."""
    e1 = p2 - p1
    e1 = e1 / np.linalg.norm(e1, axis=-1, keepdims=True)
    e3 = np.cross(e1, p3 - p1)
    e3 = e3 / np.linalg.norm(e3, axis=-1, keepdims=True)
    return np.stack([e1, np.cross(e3, e1), e3], axis=-1)


def load(name: str) -> RealData:
    """A built-in real dataset by name (see `available()`); its robot is the built-in of the same
    chain (`jc.robots.get("talos_left_arm" | "ur10" | "tiago_arm")`)."""
    if name not in REAL_DATASETS:
        raise KeyError(f"unknown real dataset {name!r}; built-ins: {', '.join(available())}")
    spec = REAL_DATASETS[name]
    folder = os.path.join(DATA_DIR, spec["folder"])
    robot = robots.get(spec["robot"])  # cached: one robot object, so compiled solvers are reused
    path = os.path.join(folder, spec["csv"])
    q = read_columns(path, spec["joints"])
    extra = {}
    if name == "talos":
        data = Dataset(q=q, y=read_columns(path, ("x1", "y1", "z1")), device="position",
                       covariates={"time": read_columns(path, ("t",))[:, 0]}, joint_names=spec["joints"], source=path)
    elif name == "ur10":
        pose = read_columns(path, ("x1", "y1", "z1", "phix1", "phiy1", "phiz1"))
        R = np.stack([rpy_matrix(r) for r in pose[:, 3:]])
        data = Dataset(q=q, R=R, p=pose[:, :3], device="pose", joint_names=spec["joints"], source=path)
    else:
        pts = [read_columns(path, (f"x{k}", f"y{k}", f"z{k}")) for k in (1, 2, 3)]
        R = triad_frame(*pts)
        local = np.stack([np.einsum("nji,nj->ni", R, p - pts[0]) for p in pts], axis=1)  # (N, 3 points, 3)
        extra["points"] = np.stack(pts, axis=1)  # (N, 3 points, 3), m
        extra["triad"] = local.mean(axis=0)
        extra["triad_spread_m"] = float(np.max(np.abs(local - extra["triad"])))
        data = Dataset(q=q, R=R, p=pts[0], device="pose", joint_names=spec["joints"], source=path)
    if robot.joint_names != spec["joints"]:
        raise DataError(f"{path}: joint columns {spec['joints']} do not match the URDF chain {robot.joint_names}")
    return RealData(name, robot, data, spec["description"], FIGAROH[name], extra)


def with_markers(real: RealData) -> RealData:
    """TIAGo read as its three distinct marker points, each with its own identified offset on the
    tip link (device "multi_position", readings (N, 3, 3)) instead of one marker pose."""
    if "points" not in real.extra:
        raise ValueError(f"dataset {real.name!r} has one marker point; with_markers is for multi-point data (tiago)")
    d = real.data
    data = Dataset(q=d.q, y=real.extra["points"], device="multi_position", covariates=d.covariates,
                   joint_names=d.joint_names, source=d.source)
    return dataclasses.replace(real, data=data)


@functools.cache
def _compliant_robot(name: str):
    return with_gravity_compliance(robots.get(REAL_DATASETS[name]["robot"]))


def with_compliance(real: RealData) -> RealData:
    """The dataset on its robot with joint compliance under gravity (`with_gravity_compliance`):
    the joint inputs gain the nominal gravity torques. The compliant robot is cached per dataset."""
    if "compliance_of" in real.robot.extras:
        return real
    robot = _compliant_robot(real.name)
    d = real.data
    data = Dataset(q=compliance_inputs(real.robot, d.q), y=d.y, device=d.device, covariates=d.covariates,
                   joint_names=robot.joint_names, source=d.source)
    return dataclasses.replace(real, robot=robot, data=data)


def calibration_free(robot, setting: str) -> tuple[str, ...]:
    """Robot parameter names estimated in a setting ("frames", "offsets", "full" or "prior")."""
    if setting == "frames":
        return ()
    if setting == "offsets":
        return tuple(n for n in robot.names if n.endswith(".offset"))
    if setting in ("full", "prior"):
        return tuple(robot.names)
    raise ValueError(f"unknown setting {setting!r}; expected one of {SETTINGS}")


def fold_indices(n: int, folds: int = 5, seed: int = 0) -> list[np.ndarray]:
    """Held-out sample indices of each fold: a seeded permutation cut into `folds` near-equal parts."""
    if not 2 <= folds <= n:
        raise ValueError(f"folds must be between 2 and the number of samples {n}, got {folds}")
    perm = np.random.default_rng(seed).permutation(n)
    return [np.sort(part) for part in np.array_split(perm, folds)]


def fit_on(real: RealData, setting: str, train, mu: float | None = None, **kwargs):
    """`identify` on the samples `train` only (the others get weight 0, so every subset shares one
    compiled solver). "prior" estimates every parameter with the bias term mu (no base-set cut)."""
    weights = np.zeros(len(real.data))
    weights[np.asarray(train)] = 1.0
    opts = dict(free=calibration_free(real.robot, setting), sample_weights=weights,
                sigma_orientation=SIGMA_ORIENTATION[real.name])
    if setting == "prior":
        if mu is None:
            raise ValueError("setting 'prior' needs mu")
        opts.update(base=False, bias=[mu])
    if setting == "full":  # FIGAROH's full setting: least squares on the base set, no bias term
        opts.update(bias=[0.0], max_steps=FULL_MAX_STEPS)
    opts.update(kwargs)
    return identify(real.robot, real.data, **opts)


def sample_errors(fit, real: RealData, idx):
    """Per-sample (position error mm, orientation error deg or None) of a fit on samples idx."""
    pe, oe = fit.errors(real.data.subset(np.asarray(idx)))
    return pe * 1e3, (None if oe is None else np.degrees(oe))


def point_errors(fit, real: RealData, idx) -> np.ndarray:
    """TIAGo: 3-D error (mm) of each of the three marker points, (len(idx), 3): from the fitted
    marker pose applied to the triad's mean shape (pose data), or of each fitted point (`with_markers`)."""
    idx = np.asarray(idx)
    if real.data.device.marker_reading == "frame":
        T = fit.predict(real.data.q[idx])
        pred = np.einsum("nij,kj->nki", T[:, :3, :3], real.extra["triad"]) + T[:, None, :3, 3]
    else:
        pred = real.data.device.points(fit.predict(real.data.q[idx]))
    return np.linalg.norm(pred - real.extra["points"][idx], axis=-1) * 1e3


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def choose_prior(real: RealData, train, grid=MU_GRID, weights: bool = False, inner_folds: int = 4, seed: int = 1,
                 **fit_options) -> dict:
    """mu (and with `weights`, for pose data, the orientation weight sigma_orientation among
    SIGMA_FACTORS x the a-priori value) with the smallest inner cross-validated position RMS, using
    the training samples `train` only: the outer held-out fold is never seen."""
    train = np.asarray(train)
    inner = fold_indices(len(train), inner_folds, seed)
    if not weights or "sigma_orientation" in fit_options or real.data.device.marker_reading != "frame":
        sigmas = [fit_options.pop("sigma_orientation", SIGMA_ORIENTATION[real.name])]
    else:
        sigmas = [SIGMA_ORIENTATION[real.name] * f for f in SIGMA_FACTORS]
    candidates = [(mu, so) for so in sigmas for mu in grid]
    scores = []
    for mu, so in candidates:
        errs = []
        for part in inner:
            held = train[part]
            fit = fit_on(real, "prior", np.setdiff1d(train, held), mu, sigma_orientation=so, **fit_options)
            errs.append(sample_errors(fit, real, held)[0])
        scores.append(_rms(np.concatenate(errs)))
    mu, so = candidates[int(np.argmin(scores))]
    return {"mu": float(mu), "sigma_orientation": float(so)}


def _markers_label(real: RealData) -> str:
    """The label suffix "+markers" for data read as several marker points per sample (`with_markers`), else ""."""
    return "+markers" if real.data.device.marker_reading == "points" else ""


def cross_validate(real: RealData, setting: str, folds: int = 5, seed: int = 0, grid=MU_GRID, **fit_options) -> dict:
    """k-fold cross-validation of one setting: train RMS (mean over folds) and held-out RMS pooled
    over all held-out samples (position mm; orientation deg for pose data), the parameters estimated,
    the mu chosen per fold ("prior"), and the time (compile apart from run). `fit_options` go to
    `identify` (e.g. sigma_orientation)."""
    if setting.endswith("+markers"):
        real, setting = with_markers(real), setting.removesuffix("+markers")
    if setting == "nested":
        label = "nested" + _markers_label(real)
        return nested_cross_validate(real, engineer_variants(real), folds, seed, label=label)
    if setting.endswith("+compliance"):
        real, setting = with_compliance(real), setting.removesuffix("+compliance")
    n = len(real.data)
    per_fold, mus = [], []
    t0 = time.perf_counter()
    for held in fold_indices(n, folds, seed):
        train = np.setdiff1d(np.arange(n), held)
        options, mu = dict(fit_options), None
        if setting in ("prior", "prior+weights"):
            chosen = choose_prior(real, train, grid, weights=setting == "prior+weights", **fit_options)
            mu, options["sigma_orientation"] = chosen["mu"], chosen["sigma_orientation"]
            mus.append(chosen)
        per_fold.append((fit_on(real, setting.removesuffix("+weights"), train, mu, **options), real, train, held))
    label = (setting + ("+compliance" if "compliance_of" in real.robot.extras else "")
             + _markers_label(real))
    out = _cv_summary(label, per_fold, time.perf_counter() - t0)
    if mus:
        out["chosen_per_fold"] = mus
    return out


def _cv_summary(label: str, per_fold, wall_s: float) -> dict:
    """Held-out and train RMS of the fits of a cross-validation, per_fold = [(fit, dataset used, train, held)]."""
    held_pos, held_ori, train_pos, train_ori, held_pts, n_est = [], [], [], [], [], []
    compile_s = run_s = 0.0
    for fit, real, train, held in per_fold:
        compile_s += fit.timings["compile_s"]
        run_s += fit.timings["run_s"]
        pe, oe = sample_errors(fit, real, held)
        tpe, toe = sample_errors(fit, real, train)
        held_pos.append(pe)
        train_pos.append(_rms(tpe))
        if oe is not None:
            held_ori.append(oe)
            train_ori.append(_rms(toe))
        if "points" in real.extra:
            held_pts.append(point_errors(fit, real, held))
        n_est.append(len(fit.estimated))
    folds = len(per_fold)
    out = {"setting": label, "folds": folds, "samples": len(per_fold[0][1].data), "parameters_estimated": int(np.median(n_est)),
           "train_rms_mm": float(np.mean(train_pos)), "heldout_rms_mm": _rms(np.concatenate(held_pos)),
           "compile_s": compile_s, "fit_run_s_per_fold": run_s / folds, "wall_s": wall_s}
    if held_ori:
        out.update(train_rms_deg=float(np.mean(train_ori)), heldout_rms_deg=_rms(np.concatenate(held_ori)))
    if held_pts:
        pts = np.concatenate(held_pts)
        out["heldout_rms_3points_mm"] = _rms(pts)
        out["heldout_rms_per_point_mm"] = [_rms(pts[:, k]) for k in range(pts.shape[1])]
    return out


# -- nested cross-validation over model variants ---------------------------------------------------
HUBER_K = 1.5  # Huber threshold in robust scale units (1.4826 x median per-sample error)
ROBUST_ITERATIONS = 2


@dataclasses.dataclass(frozen=True)
class Variant:
    """One candidate model for `nested_cross_validate`.

    setting: "frames", "offsets", "full" (base set by QR with column pivoting) or "prior" (every
    parameter, bias mu). orientation (pose data): "a priori" (SIGMA_ORIENTATION), "noise ratio"
    (`noise_ratio_sigma` on the training samples) or a number, the factor times the a-priori value.
    compliance: joint compliance under gravity (`with_compliance`). robust: Huber re-weighting of
    the samples (`fit_variant`)."""

    setting: str = "prior"
    mu: float | None = None
    orientation: str | float = "a priori"
    compliance: bool = False
    robust: bool = False

    @property
    def label(self) -> str:
        parts = [self.setting if self.mu is None else f"{self.setting}(mu={self.mu:g})"]
        if self.orientation != "a priori":
            parts.append("w=noise" if self.orientation == "noise ratio" else f"w={self.orientation:g}")
        parts += ["compliance"] * self.compliance + ["robust"] * self.robust
        return "+".join(parts)


def noise_ratio_sigma(real: RealData, train, sigma_position: float = 1e-3) -> float:
    """Orientation weight 1/sigma_o from the measured noise ratio: sigma_o = sigma_p x (RMS orientation
    residual per component, rad) / (RMS position residual per component, m) of the full base-set fit on
    the samples `train` (pose data only)."""
    fit = fit_on(real, "full", train)
    pe, oe = fit.errors(real.data.subset(np.asarray(train)))
    return float(sigma_position * _rms(oe) / _rms(pe))


def huber_weights(errors, k: float = HUBER_K) -> np.ndarray:
    """Huber IRLS weights of per-sample errors: 1 within k robust scales (1.4826 x median), k s / e beyond."""
    e = np.asarray(errors, float)
    scale = 1.4826 * np.median(e)
    return np.minimum(1.0, k * scale / np.maximum(e, 1e-300))


def fit_variant(real: RealData, variant: Variant, train, noise_sigmas: dict | None = None):
    """Fit one variant on the samples `train`: (fit, the dataset it was fitted on). Robust: fit,
    re-weight the training samples by `huber_weights` of their weighted residual norm, refit
    (ROBUST_ITERATIONS times). `noise_sigmas` caches `noise_ratio_sigma` of these samples per
    compliance flag (it does not depend on the other choices)."""
    train = np.asarray(train)
    if variant.compliance:
        real = with_compliance(real)
    noise_sigmas = {} if noise_sigmas is None else noise_sigmas
    options = {}
    if real.data.device.marker_reading == "frame":
        so = variant.orientation
        if so == "noise ratio" and variant.compliance not in noise_sigmas:
            noise_sigmas[variant.compliance] = noise_ratio_sigma(real, train)
        options["sigma_orientation"] = (noise_sigmas[variant.compliance] if so == "noise ratio"
                                        else SIGMA_ORIENTATION[real.name] * (1.0 if so == "a priori" else float(so)))
    fit = fit_on(real, variant.setting, train, variant.mu, **options)
    for _ in range(ROBUST_ITERATIONS if variant.robust else 0):
        pe, oe = fit.errors(real.data.subset(train))
        norm = pe / 1e-3 if oe is None else np.hypot(pe / 1e-3, oe / options["sigma_orientation"])
        weights = np.zeros(len(real.data))
        weights[train] = huber_weights(norm)
        fit = fit_on(real, variant.setting, train, variant.mu, sample_weights=weights, **options)
    return fit, real


def choose_variant(real: RealData, variants, train, inner_folds: int = 4, seed: int = 1) -> tuple[Variant, list[float]]:
    """The variant with the smallest inner cross-validated position RMS on the samples `train` only
    (the outer held-out fold is never seen), and every variant's inner score (mm)."""
    train = np.asarray(train)
    inner = fold_indices(len(train), inner_folds, seed)
    noise_sigmas = [{} for _ in inner]
    scores = []
    for v in variants:
        errs = []
        for part, cache in zip(inner, noise_sigmas):
            fit, used = fit_variant(real, v, np.setdiff1d(train, train[part]), cache)
            errs.append(sample_errors(fit, used, train[part])[0])
        scores.append(_rms(np.concatenate(errs)))
    return variants[int(np.argmin(scores))], scores


def engineer_variants(real: RealData, mu_grid=MU_GRID) -> tuple[Variant, ...]:
    """The candidates a robotics engineer would try, fixed before any fit: base set (QR) or prior
    over mu_grid; a-priori or noise-ratio orientation weight (pose data); with or without joint
    compliance under gravity; with or without Huber re-weighting."""
    models = [("full", None)] + [("prior", mu) for mu in mu_grid]
    weights = ("a priori", "noise ratio") if real.data.device.marker_reading == "frame" else ("a priori",)
    return tuple(Variant(s, mu, w, c, r) for s, mu in models for w in weights for c in (False, True) for r in (False, True))


def nested_cross_validate(real: RealData, variants, folds: int = 5, seed: int = 0, inner_folds: int = 4,
                          label: str = "nested") -> dict:
    """k-fold cross-validation in which every choice among `variants` (parameter set, prior weight,
    orientation weight, compliance, robust loss) is made per outer fold by an inner cross-validation
    on that fold's training samples only (`choose_variant`); held-out figures as `cross_validate`,
    with the variant chosen per fold and its inner score. One variant: its plain cross-validation."""
    variants = tuple(variants)
    n = len(real.data)
    per_fold, chosen = [], []
    t0 = time.perf_counter()
    for held in fold_indices(n, folds, seed):
        train = np.setdiff1d(np.arange(n), held)
        if len(variants) == 1:  # nothing to choose: plain k-fold cross-validation of that variant
            best, scores = variants[0], [float("nan")]
        else:
            best, scores = choose_variant(real, variants, train, inner_folds, seed + 1)
        chosen.append({"variant": best.label, "inner_rms_mm": min(scores)})
        fit, used = fit_variant(real, best, train)
        per_fold.append((fit, used, train, held))
    out = _cv_summary(label, per_fold, time.perf_counter() - t0)
    out.update(chosen_per_fold=chosen, candidates=len(variants))
    return out
