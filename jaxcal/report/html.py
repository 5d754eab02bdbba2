"""Self-contained interactive HTML: the calibration report (`report_html`) and the comparison of two runs
(`compare_html`).

One file each, working offline: CSS and JavaScript are inline and written here (no library, no CDN),
and a Content-Security-Policy allows only this page's own script (by its SHA-256) and no network
fetch. The report has the quality summary, a before/after error chart per sample drawn as inline SVG
by the script (log scale; circles training, squares held-out; a tooltip with the sample's errors; legend
entries toggle their series), the parameter table (a click on a header sorts it; `?sort=KEY&dir=desc`
in the URL sorts on load), health warnings, the verdict, provenance, and below the Markdown report
rendered statically. Text from inputs (robot, file and parameter names, warnings) is escaped in the
HTML, travels to the script only as JSON data (with `<`, `>` and `&` as \\u escapes) and reaches the
page only through `textContent`: nothing from data is ever parsed as HTML or run. When the script has
drawn the page it sets `document.body.dataset.ready = "1"`.
"""

from __future__ import annotations

import base64
import hashlib
import html
import json

import numpy as np

BLANK = (None, "")  # an empty table cell
UNIT_SCALE = {"length": (1e3, "mm"), "angle": (1e3, "mrad")}  # change and standard error shown in mm / mrad

CSS = """
body{font-family:system-ui,sans-serif;max-width:1150px;margin:1.5em auto;padding:0 1em;color:#222}
h1{font-size:1.6em}h2{margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;font-size:.88em;margin:.5em 0}td,th{border:1px solid #ccc;padding:2px 8px;text-align:right}
td:first-child,th:first-child{text-align:left}th{background:#f4f4f4}img{max-width:100%}code{background:#f4f4f4}
table.sortable th{cursor:pointer;user-select:none}table.sortable th[aria-sort=ascending]::after{content:" \\25B2"}
table.sortable th[aria-sort=descending]::after{content:" \\25BC"}
.ok{color:#17692a;font-weight:bold}.bad{color:#b00020;font-weight:bold}
.legend{display:flex;gap:.6em;flex-wrap:wrap;margin:.3em 0}
.legend button{border:1px solid #bbb;background:#fff;border-radius:4px;padding:2px 8px;cursor:pointer;font:inherit}
.legend button[aria-pressed=false]{opacity:.35;text-decoration:line-through}
.swatch{display:inline-block;width:10px;height:10px;margin-right:5px;vertical-align:middle}
#tip{position:absolute;display:none;background:#222;color:#fff;padding:4px 8px;border-radius:4px;font-size:.85em;
pointer-events:none;white-space:nowrap}
svg .pt{stroke:#222;stroke-width:.5}svg text{font-size:12px;fill:#333}svg .grid{stroke:#e4e4e4}
.static{border-top:3px solid #ddd;margin-top:2.5em}
"""

SORT_JS = r"""
function cellValue(td, type) {
  var v = td.getAttribute("data-v");
  if (type === "num") { var x = parseFloat(v); return isNaN(x) ? null : x; }
  return (v === null ? td.textContent : v).toLowerCase();
}
function sortTable(table, key, dir) {
  var ths = table.tHead.rows[0].cells, col = -1, type = "text";
  for (var i = 0; i < ths.length; i++) {
    if (ths[i].getAttribute("data-key") === key) {
      col = i; type = ths[i].getAttribute("data-type");
      ths[i].setAttribute("aria-sort", dir === "desc" ? "descending" : "ascending");
    } else { ths[i].removeAttribute("aria-sort"); }
  }
  if (col < 0) { return false; }
  var body = table.tBodies[0], rows = Array.prototype.slice.call(body.rows), sign = dir === "desc" ? -1 : 1;
  rows.sort(function (r1, r2) {
    var a = cellValue(r1.cells[col], type), b = cellValue(r2.cells[col], type);
    if (a === null || b === null) { return a === null ? (b === null ? 0 : 1) : -1; }
    return a < b ? -sign : (a > b ? sign : 0);
  });
  rows.forEach(function (r) { body.appendChild(r); });
  table.setAttribute("data-sorted", key + ":" + dir);
  return true;
}
window.jaxcalSort = function (key, dir) {
  var done = false;
  document.querySelectorAll("table.sortable").forEach(function (t) { done = sortTable(t, key, dir) || done; });
  return done;
};
function setUpSorting() {
  document.querySelectorAll("table.sortable").forEach(function (t) {
    Array.prototype.forEach.call(t.tHead.rows[0].cells, function (th) {
      th.addEventListener("click", function () {
        sortTable(t, th.getAttribute("data-key"), th.getAttribute("aria-sort") === "ascending" ? "desc" : "asc");
      });
    });
  });
  var q = new URLSearchParams(window.location.search);
  if (q.get("sort")) { window.jaxcalSort(q.get("sort"), q.get("dir") === "desc" ? "desc" : "asc"); }
}
"""

CHART_JS = r"""
var NS = "http://www.w3.org/2000/svg";
var COLOR = {before: "#9e9e9e", after: "#1f77b4"};
function svgEl(tag, attrs, parent) {
  var e = document.createElementNS(NS, tag);
  Object.keys(attrs).forEach(function (k) { e.setAttribute(k, attrs[k]); });
  if (parent) { parent.appendChild(e); }
  return e;
}
function fmt(v) { return v === null || v === undefined ? "n/a" : Number(v).toPrecision(4); }
function drawChart(holder, legend, tip, data) {
  var W = 1000, H = 380, L = 70, R = 15, T = 15, B = 45, splits = data.splits, total = 0, vals = [];
  splits.forEach(function (s) {
    total += s.before.length;
    s.before.concat(s.after).forEach(function (v) { if (v > 0) { vals.push(v); } });
  });
  if (!vals.length) { vals = [1e-3, 1]; }
  var lo = Math.floor(Math.log10(Math.min.apply(null, vals))), hi = Math.ceil(Math.log10(Math.max.apply(null, vals)));
  if (hi <= lo) { hi = lo + 1; }
  function x(i) { return L + (W - L - R) * (i + 0.5) / Math.max(total, 1); }
  function y(v) { var l = Math.log10(Math.max(v, Math.pow(10, lo))); return T + (H - T - B) * (1 - (l - lo) / (hi - lo)); }
  var svg = svgEl("svg", {viewBox: "0 0 " + W + " " + H, width: "100%", role: "img", id: "errchart"}, holder);
  for (var d = lo; d <= hi; d++) {
    svgEl("line", {x1: L, x2: W - R, y1: y(Math.pow(10, d)), y2: y(Math.pow(10, d)), "class": "grid"}, svg);
    svgEl("text", {x: L - 6, y: y(Math.pow(10, d)) + 4, "text-anchor": "end"}, svg).textContent = "1e" + d;
  }
  svgEl("text", {x: 16, y: (T + H - B) / 2, transform: "rotate(-90 16 " + (T + H - B) / 2 + ")", "text-anchor": "middle"},
        svg).textContent = "position error [mm] (log)";
  var offset = 0;
  splits.forEach(function (s) {
    var n = s.before.length;
    if (offset > 0) { svgEl("line", {x1: x(offset - 0.5), x2: x(offset - 0.5), y1: T, y2: H - B, stroke: "#555",
                                     "stroke-dasharray": "5,4"}, svg); }
    svgEl("text", {x: (x(offset) + x(offset + n - 1)) / 2, y: H - 12, "text-anchor": "middle"}, svg).textContent =
      s.label + " (" + n + " samples)";
    ["before", "after"].forEach(function (kind) {
      var g = svgEl("g", {"class": "series", "data-series": s.id + "-" + kind, fill: COLOR[kind]}, svg);
      s[kind].forEach(function (v, i) {
        var cx = x(offset + i), cy = y(v), mk = s.id === "heldout"
          ? svgEl("rect", {x: cx - 4, y: cy - 4, width: 8, height: 8}, g) : svgEl("circle", {cx: cx, cy: cy, r: 4}, g);
        mk.setAttribute("class", "pt");
        mk.setAttribute("data-split", s.id);
        mk.setAttribute("data-kind", kind);
        mk.setAttribute("data-i", String(i));
      });
      var b = document.createElement("button");
      b.type = "button";
      b.setAttribute("aria-pressed", "true");
      b.setAttribute("data-series", s.id + "-" + kind);
      var sw = document.createElement("span");
      sw.className = "swatch";
      sw.style.background = COLOR[kind];
      sw.style.borderRadius = s.id === "heldout" ? "0" : "50%";
      b.appendChild(sw);
      b.appendChild(document.createTextNode((kind === "before" ? "nominal" : "calibrated") + ", " + s.label));
      b.addEventListener("click", function () {
        var on = b.getAttribute("aria-pressed") !== "true";
        b.setAttribute("aria-pressed", on ? "true" : "false");
        g.style.display = on ? "" : "none";
      });
      legend.appendChild(b);
    });
    offset += n;
  });
  var bySplit = {};
  splits.forEach(function (s) { bySplit[s.id] = s; });
  svg.addEventListener("mousemove", function (ev) {
    var t = ev.target;
    if (!t.classList || !t.classList.contains("pt")) { tip.style.display = "none"; return; }
    var s = bySplit[t.getAttribute("data-split")], i = Number(t.getAttribute("data-i"));
    tip.textContent = s.label + " sample " + i + ": nominal " + fmt(s.before[i]) +
      " mm, calibrated " + fmt(s.after[i]) + " mm";
    tip.style.left = (ev.pageX + 12) + "px";
    tip.style.top = (ev.pageY + 12) + "px";
    tip.style.display = "block";
  });
  svg.addEventListener("mouseleave", function () { tip.style.display = "none"; });
}
"""

REPORT_JS = SORT_JS + CHART_JS + r"""
document.addEventListener("DOMContentLoaded", function () {
  var data = JSON.parse(document.getElementById("chart-data").textContent);
  drawChart(document.getElementById("chart"), document.getElementById("legend"), document.getElementById("tip"), data);
  setUpSorting();
  document.body.dataset.ready = "1";
});
"""

COMPARE_JS = SORT_JS + r"""
document.addEventListener("DOMContentLoaded", function () {
  setUpSorting();
  document.body.dataset.ready = "1";
});
"""


# -- building blocks ------------------------------------------------------------------------------------
def esc(text) -> str:
    """Text from anywhere as HTML text (quotes too: safe in attributes)."""
    return html.escape(str(text), quote=True)


def json_script(obj) -> str:
    """JSON to embed in `<script type="application/json">`: `<`, `>`, `&` and line separators as \\u escapes,
    so no text in it can end the element or start markup."""
    text = json.dumps(obj, allow_nan=False)
    for c in "<>&\u2028\u2029":
        text = text.replace(c, f"\\u{ord(c):04x}")
    return text


def fmt(v, spec=".4g") -> str:
    """A number for a table cell; "n/a" for None."""
    return "n/a" if v is None else format(v, spec)


def _num_attr(v) -> str:
    return "" if v is None or not np.isfinite(v) else f" data-v='{float(v)!r}'"


def table(columns, rows, table_id=None, sortable=False) -> str:
    """An HTML table. columns: (key, title, type "num"/"text"); rows: lists of cells, each a number (shown
    with `fmt`, sorted by value), None ("n/a"), a (value, shown text) pair, or text (escaped)."""
    head = "".join(f"<th data-key='{esc(k)}' data-type='{t}'>{esc(title)}</th>" for k, title, t in columns)
    body = []
    for row in rows:
        cells = []
        for cell in row:
            if isinstance(cell, tuple):
                cells.append(f"<td{_num_attr(cell[0])}>{esc(cell[1])}</td>")
            elif cell is None or isinstance(cell, (int, float)) and not isinstance(cell, bool):
                cells.append(f"<td{_num_attr(cell)}>{fmt(cell)}</td>")
            else:
                cells.append(f"<td>{esc(cell)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    attrs = (f" id='{esc(table_id)}'" if table_id else "") + (" class='sortable'" if sortable else "")
    return f"<table{attrs}><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def page(title: str, body: str, script: str) -> str:
    """A whole HTML document; its Content-Security-Policy admits only `script` (by hash), inline styles and
    images beside the file, and nothing from the network."""
    digest = base64.b64encode(hashlib.sha256(script.encode()).digest()).decode()
    csp = f"default-src 'none'; script-src 'sha256-{digest}'; style-src 'unsafe-inline'; img-src 'self' data:"
    return (f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
            f"<meta http-equiv='Content-Security-Policy' content=\"{csp}\">"
            f"<meta name='viewport' content='width=device-width'><title>{esc(title)}</title><style>{CSS}</style></head>\n"
            f"<body>\n{body}\n<script>{script}</script>\n</body></html>\n")


def markdown_body(markdown_text: str) -> str:
    """Markdown as HTML by markdown-it-py (a dependency of rich) with raw HTML off: a tag in the text is shown."""
    from markdown_it import MarkdownIt

    return MarkdownIt("commonmark", {"html": False}).enable("table").render(markdown_text)


def _get(d, *path):
    for key in path:
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return d


# -- the report ---------------------------------------------------------------------------------------
def quality_rows(summary: dict) -> list[list]:
    """(quantity, before, after) rows of the quality summary: RMS on each split, validation, conditioning,
    observability indices and whatever the summary's `quality` block holds."""
    rows = []
    for split, label in (("train", "training"), ("heldout", "held-out")):
        for key, unit in (("position_mm", "mm"), ("orientation_mrad", "mrad")):
            r = _get(summary, "rms", split, key)
            if r:
                rows.append([f"{label} RMS {key.split('_')[0]} [{unit}]", r.get("before"), r.get("after")])
    v = summary.get("validation")
    if v:
        rows.append([f"validation RMS position [mm] ({v.get('samples')} samples)", _get(v, "before", "position_mm"),
                     _get(v, "after", "position_mm")])
    ident = summary.get("identifiability") or {}
    rows.append(["estimated / free parameters", BLANK, f"{ident.get('estimated')} / {ident.get('free')}"])
    rows.append(["condition number (scaled Jacobian)", BLANK, ident.get("condition_number_scaled")])
    for key, value in (ident.get("observability") or {}).items():
        if key.startswith("O"):
            rows.append([f"observability {key}", BLANK, value])
    quality = summary.get("quality") or {}
    for split, axes in (quality.get("per_axis") or {}).items():
        label = "held-out" if split == "heldout" else "training"
        for axis, v in axes.items():
            rows.append([f"{label} RMSE {axis} [mm] (R\u00b2 {fmt(v.get('r2'), '.8g')})", BLANK, v.get("rmse_mm")])
    if "correlated_pairs" in quality:
        pairs = quality["correlated_pairs"]
        shown = "; ".join(f"{p['a']} ~ {p['b']} {p['rho']:+.3f}" for p in pairs[:6]) + (" ..." if len(pairs) > 6 else "")
        rows.append([f"parameter pairs with |rho| > {quality.get('correlation_threshold', 0.8):g}", BLANK,
                     f"{len(pairs)}" + (f": {shown}" if pairs else "")])
    return rows


def chart_data(summary: dict) -> dict:
    """The chart's series: per split, the per-sample position errors (mm) before and after calibration."""
    labels = {"train": "training", "heldout": "held-out"}
    splits = []
    for split, label in labels.items():
        e = _get(summary, "per_sample_errors_mm", split)
        if e and e.get("before") is not None and e.get("after") is not None:
            splits.append({"id": split, "label": label, "before": [float(v) for v in e["before"]],
                           "after": [float(v) for v in e["after"]]})
    return {"splits": splits}


def parameter_table(parameters) -> str:
    """The sortable parameter table: change and standard error in mm / mrad, and change / standard error."""
    rows = []
    for p in parameters:
        k, unit = UNIT_SCALE.get(p.get("unit"), (1.0, ""))
        se = p.get("std_error")
        z = p["change"] / se if se else None
        rows.append([p["name"], p["nominal"], p["identified"], p["change"] * k, None if se is None else se * k,
                     None if z is None else abs(z), unit, p.get("status", "")])
    cols = [("name", "parameter", "text"), ("nominal", "nominal [m, rad]", "num"), ("identified", "identified", "num"),
            ("change", "change [mm, mrad]", "num"), ("std_error", "std. error", "num"), ("abs_z", "|change| / std. error", "num"),
            ("unit", "unit", "text"), ("status", "status", "text")]
    return table(cols, rows, "params", sortable=True)


def _health(health) -> str:
    if not health:
        return ""
    if health.get("ok"):
        return "<p class='ok'>Health: ok.</p>"
    items = "".join(f"<li>{esc(w)}</li>" for w in health.get("warnings", []))
    return (f"<p class='bad'>Health: {len(health.get('warnings', []))} warning(s); do not use this calibration before "
            f"reading them.</p><ul id='warnings'>{items}</ul>")


def _verdict(verdict) -> str:
    if not verdict:
        return ""
    rows = [[c["check"], c["value"] if isinstance(c["value"], (int, float)) and not isinstance(c["value"], bool)
             else str(c["value"]), str(c["threshold"]), "pass" if c["pass"] else "FAIL"] for c in verdict["checks"]]
    cls, word = ("ok", "PASS") if verdict["pass"] else ("bad", "FAIL")
    return (f"<h2>Verdict</h2><p id='verdict' class='{cls}'>{word}</p>" +
            table([("check", "check", "text"), ("value", "value", "num"), ("threshold", "threshold", "text"),
                   ("result", "", "text")], rows))


def _provenance(prov) -> str:
    if not prov:
        return ""
    rows = [["jaxcal", f"{prov.get('jaxcal_version')} (commit {prov.get('git_commit') or 'n/a'})"],
            ["python / jax / numpy", f"{prov.get('python')} / {prov.get('jax')} / {prov.get('numpy')}"],
            ["time (UTC)", prov.get("timestamp_utc", "")], ["config hash", prov.get("config_hash", "")],
            ["command line", " ".join(prov.get("command_line", []))]]
    rows += [[f"{role}: {f['path']}", f"sha256 {f['sha256'] or 'n/a (not a file)'}"] for role, f in prov.get("inputs", {}).items()]
    return "<h2>Provenance</h2>" + table([("what", "", "text"), ("value", "", "text")], rows)


def report_html(summary: dict, markdown_text: str) -> str:
    """The interactive calibration report of a `run_job` summary, with the Markdown report below."""
    robot = summary.get("robot", "")
    s = summary.get("samples") or {}
    sup = summary.get("supported")
    sup_line = "" if not sup else (
        f"<p>Corrections the data support (&ge; {esc(sup['sigma'])} standard errors): {len(sup['kept'])} of "
        f"{len(sup['kept']) + len(sup['dropped'])}; with only those, held-out RMS "
        f"{fmt(_get(sup, 'heldout', 'position_mm'))} mm.</p>")
    body = "".join([
        f"<h1>Calibration report: {esc(robot)}</h1>", _health(summary.get("health")),
        f"<p>Data <code>{esc(summary.get('data', ''))}</code>: {esc(s.get('total'))} samples "
        f"({esc(s.get('train'))} training, {esc(s.get('heldout'))} held-out), {esc(summary.get('device', ''))} device.</p>",
        "<h2>Quality summary</h2>",
        table([("quantity", "", "text"), ("before", "nominal", "num"), ("after", "calibrated", "num")],
              quality_rows(summary), "quality"), sup_line,
        "<h2>Error per sample, nominal vs calibrated</h2>",
        "<p>Click a legend entry to hide or show its series; point at a marker for its errors.</p>",
        "<div class='legend' id='legend'></div><div id='chart'></div><div id='tip'></div>",
        f"<script type='application/json' id='chart-data'>{json_script(chart_data(summary))}</script>",
        _verdict(summary.get("verdict")),
        "<h2>Parameters</h2><p>Click a column header to sort.</p>", parameter_table(summary.get("parameters", [])),
        _provenance(summary.get("provenance")),
        f"<section class='static'>{markdown_body(markdown_text)}</section>"])
    return page(f"Calibration report: {robot}", body, REPORT_JS)


# -- comparison of two runs -----------------------------------------------------------------------------
def parameter_differences(params_a, params_b) -> list[dict]:
    """Per parameter of both runs: identified values, standard errors, difference b - a and its z-score
    (difference over the combined standard error, None without both standard errors)."""
    by_name = {p["name"]: p for p in params_b}
    out = []
    for pa in params_a:
        pb = by_name.get(pa["name"])
        if pb is None:
            continue
        diff = pb["identified"] - pa["identified"]
        sa, sb = pa.get("std_error"), pb.get("std_error")
        se = None if sa is None or sb is None else float(np.hypot(sa, sb))
        out.append({"name": pa["name"], "unit": pa.get("unit"), "a": pa["identified"], "a_se": sa, "b": pb["identified"],
                    "b_se": sb, "diff": diff, "z": diff / se if se else None})
    return out


def comparison_rows(a: dict, b: dict) -> list[list]:
    """(quantity, run A, run B, B - A) rows: RMS after calibration on each split and validation, samples, conditioning."""
    def diff(x, y):
        return None if x is None or y is None else y - x

    rows = []
    for what, path in (("training RMS [mm]", ("rms", "train", "position_mm", "after")),
                       ("held-out RMS [mm]", ("rms", "heldout", "position_mm", "after")),
                       ("validation RMS [mm]", ("validation", "after", "position_mm")),
                       ("nominal held-out RMS [mm]", ("rms", "heldout", "position_mm", "before")),
                       ("samples", ("samples", "total")),
                       ("estimated parameters", ("identifiability", "estimated")),
                       ("condition number", ("identifiability", "condition_number_scaled"))):
        va, vb = _get(a, *path), _get(b, *path)
        rows.append([what, va, vb, diff(va, vb)])
    return rows


def compare_html(a: dict, b: dict, label_a: str, label_b: str) -> str:
    """The comparison page of two `jaxcal calibrate` results (results.json contents) of one robot."""
    rows = []
    for d in parameter_differences(a.get("parameters", []), b.get("parameters", [])):
        k, unit = UNIT_SCALE.get(d["unit"], (1.0, ""))
        scaled = [None if v is None else v * k for v in (d["a_se"], d["b_se"], d["diff"])]
        rows.append([d["name"], d["a"], scaled[0], d["b"], scaled[1], scaled[2], d["z"],
                     None if d["z"] is None else abs(d["z"]), unit])
    cols = [("name", "parameter", "text"), ("a", "A identified [m, rad]", "num"), ("a_se", "A std. error", "num"),
            ("b", "B identified", "num"), ("b_se", "B std. error", "num"), ("diff", "B - A", "num"), ("z", "z", "num"),
            ("abs_z", "|z|", "num"), ("unit", "unit of errors / difference", "text")]
    run_rows = [[label, r.get("data", ""), _get(r, "provenance", "timestamp_utc") or "n/a",
                 (_get(r, "provenance", "config_hash") or "n/a")[:12]] for label, r in (("A: " + label_a, a), ("B: " + label_b, b))]
    body = "".join([
        f"<h1>Calibration runs compared: {esc(a.get('robot', ''))}</h1>",
        table([("run", "run", "text"), ("data", "data", "text"), ("time", "time (UTC)", "text"), ("hash", "config hash", "text")],
              run_rows, "runs"),
        "<h2>Errors after calibration</h2>",
        table([("quantity", "", "text"), ("a", "A", "num"), ("b", "B", "num"), ("diff", "B - A", "num")], comparison_rows(a, b),
              "rms"),
        "<h2>Parameters</h2><p>Difference of the calibrated values; z = (B - A) / sqrt(se_A<sup>2</sup> + se_B<sup>2</sup>): "
        "|z| above 3 means the two runs disagree beyond their noise. Click a header to sort.</p>",
        table(cols, rows, "diffs", sortable=True)])
    return page(f"Calibration runs compared: {a.get('robot', '')}", body, COMPARE_JS)


__all__ = ["chart_data", "compare_html", "comparison_rows", "esc", "json_script", "markdown_body", "page",
           "parameter_differences", "parameter_table", "quality_rows", "report_html", "table"]
