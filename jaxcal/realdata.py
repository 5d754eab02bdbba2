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
offsets), "full" (every geometric parameter; `identify` estimates the base set), "prior"
(every geometric parameter with the bias term mu ||(a - a0)/0.01||^2 of seed 004 eq 3.12; mu
chosen by inner cross-validation on the training folds only), "prior+weights" (the same with the
orientation weight of pose data chosen by the inner cross-validation too); "full+compliance" and
"prior+compliance" add a joint compliance under gravity per revolute joint (`with_compliance`).
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
from jaxcal.robots.urdf import compliance_inputs, rpy_matrix, with_gravity_compliance

DATA_DIR = os.path.join(os.path.dirname(__file__), "robots", "data", "real")

# FIGAROH 1.0.2 on the same files, 5-fold cross-validated position RMS (mm) of the per-sample 3-D
# error, from data/real/README.md: frames only, full parameters, best variant.
FIGAROH = {
    "talos": {"frames": 5.45, "full": 0.85, "best": 0.74, "best_variant": "full + joint compliance"},
    "ur10": {"frames": 4.25, "full": 4.12, "best": 3.95, "best_variant": "prior-regularised, CV-tuned",
             "frames_deg": 0.63, "full_deg": 0.50},
    "tiago": {"frames": 4.54, "full": 6.03, "best": 4.30, "best_variant": "three marker points"},
}

_SPECS = {
    "talos": dict(robot="talos_left_arm", folder="talos", urdf="talos.urdf", csv="left_arm_mocap.csv", tip="gripper_left_base_link",
                  joints=("torso_1_joint", "torso_2_joint") + tuple(f"arm_left_{i}_joint" for i in range(1, 8)),
                  description="PAL TALOS humanoid, torso + left arm, motion-capture positions of one marker"),
    "ur10": dict(robot="ur10", folder="ur10", urdf="ur10.urdf", csv="calibration_pose.csv", tip="wrist_3_link",
                 joints=("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
                         "wrist_3_joint"),
                 description="Universal Robots UR10, full 6-D marker poses"),
    "tiago": dict(robot="tiago_arm", folder="tiago", urdf="tiago.urdf", csv="qualisys_static_postures.csv", tip="wrist_ft_tool_link",
                  joints=("torso_lift_joint",) + tuple(f"arm_{i}_joint" for i in range(1, 8)),
                  description="PAL TIAGo torso + arm, Qualisys motion capture of a rigid three-point marker"),
}
# Orientation residual weight 1/sigma (rad), fixed a priori: UR10 1 mrad per mm as for a tracked marker
# frame; TIAGo's orientation comes from a triad of ~0.1 m, so 1 mm of point noise is ~10 mrad.
SIGMA_ORIENTATION = {"talos": 1e-3, "ur10": 1e-3, "tiago": 1e-2}
MU_GRID = tuple(10.0 ** k for k in range(-3, 3))
SIGMA_FACTORS = (0.1, 0.3, 1.0)  # orientation weights tried by the inner CV of "prior" (pose data)
SETTINGS = ("frames", "offsets", "full", "prior", "prior+weights", "full+compliance", "prior+compliance")


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
    return tuple(_SPECS)


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
    if name not in _SPECS:
        raise KeyError(f"unknown real dataset {name!r}; built-ins: {', '.join(available())}")
    spec = _SPECS[name]
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


@functools.cache
def _compliant_robot(name: str):
    return with_gravity_compliance(robots.get(_SPECS[name]["robot"]))


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
    opts.update(kwargs)
    return identify(real.robot, real.data, **opts)


def sample_errors(fit, real: RealData, idx):
    """Per-sample (position error mm, orientation error deg or None) of a fit on samples idx."""
    pe, oe = fit.errors(real.data.subset(np.asarray(idx)))
    return pe * 1e3, (None if oe is None else np.degrees(oe))


def point_errors(fit, real: RealData, idx) -> np.ndarray:
    """TIAGo: 3-D error (mm) of each of the three marker points, (len(idx), 3), from the fitted
    marker pose applied to the triad's mean shape."""
    idx = np.asarray(idx)
    T = fit.predict(real.data.q[idx])
    pred = np.einsum("nij,kj->nki", T[:, :3, :3], real.extra["triad"]) + T[:, None, :3, 3]
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
    if not weights or "sigma_orientation" in fit_options or real.data.device.kind != "pose":
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


def cross_validate(real: RealData, setting: str, folds: int = 5, seed: int = 0, grid=MU_GRID, **fit_options) -> dict:
    """k-fold cross-validation of one setting: train RMS (mean over folds) and held-out RMS pooled
    over all held-out samples (position mm; orientation deg for pose data), the parameters estimated,
    the mu chosen per fold ("prior"), and the time (compile apart from run). `fit_options` go to
    `identify` (e.g. sigma_orientation)."""
    if setting.endswith("+compliance"):
        real, setting = with_compliance(real), setting.removesuffix("+compliance")
    n = len(real.data)
    held_pos, held_ori, train_pos, train_ori, held_pts, n_est, mus = [], [], [], [], [], [], []
    compile_s = run_s = 0.0
    t0 = time.perf_counter()
    for held in fold_indices(n, folds, seed):
        train = np.setdiff1d(np.arange(n), held)
        options, mu = dict(fit_options), None
        if setting in ("prior", "prior+weights"):
            chosen = choose_prior(real, train, grid, weights=setting == "prior+weights", **fit_options)
            mu, options["sigma_orientation"] = chosen["mu"], chosen["sigma_orientation"]
            mus.append(chosen)
        fit = fit_on(real, setting.removesuffix("+weights"), train, mu, **options)
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
    label = setting + ("+compliance" if "compliance_of" in real.robot.extras else "")
    out = {"setting": label, "folds": folds, "samples": n, "parameters_estimated": int(np.median(n_est)),
           "train_rms_mm": float(np.mean(train_pos)), "heldout_rms_mm": _rms(np.concatenate(held_pos)),
           "compile_s": compile_s, "fit_run_s_per_fold": run_s / folds, "wall_s": time.perf_counter() - t0}
    if held_ori:
        out.update(train_rms_deg=float(np.mean(train_ori)), heldout_rms_deg=_rms(np.concatenate(held_ori)))
    if held_pts:
        out["heldout_rms_3points_mm"] = _rms(np.concatenate(held_pts))
    if mus:
        out["chosen_per_fold"] = mus
    return out
