"""``xstack info``: what is in a MeasurementSet, a store or a FITS image (listobs / imhead)."""

from __future__ import annotations

import argparse
from typing import Any

from xstack.cli._storage import add_storage_options


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "info", help="summary of a MeasurementSet, store or FITS image (like listobs/imhead)",
        description="What CASA's listobs and imhead tell. A MeasurementSet or store: fields and "
                    "phase centers, spectral windows, time range and integration, antennas and "
                    "baselines, correlations, the flagged fraction of the real cells (grid "
                    "padding is not data) and the weights against the data's own scatter. A "
                    "FITS image: size, cell, beam, units, frequency, phase and pointing center, "
                    "primary-beam state, mosaic. See docs/info.md.")
    p.add_argument("path", metavar="MS|STORE|FITS", help="MeasurementSet, zarr store or FITS image")
    p.add_argument("--datacolumn", default="DATA",
                   help="MeasurementSet only: the visibility column counted and compared with "
                        "the weights (DATA, CORRECTED_DATA, MODEL_DATA; default DATA)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    add_storage_options(p)
    return p


def _fmt_hz(hz: float | None) -> str:
    if hz is None:
        return "-"
    for unit, scale in (("GHz", 1e9), ("MHz", 1e6), ("kHz", 1e3)):
        if abs(hz) >= scale:
            return f"{hz / scale:.6g} {unit}"
    return f"{hz:.6g} Hz"


def _fmt_s(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.3g} h"
    if seconds >= 60:
        return f"{seconds / 60:.3g} min"
    return f"{seconds:.3g} s"


def data_lines(d: dict[str, Any]) -> list[str]:
    """Human-readable lines for an MS or store summary."""
    kind = "MeasurementSet" if d["kind"] == "ms" else f"store ({d.get('store_kind') or 'zarr'})"
    out = [f"{d['path']}: {kind}, telescope {d['telescope']}"]
    if d.get("format"):
        out.append(f"format     {d['format']}"
                   + (f", written by {', '.join(d['written_by'])}" if d.get("written_by") else "")
                   + (f"; data groups {', '.join(d['data_groups'])}" if d.get("data_groups") else ""))
    t = d["time"]
    if t["start_utc"]:
        out.append(f"time       {t['start_utc']} - {t['end_utc']} UTC ({_fmt_s(t['duration_s'])}), "
                   f"integration {t['integration_s']:.4g} s, {t['n_times']} time stamps"
                   + (f", {t['n_scans']} scan(s)" if t.get("n_scans") else ""))
    out.append(f"fields     {len(d['fields'])}")
    for f in d["fields"]:
        rows = f" ({f['n_rows']} rows)" if "n_rows" in f else ""
        out.append(f"  {f['id']:>3} {f['name']:<20} {f['ra_hms']} {f['dec_dms']}  "
                   f"({f['ra_deg']:.6f}, {f['dec_deg']:+.6f} deg){rows}")
    out.append(f"spectral windows {len(d['spectral_windows'])}")
    for s in d["spectral_windows"]:
        out.append(f"  {s['id']:>3} {s['n_channels']} channels {_fmt_hz(s['first_channel_hz'])} - "
                   f"{_fmt_hz(s['last_channel_hz'])}, width {_fmt_hz(s['channel_width_hz'])}, "
                   f"total {_fmt_hz(s['total_bandwidth_hz'])}; {' '.join(s['correlations'])}")
    b = d["baselines"]
    lengths = "" if b["longest_m"] is None else \
        f", {b['shortest_m']:.1f} m - {b['longest_m']:.1f} m"
    out.append(f"antennas   {d['antennas']['count']}: {' '.join(d['antennas']['names'][:12])}"
               + (" ..." if d["antennas"]["count"] > 12 else ""))
    out.append(f"baselines  {b['count']} cross-correlation{'' if b['count'] == 1 else 's'}{lengths}; "
               f"autocorrelations {'present' if d['autocorrelations'] else 'none'}")
    out.append(f"correlations {' '.join(d['correlations'])}")
    frac = d["flagged_fraction"]
    flagged = "-" if frac is None else f"{frac:.1%}"
    out.append(f"data       {d['real_cells']} visibilities, {flagged} flagged (or zero weight, "
               f"non-finite)" + (f"; {d['padding_cells']} padding cells of the grid not counted"
                                 if d["padding_cells"] else ""))
    w = d["weights"]
    if w["variance_ratio"] is None:
        out.append("weights    too few neighbouring channel/integration pairs to compare with "
                   "the scatter")
    else:
        verdict = "consistent with" if w["consistent"] else "NOT"
        out.append(f"weights    data scatter / sigma from WEIGHT = {w['sigma_ratio']:.3g} "
                   f"(variance ratio {w['variance_ratio']:.3g}, {w['n_pairs']} pairs): {verdict} "
                   "1/sigma^2")
    return out


def image_lines(d: dict[str, Any]) -> list[str]:
    """Human-readable lines for a FITS image summary."""
    out = [f"{d['path']}: FITS image {' x '.join(str(n) for n in d['shape'])}"
           + (f", telescope {d['telescope']}" if d["telescope"] else "")]
    if "cell_arcsec" in d:
        c = d["cell_arcsec"]
        out.append(f"grid       {d['size'][0]} x {d['size'][1]} pixels of {c[0]:.4g}\" x {c[1]:.4g}\" "
                   f"({d['projection']}, {d['frame']}), field {d['field_of_view_arcsec'][0]:.4g}\" x "
                   f"{d['field_of_view_arcsec'][1]:.4g}\"")
        r, p = d["reference"], d["pointing"]
        out.append(f"center     {r['ra_hms']} {r['dec_dms']} ({r['ra_deg']:.6f}, "
                   f"{r['dec_deg']:+.6f} deg)")
        out.append(f"pointing   {p['ra_hms']} {p['dec_dms']} (from {d['pointing_from']})")
    out.append(f"frequency  {_fmt_hz(d['frequency_hz'])}"
               + (f", bandwidth {_fmt_hz(d['bandwidth_hz'])}" if d.get("bandwidth_hz") else ""))
    beam = d["beam"]
    out.append("beam       none in the header" if beam is None else
               f"beam       {beam['major_arcsec']:.4g}\" x {beam['minor_arcsec']:.4g}\", "
               f"PA {beam['pa_deg']:.1f} deg"
               + (" (uv coverage not 2-D: not a beam)" if (d["uv_dimensions"] or 2) < 2 else ""))
    out.append(f"units      {d['bunit'] or '-'}")
    pb = d["primary_beam"]
    state = {True: "corrected", False: "not corrected", None: "not stated (no XSPBCOR)"}
    out.append(f"primary beam {state[pb['corrected']]}"
               + (f", beam file {pb['file']}{'' if pb['file_exists'] else ' (missing)'}"
                  if pb["file"] else "")
               + (f", cutoff {pb['cutoff']:g}" if pb["cutoff"] is not None else ""))
    out.append(f"mosaic     {'yes, ' + str(d['n_pointings']) + ' pointings' if d['mosaic'] else 'no'}")
    out.append(f"pixels     {d['blanked_fraction']:.1%} blanked"
               + (f", min {d['min']:.4g}, max {d['max']:.4g}" if d["min"] is not None else ""))
    return out


def run(args: argparse.Namespace) -> int:
    from xstack._info import info
    from xstack.cli import emit_json
    from xstack.cli._output import result

    d = info(args.path, datacolumn=args.datacolumn)
    if args.json:
        emit_json(d)
        return 0
    # through the common output (stdout, and the --log file)
    result(*(image_lines(d) if d["kind"] == "fits" else data_lines(d)))
    return 0
