"""A part's inspection report, as one self-contained HTML page and as PDF.

The page carries everything inline (the colour map as a data URI, the trend
context as small SVG charts), so the HTML file can be mailed as it is and the
PDF renderer needs no network. The PDF is rendered by WeasyPrint (HTML and
CSS to PDF in Python, on the Pango text stack), which lays out the same page
the browser shows: one template, two formats.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime

from .models import ControlChart, InspectionResult

PDF_SYSTEM_PACKAGES = "libpango-1.0-0 libpangoft2-1.0-0 libharfbuzz0b fonts-dejavu-core"
"""What WeasyPrint needs from the system (Debian package names)."""


class PdfUnavailable(RuntimeError):
    """WeasyPrint or the system libraries it loads are not installed."""


@dataclass(frozen=True)
class ReportContext:
    """What a report shows besides the result itself.

    Attributes
    ----------
    colormap_png : bytes or None
        The annotated deviation map (None: no per-point deviations were kept).
    charts : sequence of ControlChart
        The part's control charts (one per comparison point, then fit_rms and
        defects): where this part lies among the last ones.
    recording : str or None
        The recording that holds the part (file name and log time).
    """

    colormap_png: bytes | None
    charts: Sequence[ControlChart]
    recording: str | None = None


def _e(v: object) -> str:
    return html.escape("–" if v is None or v == "" else str(v))


def _num(v: float | None, digits: int = 3) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def _utc(ns: int) -> str:
    try:
        return datetime.fromtimestamp(ns / 1e9, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    except (OverflowError, ValueError, OSError):
        return str(ns)


def _spark(ch: ControlChart, result_id: str, width: int = 220, height: int = 44) -> str:
    """An SVG of the chart's last values with its limits; this part's value circled."""
    vals = [(p.value, p.result_id == result_id, bool(p.rules)) for p in ch.points[-30:]]
    ys = [v for v, _, _ in vals if v is not None]
    lim = ch.limits
    extra = [lim.lcl, lim.ucl] if lim else []
    if not ys:
        return '<span class="muted">no values</span>'
    lo, hi = min(ys + extra), max(ys + extra)
    span = (hi - lo) or 1.0

    def y(v: float) -> float:
        return height - 3 - (v - lo) / span * (height - 6)

    def x(i: int) -> float:
        return 3 + i * (width - 6) / max(len(vals) - 1, 1)

    parts = [f'<svg width="{width}" height="{height}" viewBox="0 0 {width} {height}">']
    if lim:
        for level, colour in ((lim.ucl, "#a15c00"), (lim.lcl, "#a15c00"), (lim.center, "#888")):
            yl = y(level)
            parts.append(
                f'<line x1="0" x2="{width}" y1="{yl:.1f}" y2="{yl:.1f}" stroke="{colour}" '
                'stroke-width="0.7" stroke-dasharray="3,2"/>'
            )
    line = " ".join(f"{x(i):.1f},{y(v):.1f}" for i, (v, _, _) in enumerate(vals) if v is not None)
    parts.append(f'<polyline points="{line}" fill="none" stroke="#1f6f8b" stroke-width="1"/>')
    for i, (value, here, flagged) in enumerate(vals):
        if value is None:
            continue
        fill = "#b3261e" if flagged else "#1f6f8b"
        r = 3.2 if here else 1.6
        stroke = ' stroke="#000" stroke-width="1"' if here else ""
        parts.append(f'<circle cx="{x(i):.1f}" cy="{y(value):.1f}" r="{r}" fill="{fill}"{stroke}/>')
    parts.append("</svg>")
    return "".join(parts)


CSS = """
@page { size: A4; margin: 14mm 12mm; @bottom-right { content: "page " counter(page) " of "
        counter(pages); font-size: 8pt; color: #666; } }
body { font-family: "DejaVu Sans", sans-serif; font-size: 9.5pt; color: #1d2329; }
h1 { font-size: 15pt; margin: 0 0 2mm; } h2 { font-size: 11pt; margin: 5mm 0 2mm; }
table { border-collapse: collapse; width: 100%; } th, td { text-align: left; padding: 1mm 1.5mm;
        border-bottom: 0.3mm solid #d8dce0; } th { color: #555; font-size: 8pt; }
td.num { text-align: right; } .muted { color: #69737d; }
.verdict { display: inline-block; padding: 0.5mm 2mm; color: #fff; font-weight: bold; }
.pass { background: #1b7f3b; } .fail { background: #b3261e; }
.other { background: #a15c00; } img.map { width: 100%; max-height: 120mm; object-fit: contain; }
dl { display: grid; grid-template-columns: max-content 1fr; gap: 0.5mm 4mm; margin: 0; }
dt { color: #555; } dd { margin: 0; word-break: break-all; } tr.failed td { color: #b3261e; }
.trend { page-break-inside: avoid; }
"""


def report_html(result: InspectionResult, ctx: ReportContext) -> str:
    """The report of one inspection as a self-contained HTML page."""
    r = result
    status = r.status.value
    cls = status if status in ("pass", "fail") else "other"
    failing = [c.name for c in r.comparison if c.verdict.value == "fail"]
    rows = []
    for c in r.comparison:
        rows.append(
            f'<tr class="{"failed" if c.verdict.value == "fail" else ""}"><td>{_e(c.name)}</td>'
            f'<td class="num">{_num(c.deviation_mm, 4)}</td><td class="num">{_num(c.lower_mm)}</td>'
            f'<td class="num">{_num(c.upper_mm)}</td><td class="num">{c.support}</td>'
            f"<td>{_e(c.verdict.value)}</td><td>{_e(c.reason or '')}</td></tr>"
        )
    defects = [
        f'<tr><td>{i}</td><td>{_e(f.kind)}</td><td class="num">{f.peak_mm:+.3f}</td>'
        f'<td class="num">{f.area_mm2:.0f}</td><td>{", ".join(f"{v:.1f}" for v in f.center_mm)}'
        f"</td><td>{_e(f.nearest_point)}</td></tr>"
        for i, f in enumerate(r.defects or (), start=1)
    ]
    no_defects = (
        "none" if r.defects is not None else f"not checked ({_e(r.path or 'not measured')})"
    )
    fit = [
        ("RMS", f"{_num(r.rms_mm, 4)} mm"),
        ("inliers", None if r.inlier_fraction is None else f"{100 * r.inlier_fraction:.1f} %"),
        ("converged", r.converged), ("stopped", r.stop_reason), ("iterations", r.iterations),
        ("observability", _num(r.observability)),
        ("weak directions", ", ".join(r.weak_directions) or "none"),
        ("ambiguous pose", r.ambiguous), ("runner-up score", _num(r.runner_up_score)),
    ]  # fmt: skip
    trace = [
        ("line / station", f"{r.line} / {r.station}"), ("seq", r.seq), ("id", r.id),
        ("part spec version", r.spec_version), ("CAD hash", r.cad_hash), ("tree hash", r.tree_hash),
        ("calibration", r.calibration_id), ("software", r.software_version),
        ("measured on", r.path),
        ("recording", ctx.recording),
    ]  # fmt: skip
    trends = []
    for ch in ctx.charts:
        cap = ch.capability
        if cap is None:
            capability = ""
        elif cap.capability_note:
            capability = f"n = {cap.n}: {_e(cap.capability_note)}"
        else:
            capability = (f"n = {cap.n}, Cp {_num(cap.cp, 2)}, Cpk {_num(cap.cpk, 2)}, "
                          f"Pp {_num(cap.pp, 2)}, Ppk {_num(cap.ppk, 2)}")  # fmt: skip
        here = next((p for p in ch.points if p.result_id == r.id), None)
        rules = ", ".join(here.rules) if here is not None and here.rules else "none"
        limits = (f"{_num(ch.limits.lcl, 4)} .. {_num(ch.limits.ucl, 4)}" if ch.limits
                  else _e(ch.limits_note))  # fmt: skip
        trends.append(
            f'<tr class="trend"><td>{_e(ch.feature)}</td><td>{_spark(ch, r.id)}</td>'
            f"<td>{limits}</td><td>{_e(rules)}</td><td>{capability}</td></tr>"
        )
    img = (
        f'<img class="map" alt="deviation map" src="data:image/png;base64,'
        f'{base64.b64encode(ctx.colormap_png).decode()}">'
        if ctx.colormap_png
        else '<p class="muted">No per-point deviations were kept for this part.</p>'
    )

    def dl(pairs: Sequence[tuple[str, object]]) -> str:
        return "<dl>" + "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in pairs) + "</dl>"

    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Inspection report {_e(r.serial)}</title>
<style>{CSS}</style></head><body>
<h1>Inspection report: {_e(r.part)} {_e(r.serial)}</h1>
<p><span class="verdict {cls}">{_e(status.upper())}</span> &nbsp; triggered {_utc(r.triggered_ns)}
{f"&nbsp; failing: {_e(', '.join(failing))}" if failing else ""}
{f'<br><span class="muted">{_e(r.reason)}</span>' if r.reason else ""}</p>
<h2>Deviation map</h2>{img}
<h2>Comparison points</h2>
<table><thead><tr><th>point</th><th>deviation mm</th><th>lower mm</th><th>upper mm</th>
<th>support</th><th>verdict</th><th></th></tr></thead>
<tbody>{"".join(rows) or '<tr><td colspan="7" class="muted">none</td></tr>'}</tbody></table>
<h2>Surface defects</h2>
<table><thead><tr><th>#</th><th>kind</th><th>peak mm</th><th>area mm²</th><th>centre mm (CAD)</th>
<th>nearest point</th></tr></thead>
<tbody>{"".join(defects) or f'<tr><td colspan="6" class="muted">{no_defects}</td></tr>'}</tbody>
</table>
<h2>Fit</h2>{dl(fit)}
<h2>Traceability</h2>{dl(trace)}
<h2>Trend context</h2>
<p class="muted">The last parts of {_e(r.part)} on each control chart; this part circled, run
rules in red.</p>
<table><thead><tr><th>feature</th><th>last parts</th><th>control limits</th>
<th>rules here</th><th>capability</th></tr></thead><tbody>{"".join(trends)}</tbody></table>
</body></html>"""


def report_pdf(page: str) -> bytes:
    """The report page as PDF bytes.

    Raises
    ------
    PdfUnavailable
        WeasyPrint, or the Pango libraries it loads, are not installed.
    """
    try:
        import weasyprint  # its import loads Pango: a missing library fails here
    except (ImportError, OSError) as exc:
        raise PdfUnavailable(
            "PDF reports need WeasyPrint (pip install weasyprint) and the system "
            f"packages {PDF_SYSTEM_PACKAGES} (apt-get install)"
        ) from exc
    pdf: bytes = weasyprint.HTML(string=page).write_pdf()
    return pdf
