"""The calibration job behind `jaxcal calibrate`: fit on a training split, check on held-out data,
and one Markdown + PNG report (and the same as HTML) with the numbers a reviewer asks for.

`run_job` computes everything in memory; `write_job` writes the files into a hidden staging folder
and swaps it in as the output folder only after every file exists (so a failure leaves no partial
output, and no stale file of an earlier run survives). Every string that comes from an input (robot,
parameter and column names, paths, warnings) is escaped in the Markdown, and the HTML renderer passes
no raw HTML through, so a name such as `<img onerror=...>` is shown as text.
"""

from __future__ import annotations

import dataclasses
import html
import os
import re

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jaxcal.fit.core import x_scale  # noqa: E402
from jaxcal.fit.identifiable import observability_indices  # noqa: E402
from jaxcal.fit.identify import identify  # noqa: E402
from jaxcal.fit.sessions import readings_for  # noqa: E402
from jaxcal.io_atomic import replace_folder, write_json_atomic, write_text_atomic  # noqa: E402
from jaxcal.report.html import markdown_body, report_html  # noqa: E402
from jaxcal.report.plots import plain_text, plot_convergence, save_atomic  # noqa: E402


@dataclasses.dataclass
class JobResult:
    fit: object  # FitResult on the training split
    nominal: object  # nominal robot with only the device frame / marker fitted (the fair "before")
    train: object
    test: object | None
    summary: dict
    supported_a: np.ndarray | None = None  # robot parameters with only the corrections of >= SUPPORTED_SIGMA kept


SUPPORTED_SIGMA = 2.0  # a correction the data support: |change| >= this many standard errors


def _rms(e):
    return None if e is None or len(e) == 0 else float(np.sqrt(np.mean(np.asarray(e) ** 2)))


def _errors(fit, data):
    """Per-sample position (and orientation) errors, mm and mrad."""
    pe, oe = fit.errors(data)
    return (None if pe is None else pe * 1e3), (None if oe is None else oe * 1e3)


def identifiability_summary(fit) -> dict:
    """What the data could identify: counts, the base set, undetermined parameters, conditioning."""
    idx = np.asarray(fit.info["estimated_index"], int)
    units = tuple(fit.robot.units) + tuple(fit.device.units)
    if len(idx):
        Js = np.asarray(fit.jacobian)[:, idx] * x_scale(units)[idx]
        s = np.linalg.svd(Js, compute_uv=False)
        cond = float(s[0] / max(s[-1], 1e-300))
        observability = observability_indices(Js) if s[-1] > 0 else None
    else:
        cond = observability = None
    return {
        "free": int(len(fit.estimated) + len(fit.undetermined)),
        "estimated": len(fit.estimated),
        "undetermined": [n for n in fit.undetermined if n not in fit.held_at_start],
        "held_at_start": list(fit.held_at_start),
        "regrouped": list(fit.regrouped),
        "no_effect": list(fit.no_effect),
        "condition_number_scaled": cond,
        "observability": observability,
        "poorly_determined": [n for n in fit.poorly_determined() if n not in fit.undetermined],
        "weak_directions": [{"sigma": s_, "direction": d} for s_, d in fit.weak_directions],
    }


def parameter_rows(fit) -> list[dict]:
    """One row per parameter: nominal, identified, change and standard error (SI: m, rad)."""
    nom = np.concatenate([fit.robot.nominal_np, fit.device.nominal_np])
    est = np.asarray(fit.a_full)
    se = fit.std_errors
    units = tuple(fit.robot.units) + tuple(fit.device.units)
    rows = []
    for i, n in enumerate(fit.names):
        status = fit.status(n)
        rows.append({"name": n, "unit": units[i], "nominal": float(nom[i]), "identified": float(est[i]),
                     "change": float(est[i] - nom[i]), "std_error": float(se[n]) if n in se else None, "status": status})
    return rows


def supported_corrections(fit, k: float = SUPPORTED_SIGMA):
    """(a, kept, dropped): the robot parameters at nominal except the corrections the data support, |identified -
    nominal| >= k standard errors (every parameter with a standard error is judged; the others stay nominal)."""
    nominal = np.asarray(fit.robot.nominal_np, float)
    a = nominal.copy()
    kept, dropped = [], []
    for name, se in fit.std_errors.items():
        if name not in fit.robot.names:
            continue
        i = fit.robot.names.index(name)
        change = float(fit.a[i]) - nominal[i]
        if abs(change) >= k * se:
            a[i] = float(fit.a[i])
            kept.append(name)
        else:
            dropped.append(name)
    return a, kept, dropped


def _rms_of(fit, data) -> dict | None:
    """Position (mm) and orientation (mrad) RMS of a fit on data; None without data."""
    if data is None or len(data) == 0:
        return None
    pe, oe = _errors(fit, data)
    out = {"position_mm": _rms(pe)}
    if oe is not None:
        out["orientation_mrad"] = _rms(oe)
    return out


def supported_summary(robot, fit, train, test, identify_kw):
    """The model with only the supported corrections (`supported_corrections`), its device frame / marker refitted
    on the training samples: (a, summary dict with the kept and dropped names and its train / held-out RMS)."""
    a, kept, dropped = supported_corrections(fit)
    kw = {k: v for k, v in identify_kw.items() if k not in ("free", "progress")}
    refit = identify(robot, train, free=(), a0=a, **kw)
    return a, {"sigma": SUPPORTED_SIGMA, "kept": kept, "dropped": dropped, "train": _rms_of(refit, train),
               "heldout": _rms_of(refit, test),
               "device_params": dict(zip(refit.device.names, np.asarray(refit.device_params).tolist()))}


CORRELATED = 0.8  # |rho| above which a parameter pair is listed (FIGAROH's quality report uses the same)


def axis_quality(fit, data) -> dict | None:
    """Per position axis of the readings (x, y, z; marker k of several: x1 ... z_K): RMSE (mm) of the calibrated
    model and R^2 = 1 - sum r^2 / sum (y - mean y)^2; None for a device whose readings hold no point, and for
    several sessions (each has its own frame)."""
    device = fit.device
    if device.marker_reading not in ("point", "points", "frame") or len(data) == 0:  # sessions: one frame each
        return None
    meas = device.points(readings_for(device, data))
    pred = device.points(fit.predict(data.q))
    r, y = (meas - pred).reshape(len(data), -1), meas.reshape(len(data), -1)
    k = y.shape[1] // 3
    labels = [f"{a}{i + 1 if k > 1 else ''}" for i in range(k) for a in "xyz"]
    ss_tot = np.sum((y - y.mean(axis=0)) ** 2, axis=0)
    return {lab: {"rmse_mm": float(np.sqrt(np.mean(r[:, j] ** 2)) * 1e3),
                  "r2": float(1.0 - np.sum(r[:, j] ** 2) / ss_tot[j]) if ss_tot[j] > 0 else None}
            for j, lab in enumerate(labels)}


def correlated_pairs(fit, threshold: float = CORRELATED) -> list[dict]:
    """Pairs of estimated parameters whose estimates correlate with |rho| > threshold (from the fit's
    covariance), strongest first."""
    if fit.covariance is None:
        return []
    C = np.asarray(fit.covariance)
    sd = np.sqrt(np.maximum(np.diag(C), 1e-300))
    rho = C / np.outer(sd, sd)
    i, j = np.triu_indices(len(sd), 1)
    keep = np.abs(rho[i, j]) > threshold
    pairs = [{"a": fit.estimated[a], "b": fit.estimated[b], "rho": float(rho[a, b])} for a, b in zip(i[keep], j[keep])]
    return sorted(pairs, key=lambda p: -abs(p["rho"]))


def quality_summary(fit, train, test) -> dict:
    """FIGAROH's quality report: per-axis RMSE and R^2 on the training and held-out samples, and the correlated
    parameter pairs."""
    out = {"per_axis": {split: axis_quality(fit, d) for split, d in (("train", train), ("heldout", test)) if d is not None},
           "correlated_pairs": correlated_pairs(fit), "correlation_threshold": CORRELATED}
    out["per_axis"] = {k: v for k, v in out["per_axis"].items() if v is not None}
    return out


def quality_lines(quality: dict, limit: int = 8) -> list[str]:
    """The quality block as terminal lines."""
    lines = []
    for split, axes in quality.get("per_axis", {}).items():
        cells = ", ".join(f"{a} {v['rmse_mm']:.4g} mm" + (f" (R^2 {v['r2']:.8g})" if v["r2"] is not None else "")
                          for a, v in axes.items())
        lines.append(f"{'held-out' if split == 'heldout' else 'training'} per axis: {cells}")
    pairs = quality.get("correlated_pairs", [])
    if pairs:
        shown = ", ".join(f"{p['a']} ~ {p['b']} {p['rho']:+.3f}" for p in pairs[:limit])
        more = f" (+{len(pairs) - limit} more in results.json)" if len(pairs) > limit else ""
        lines.append(f"correlated parameter pairs (|rho| > {quality['correlation_threshold']:g}): {shown}{more}")
    else:
        lines.append(f"no estimated parameter pair correlates with |rho| > {quality.get('correlation_threshold', CORRELATED):g}")
    return lines


def run_job(robot, data, holdout: float = 0.25, seed: int = 0, history: bool = True, validation=None,
            **identify_kw) -> JobResult:
    """Fit `robot` on a random (1 - holdout) share of `data`; evaluate both the calibrated and the
    nominal model (device frame / marker fitted) on the training and held-out samples, and on `validation`
    (a separate Dataset measured in the same set-up: the training fit's device frame is used), and the model
    with only the corrections the data support (`supported_summary`).
    history: record the cost per solver step for the convergence plot (one more compile)."""
    train, test = data.split(1.0 - holdout, seed) if holdout > 0 else (data, None)
    if test is not None and len(test) == 0:
        test = None
    fit = identify(robot, train, history=history, **identify_kw)
    nominal = identify(robot, train, free=(), **{k: v for k, v in identify_kw.items() if k != "free"})
    errs = {"train": (_errors(nominal, train), _errors(fit, train))}
    if test is not None:
        errs["heldout"] = (_errors(nominal, test), _errors(fit, test))
    rms = {}
    for split, ((pb, ob), (pa, oa)) in errs.items():
        rms[split] = {"position_mm": {"before": _rms(pb), "after": _rms(pa)}}
        if ob is not None:
            rms[split]["orientation_mrad"] = {"before": _rms(ob), "after": _rms(oa)}
    summary = {
        "robot": robot.name, "data": data.source, "units_in_file": getattr(data, "units", None),
        "device": data.device.kind, "samples": {"total": len(data), "train": len(train), "heldout": 0 if test is None else len(test)},
        "holdout": holdout, "seed": seed, "solver": fit.info.get("solver"),
        "rms": rms, "converged": bool(fit.converged), "iterations": int(fit.iterations),
        "timings_s": {k: float(v) for k, v in fit.timings.items()},
        "identifiability": identifiability_summary(fit), "parameters": parameter_rows(fit),
        "device_params": {"calibrated": dict(zip(fit.device.names, np.asarray(fit.device_params).tolist())),
                          "nominal_robot": dict(zip(nominal.device.names, np.asarray(nominal.device_params).tolist()))},
        "per_sample_errors_mm": {split: {"before": None if v[0][0] is None else v[0][0].tolist(),
                                         "after": None if v[1][0] is None else v[1][0].tolist()} for split, v in errs.items()},
    }
    summary["sessions"] = fit.info.get("sessions", [])
    summary["quality"] = quality_summary(fit, train, test)
    if validation is not None:
        summary["validation"] = {"data": validation.source, "samples": len(validation),
                                 "before": _rms_of(nominal, validation), "after": _rms_of(fit, validation)}
    supported_a, summary["supported"] = supported_summary(robot, fit, train, test, identify_kw)
    summary["heldout_verdict"] = heldout_verdict(summary)
    summary["health"] = job_health(fit, summary)
    return JobResult(fit, nominal, train, test, summary, supported_a)


VERIFY_KEYS = {  # threshold -> where its value is in the summary
    "max_train_rms_mm": ("rms", "train", "position_mm", "after"),
    "max_heldout_rms_mm": ("rms", "heldout", "position_mm", "after"),
    "max_validation_rms_mm": ("validation", "after", "position_mm"),
    "max_heldout_orientation_mrad": ("rms", "heldout", "orientation_mrad", "after"),
    "max_condition_number": ("identifiability", "condition_number_scaled"),
}


def _lookup(summary, path):
    for key in path:
        if not isinstance(summary, dict) or key not in summary:
            return None
        summary = summary[key]
    return summary


def verify(summary: dict, thresholds: dict) -> dict:
    """The pass/fail verdict of a calibration against thresholds (`VERIFY_KEYS`, and `require_health_ok`, default
    true): one check per threshold with its value; a threshold whose quantity the run does not have (no held-out
    or validation samples) fails, so a CI gate never passes on a missing number."""
    unknown = sorted(set(thresholds) - set(VERIFY_KEYS) - {"require_health_ok"})
    if unknown:
        from jaxcal.names import suggestion

        raise ValueError(f"unknown threshold(s) {unknown}{suggestion(unknown[0], list(VERIFY_KEYS) + ['require_health_ok'])}; "
                         f"known: {', '.join(VERIFY_KEYS)}, require_health_ok")
    checks = []
    for key, limit in thresholds.items():
        if key == "require_health_ok":
            continue
        if isinstance(limit, bool) or not isinstance(limit, (int, float)) or not np.isfinite(limit):
            raise ValueError(f"threshold {key!r} must be a finite number, got {limit!r}")
        value = _lookup(summary, VERIFY_KEYS[key])
        checks.append({"check": key, "value": value, "threshold": float(limit),
                       "pass": value is not None and value <= limit})
    if thresholds.get("require_health_ok", True):
        checks.append({"check": "health_ok", "value": summary["health"]["ok"], "threshold": True,
                       "pass": bool(summary["health"]["ok"])})
    return {"pass": all(c["pass"] for c in checks), "checks": checks}


# -- plots ---------------------------------------------------------------------------------------
def plot_errors_per_pose(summary, path):
    """Position error of every sample before and after calibration, training and held-out side by side."""
    splits = [s for s in ("train", "heldout") if s in summary["per_sample_errors_mm"]]
    fig, axes = plt.subplots(1, len(splits), figsize=(6.5 * len(splits), 4.0), squeeze=False, layout="constrained")
    for ax, split in zip(axes[0], splits):
        e = summary["per_sample_errors_mm"][split]
        b, a = np.asarray(e["before"]), np.asarray(e["after"])
        order = np.argsort(-b)
        idx = np.arange(len(b))
        ax.bar(idx, b[order], width=0.9, color="#bbbbbb", label=f"before (RMS {_rms(b):.3g} mm)")
        ax.bar(idx, a[order], width=0.5, color="#1f77b4", label=f"after (RMS {_rms(a):.3g} mm)")
        ax.set_yscale("log")
        ax.set_xlabel("sample (sorted by error before)")
        ax.set_ylabel("position error [mm]")
        ax.set_title(f"{'training' if split == 'train' else 'held-out'} samples ({len(b)})")
        ax.legend(fontsize=9, loc="upper right")
        ax.grid(True, axis="y", which="both", alpha=0.3)
    fig.suptitle(f"{plain_text(summary['robot'])}: error per pose, nominal vs calibrated")
    return save_atomic(fig, path)


def _plane_axes(points):
    """The two coordinate axes along which the measured points spread most (a readable 2-D view)."""
    return tuple(sorted(np.argsort(-np.ptp(points, axis=0))[:2]))


def plot_error_map(job: JobResult, path):
    """Measured points of all samples projected on their widest coordinate plane, coloured by the
    position error before and after (each panel with its own colour scale: after calibration the
    error is often 100x smaller, and its pattern over the workspace is what is left to explain)."""
    data = [d for d in (job.train, job.test) if d is not None]
    pts = np.concatenate([d.device.points(d.y)[:, 0] for d in data]) * 1e3
    before = np.concatenate([_errors(job.nominal, d)[0] for d in data])
    after = np.concatenate([_errors(job.fit, d)[0] for d in data])
    heldout = np.concatenate([np.full(len(d), i == 1) for i, d in enumerate(data)])
    i, j = _plane_axes(pts)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), layout="constrained")
    for ax, err, title in zip(axes, (before, after), ("before (nominal)", "after (calibrated)")):
        vmax = float(np.percentile(err, 98))
        for held, marker in ((False, "o"), (True, "^")):
            sel = heldout == held
            sc = ax.scatter(pts[sel, i], pts[sel, j], c=err[sel], cmap="viridis", vmin=0, vmax=vmax, marker=marker,
                            s=40, edgecolors="k", linewidths=0.3, label="held-out" if held else "training")
        fig.colorbar(sc, ax=ax, label="position error [mm]", shrink=0.9)
        ax.set_title(f"{title}: RMS {_rms(err):.3g} mm")
        ax.set_xlabel(f"{'xyz'[i]} [mm] (device frame)")
        ax.set_ylabel(f"{'xyz'[j]} [mm] (device frame)")
        ax.set_aspect("equal", adjustable="box")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    fig.suptitle(f"{plain_text(job.summary['robot'])}: position error over the workspace (circles training, triangles held-out)")
    return save_atomic(fig, path)


# -- Markdown -------------------------------------------------------------------------------------
_MD_SPECIAL = set("\\`*[]<>|&!")


def _one_line(text) -> str:
    """`text` as one line: control characters (newlines, NUL, escapes) become spaces."""
    return "".join(" " if (ord(c) < 32 or ord(c) == 127) else c for c in str(text))


def md_text(text) -> str:
    """A string from an input (a name, a path, a warning) as literal Markdown text: one line, with the
    characters that start HTML, links, images, code or table cells backslash-escaped."""
    return "".join("\\" + c if c in _MD_SPECIAL else c for c in _one_line(text))


def md_code(text) -> str:
    """A string from an input as a Markdown code span, fenced by more backticks than it holds."""
    text = _one_line(text)
    fence = "`" * (max((len(m) for m in re.findall("`+", text)), default=0) + 1)
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def _fmt(v, spec=".4g"):
    return "n/a" if v is None else format(v, spec)


def _display(row):
    """Change and standard error in mm / mrad (lengths / angles) or plain (gains, scales)."""
    k = 1e3 if row["unit"] in ("length", "angle") else 1.0
    unit = {"length": "mm", "angle": "mrad"}.get(row["unit"], "")
    return row["change"] * k, None if row["std_error"] is None else row["std_error"] * k, unit


def job_health(fit, summary) -> dict:
    """The fit's health record plus the held-out check: a calibrated model no better than the nominal one on
    held-out samples is a warning too."""
    health = fit.health.to_dict()
    h = summary["rms"].get("heldout", {}).get("position_mm")
    if h and h["before"] is not None and h["after"] >= h["before"]:
        health["warnings"] = list(health["warnings"]) + [summary["heldout_verdict"]]
        health["ok"] = False
    return health


def heldout_verdict(summary) -> str | None:
    """One sentence on whether the calibration generalises to the held-out samples."""
    h = summary["rms"].get("heldout", {}).get("position_mm")
    if not h or h["before"] is None:
        return None
    if h["after"] >= h["before"]:
        n, p = summary["samples"]["train"], summary["identifiability"]["estimated"]
        return (f"The calibrated model is no better than the nominal one on held-out samples ({h['before']:.3g} -> "
                f"{h['after']:.3g} mm): {p} parameters from {n} samples overfit or the remaining error is not geometric. "
                "Try fewer parameters (e.g. --free '*.offset'), more samples, or `jaxcal diagnose`.")
    return f"Held-out error reduced by {100 * (1 - h['after'] / h['before']):.0f}% ({h['before']:.3g} -> {h['after']:.3g} mm)."


def session_markdown(rows: list[dict]) -> list[str]:
    """The "Sessions" section: one device frame per session (`fit.sessions.session_summary`)."""
    if not rows:
        return []
    lines = ["## Sessions", "", f"sessions: {len(rows)} (one device frame each); training samples, RMS error and where "
             "each session's frame lies from the first one's.", "",
             "| session | samples | RMS [mm] | frame offset [m] | frame rotation [deg] | |", "|---|---|---|---|---|---|"]
    for r in rows:
        flag = "RMS above 3x the others' median" if r["inconsistent"] else ""
        lines.append(f"| {md_text(r['session'])} | {r['samples']} | {_fmt(r['rms'])} | {_fmt(r.get('frame_offset_m'))} | "
                     f"{_fmt(np.degrees(r['frame_rotation_rad']) if 'frame_rotation_rad' in r else None, '.3g')} | {flag} |")
    return lines + [""]


def job_markdown(summary, images: dict, robot_file: str | None) -> str:
    r = summary["rms"]
    s = summary["samples"]
    health = summary["health"]
    status = ("**Health: ok.**" if health["ok"] else
              f"**Health: {len(health['warnings'])} warning(s); do not use this calibration before reading them.**")
    warnings = [f"- {md_text(w)}" for w in health["warnings"]] + ([""] if health["warnings"] else [])
    lines = [f"# Calibration report: {md_text(summary['robot'])}", "", status, ""] + warnings + [
             f"Data: {md_code(summary['data'])} ({s['total']} samples, {summary['device']} device; units in file "
             f"{summary['units_in_file']}). Training {s['train']}, held-out {s['heldout']} (random split, seed {summary['seed']}).",
             "", "## Errors before and after", "",
             "\"Before\" is the nominal robot with the unknown device frame and marker fitted (the fair baseline).", "",
             "| samples | position RMS before [mm] | after [mm] |" + (" orientation before [mrad] | after [mrad] |"
                                                                    if "orientation_mrad" in r["train"] else ""),
             "|---|---|---|" + ("---|---|" if "orientation_mrad" in r["train"] else "")]
    for split in ("train", "heldout"):
        if split not in r:
            continue
        row = f"| {'training' if split == 'train' else 'held-out'} | {_fmt(r[split]['position_mm']['before'])} | " \
              f"{_fmt(r[split]['position_mm']['after'])} |"
        if "orientation_mrad" in r[split]:
            row += f" {_fmt(r[split]['orientation_mrad']['before'])} | {_fmt(r[split]['orientation_mrad']['after'])} |"
        lines.append(row)
    t = summary["timings_s"]
    verdict = heldout_verdict(summary)
    lines += ["", md_text(verdict)] if verdict else []
    lines += ["", f"Solver {summary['solver']}: {summary['iterations']} iterations, converged {summary['converged']}; "
              f"compile {t.get('compile_s', 0):.2f} s, run {t.get('run_s', 0) * 1e3:.1f} ms.", ""]
    lines += session_markdown(summary.get("sessions", []))
    lines += validation_markdown(summary.get("validation"))
    if summary.get("quality"):
        lines += ["## Quality", ""] + [f"- {md_text(line)}" for line in quality_lines(summary["quality"], limit=20)] + [""]
    ident = summary["identifiability"]
    lines += ["## Identifiability", "",
              f"{ident['estimated']} of {ident['free']} free parameters identified (base set of the weighted Jacobian's "
              f"columns, seed 001 App. III); scaled condition number {_fmt(ident['condition_number_scaled'], '.3g')}.", ""]
    if ident.get("observability"):
        lines.append("Observability indices of the scaled Jacobian (Sun & Hollerbach): " + ", ".join(
            f"{k} {ident['observability'][k]:.4g}" for k in ("O1", "O2", "O3", "O4", "O5")) + ".")
        lines.append("")
    if ident["undetermined"]:
        lines.append(f"Not separable from the others (kept at their prior): {', '.join(map(md_text, ident['undetermined']))}.")
    if ident.get("held_at_start"):
        lines.append("Fitted with the nominal robot at the start, then held: not separable from robot parameters in the "
                     f"full fit, which moved those instead: {', '.join(map(md_text, ident['held_at_start']))}.")
    if ident["poorly_determined"]:
        lines.append("Standard error above 10% of a typical size (1 cm / 0.01 rad): "
                     f"{', '.join(map(md_text, ident['poorly_determined']))}.")
    lines += ["", "## Parameters", "", "| parameter | nominal | identified | change | std. error | unit | status |",
              "|---|---|---|---|---|---|---|"]
    for row in summary["parameters"]:
        ch, se, unit = _display(row)
        lines.append(f"| {md_text(row['name'])} | {row['nominal']:.6g} | {row['identified']:.6g} | {ch:+.4g} | {_fmt(se, '.3g')} | "
                     f"{unit} | {row['status']} |")
    lines += ["", "Nominal and identified values in m / rad; change and standard error in mm / mrad.", "", "## Plots", ""]
    for title, name in images.items():
        lines += [f"### {title}", "", f"![{title}]({name})", ""]
    if robot_file:
        lines += ["## Calibrated robot", "", f"{md_code(robot_file)} (device frame and marker offset are in `results.json`).", ""]
    lines += supported_markdown(summary.get("supported"), summary.get("supported_file"))
    lines += verdict_markdown(summary.get("verdict"))
    return "\n".join(lines)


def _rms_cell(d, key="position_mm"):
    return _fmt(None if d is None else d.get(key))


def validation_markdown(v) -> list[str]:
    """The "Validation data" section: the calibration on a separate file measured in the same set-up."""
    if not v:
        return []
    return ["## Validation data", "", f"{md_code(v['data'])}: {v['samples']} samples, measured apart from the calibration "
            "data (device frame of the training fit).", "", "| | position RMS [mm] |", "|---|---|",
            f"| nominal robot | {_rms_cell(v['before'])} |", f"| calibrated | {_rms_cell(v['after'])} |", ""]


def supported_markdown(sup, file_name) -> list[str]:
    """The section on the model with only the corrections the data support (>= 2 standard errors)."""
    if not sup:
        return []
    where = f" Written as {md_code(file_name)}." if file_name else ""
    return ["## Corrections the data support", "",
            f"{len(sup['kept'])} of {len(sup['kept']) + len(sup['dropped'])} estimated robot corrections are at least "
            f"{sup['sigma']:g} standard errors from nominal; the model with only those (device frame and marker refitted) "
            f"gives training RMS {_rms_cell(sup['train'])} mm and held-out {_rms_cell(sup['heldout'])} mm.{where}", "",
            f"Dropped (within {sup['sigma']:g} standard errors of nominal): {', '.join(map(md_text, sup['dropped'])) or 'none'}.",
            ""]


def verdict_markdown(verdict) -> list[str]:
    """The `--verify` verdict: pass / fail per threshold."""
    if not verdict:
        return []
    lines = ["## Verdict", "", f"**{'PASS' if verdict['pass'] else 'FAIL'}**", "", "| check | value | threshold | |",
             "|---|---|---|---|"]
    for c in verdict["checks"]:
        value = c["value"] if isinstance(c["value"], bool) or c["value"] is None else _fmt(c["value"])
        lines.append(f"| {c['check']} | {value} | {c['threshold']} | {'pass' if c['pass'] else 'FAIL'} |")
    return lines + [""]


_CSS = ("body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}"
        "table{border-collapse:collapse;font-size:0.9em}td,th{border:1px solid #ccc;padding:2px 8px;text-align:right}"
        "td:first-child,th:first-child{text-align:left}img{max-width:100%}code{background:#f4f4f4}")


def job_html(markdown_text: str, title: str) -> str:
    """The Markdown report as one self-contained HTML page (images stay beside it), rendered with
    markdown-it-py (a dependency of rich) with raw HTML off: any tag in the text is shown, never run."""
    body = markdown_body(markdown_text)
    title = html.escape(_one_line(title))
    return (f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{title}</title><style>{_CSS}</style></head>"
            f"<body>\n{body}</body></html>\n")


def supported_file_name(robot_file: str) -> str:
    """`ur10_calibrated.urdf` -> `ur10_calibrated_2sigma.urdf`."""
    stem, ext = os.path.splitext(robot_file)
    return f"{stem}_{SUPPORTED_SIGMA:g}sigma{ext}"


def write_job(out: str, job: JobResult, write_robot=None, robot_file: str | None = None, exports=None) -> list[str]:
    """Write results.json, report.md, report.html (interactive, `jaxcal.report.html.report_html`), the plots,
    verdict.json (after `--verify`) and, via `write_robot(path, a)`, the calibrated robot and the robot with only
    the supported corrections (`supported_file_name(robot_file)`). `exports` maps more plain file names to
    `write(path, a, device_params)` (`jaxcal.robots.exports.export_writers`): each is written for the calibration
    and, under `supported_file_name(name)`, for the supported corrections with their refitted device frame.

    Everything is first written to a hidden staging folder beside `out` and swapped in as `out` only
    when all files exist (`jaxcal.io_atomic.replace_folder`): a failure leaves `out` as it was (the
    staging folder is removed), and files of an earlier run that this one does not write are gone.
    `robot_file` must be a plain file name (`jaxcal.io_atomic.safe_filename`)."""
    for name in [robot_file] + list(exports or ()):
        if name is not None and (os.path.basename(name) != name or name.startswith(".")):
            raise ValueError(f"output file names must be plain file names, got {name!r}")
    os.makedirs(out, exist_ok=True)
    names = replace_folder(out, lambda stage: _write_all(stage, job, write_robot, robot_file, exports or {}))
    return [os.path.join(out, n) for n in names]


def _write_exports(folder, job, exports) -> list[str]:
    """The `exports` files of `write_job` for the calibration and for the supported corrections; their names."""
    names = []
    sup = job.summary.get("supported") or {}
    for name, write in exports.items():
        write(os.path.join(folder, name), np.asarray(job.fit.a), job.summary["device_params"]["calibrated"])
        names.append(name)
        if job.supported_a is not None and "device_params" in sup:
            write(os.path.join(folder, supported_file_name(name)), job.supported_a, sup["device_params"])
            names.append(supported_file_name(name))
    return names


def _write_all(folder, job, write_robot, robot_file, exports):
    images = {"Error per pose": "errors_per_pose.png", "Error over the workspace": "error_map.png",
              "Convergence": "convergence.png"}
    plot_errors_per_pose(job.summary, os.path.join(folder, images["Error per pose"]))
    plot_error_map(job, os.path.join(folder, images["Error over the workspace"]))
    if job.fit.history is not None:
        plot_convergence(job.fit.history, os.path.join(folder, images["Convergence"]),
                         f"{plain_text(job.summary['robot'])}: solver convergence")
    else:
        images.pop("Convergence")
    names = list(images.values())
    extra = {}
    if write_robot is not None and robot_file:
        os.chmod(write_robot(os.path.join(folder, robot_file), np.asarray(job.fit.a)), 0o644)
        names.append(robot_file)
        if job.supported_a is not None:
            extra["supported_file"] = supported_file_name(robot_file)
            os.chmod(write_robot(os.path.join(folder, extra["supported_file"]), job.supported_a), 0o644)
            names.append(extra["supported_file"])
    names += _write_exports(folder, job, exports)
    if "verdict" in job.summary:
        write_json_atomic(os.path.join(folder, "verdict.json"), job.summary["verdict"])
        names.append("verdict.json")
    names += ["report.md", "report.html", "results.json"]
    summary = dict(job.summary, files=names, **extra)
    text = job_markdown(summary, images, robot_file)
    write_text_atomic(os.path.join(folder, "report.md"), text)
    write_text_atomic(os.path.join(folder, "report.html"), report_html(summary, text))
    write_json_atomic(os.path.join(folder, "results.json"), summary)
    return names


__all__ = ["JobResult", "axis_quality", "correlated_pairs", "identifiability_summary", "job_html", "job_markdown", "md_code",
           "md_text", "parameter_rows", "plot_error_map", "plot_errors_per_pose", "quality_lines", "quality_summary", "run_job",
           "supported_corrections", "verify", "write_job"]
