"""Several measurement sessions in one calibration: one device frame per session, the robot and marker shared.

`identify` calls `session_dataset` by itself when the data carry a "session" covariate with two or more
labels (a `session` column in the CSV). `session_summary` says how consistent the sessions are: samples,
RMS error per session, and where each session's frame lies relative to the first (how far the tracker
was moved). `jaxcal.fit.identify.apply_to_session` uses a calibrated robot on a new session: only that
session's device parameters are fitted (docs/identification.md, "Sessions").
"""

from __future__ import annotations

import numpy as np

from jaxcal.fit.data import Dataset
from jaxcal.kin.rotations import log_so3
from jaxcal.measure.base import frame_from_params
from jaxcal.measure.sessions import SESSION, Sessions, sorted_labels

INCONSISTENT = 3.0  # a session whose RMS error exceeds this multiple of the others' median is flagged


def session_labels(data: Dataset) -> tuple[str, ...]:
    """The distinct session labels of a dataset (empty without a "session" covariate)."""
    return sorted_labels(data.covariates[SESSION]) if SESSION in data.covariates else ()


def session_dataset(data: Dataset, per_session=("dev",)) -> Dataset:
    """The dataset read by `Sessions(data.device)`: each reading followed by its session's index."""
    labels = session_labels(data)
    if not labels:
        raise ValueError("the data have no 'session' covariate (a `session` column): nothing to split into sessions")
    device = Sessions.build(data.device, labels, per_session)
    out = Dataset(data.q, device.encode(data.y, data.covariates[SESSION]), device, dict(data.covariates),
                  joint_names=data.joint_names, source=data.source)
    out.units = dict(data.units)
    return out


def readings_for(device, data: Dataset) -> np.ndarray:
    """data's readings as `device` reads them: encoded with the session index when the device is a `Sessions`
    and the data are in the wrapped device's form."""
    if isinstance(device, Sessions) and not isinstance(data.device, Sessions):
        if SESSION not in data.covariates:
            raise ValueError(f"this calibration has sessions {list(device.labels)}: the data need a 'session' column")
        return device.encode(data.y, data.covariates[SESSION])
    return data.y


def session_device_params(device: Sessions, inner_params) -> np.ndarray:
    """A wrapped parameter vector with the wrapped device's parameters `inner_params` in every session."""
    d = np.zeros(device.n_params)
    for s in range(device.sessions):
        d[device.index[s]] = np.asarray(inner_params, float)
    return d


def session_summary(fit, data: Dataset) -> list[dict]:
    """Per session: label, samples, RMS error (the fit's unit), and its frame's offset from the first session's
    frame (translation m, rotation rad), with `inconsistent` set where the RMS error exceeds INCONSISTENT x the
    median of the other sessions'."""
    device = fit.device
    if not isinstance(device, Sessions):
        return []
    pe, oe = fit.errors(data)
    err = pe if pe is not None else oe
    idx = np.asarray(readings_for(device, data))[:, -1].astype(int)
    rms = [float(np.sqrt(np.mean(err[idx == s] ** 2)) * 1e3) if np.any(idx == s) else float("nan")
           for s in range(device.sessions)]
    frames = _frames(device, np.asarray(fit.device_params))
    out = []
    for s, label in enumerate(device.labels):
        others = [r for k, r in enumerate(rms) if k != s and np.isfinite(r)]
        row = {"session": label, "samples": int(np.sum(idx == s)), "rms": rms[s],
               "inconsistent": bool(others) and rms[s] > INCONSISTENT * float(np.median(others))}
        if frames is not None:
            rel = frames[0].inverse().compose(frames[s])
            row["frame_offset_m"] = float(np.linalg.norm(np.asarray(rel.p)))
            row["frame_rotation_rad"] = float(np.linalg.norm(np.asarray(log_so3(rel.R))))
        out.append(row)
    return out


def _frames(device: Sessions, d):
    """Each session's device frame as a Pose, or None when the frame is not per session."""
    blocks = device.frame_blocks(np.zeros((0, device.reading_shape[0])))
    if not blocks:
        return None
    return [frame_from_params(d[np.asarray(idx)]) for idx, _ in blocks]


def summary_lines(rows: list[dict], unit: str) -> list[str]:
    """The session table as report lines."""
    if not rows:
        return []
    lines = [f"sessions: {len(rows)} (one device frame each)"]
    for r in rows:
        where = (f", frame {r['frame_offset_m']:.4g} m / {np.degrees(r['frame_rotation_rad']):.3g} deg from "
                 f"{rows[0]['session']}" if "frame_offset_m" in r else "")
        flag = f"  <- RMS above {INCONSISTENT:g}x the other sessions' median" if r["inconsistent"] else ""
        lines.append(f"  {r['session']}: {r['samples']} samples, RMS {r['rms']:.4g} {unit}{where}{flag}")
    return lines
