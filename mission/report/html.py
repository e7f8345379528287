"""report.html: one self-contained page (figures inlined as base64 PNG) of a report document."""

from __future__ import annotations

import base64
import html


def html_page(doc: dict, pngs: dict[str, bytes]) -> str:
    """The page of a report document (mission.report.document): its summary and users are the
    result document's (mission.result.Result.to_document), as `--json` prints them."""
    esc = html.escape
    rows = []
    for u in doc["users"]:
        def cell(v, fmt="{:.2f}"):
            return "–" if v is None else (fmt.format(v) if isinstance(v, float) else esc(str(v)))
        rows.append(
            "<tr>" + "".join(f"<td>{c}</td>" for c in (
                esc(u["id"]), cell(u["lat_deg"], "{:.7f}"), cell(u["lon_deg"], "{:.7f}"), cell(u["alt_m"], "{:.1f}"),
                cell(u["error_bound_95_m"]), cell(u.get("error_m")), cell(u.get("bias_m")),
                str(u.get("measurements", 0)),
                "yes" if u.get("ambiguous") else "no",
            )) + "</tr>"
        )
    imgs = "\n".join(
        f'<figure><img alt="{esc(name)}" src="data:image/png;base64,{base64.b64encode(data).decode("ascii")}">'
        f"<figcaption>{esc(name.replace('_', ' '))}</figcaption></figure>"
        for name, data in pngs.items()
    )
    n = doc["noise"]["range_sigma_m"]
    flown = doc["flown_m"]
    o = doc["origin"]
    duration = "" if doc["duration_s"] is None else f" in {doc['duration_s']:.0f} s"
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{esc(doc["title"])}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; max-width: 1000px; }}
table {{ border-collapse: collapse; }} td, th {{ border: 1px solid #bbb; padding: 3px 8px; text-align: right; }}
figure {{ margin: 1em 0; }} img {{ max-width: 100%; border: 1px solid #ddd; }}
</style></head><body>
<h1>{esc(doc["title"])}</h1>
<p>Status: <b>{esc(str(doc["status"]))}</b> ({esc(str(doc["reason"]))}); {doc["measurements"]} ranges at
{doc["keyframes"]} keyframes; {"–" if flown is None else f"{flown:.0f}"} m flown{duration}.
Origin {o["lat_deg"]:.7f}, {o["lon_deg"]:.7f}, {o["alt_m"]:.1f} m.
Noise model σ(d) = {n["range_s0_m"]:.3g} + {n["range_a_m"]:.3g}·exp({n["range_b_per_m"]:.3g}·d) m,
σ<sub>GPS</sub> = {doc["noise"]["sigma_gps_m"]:.3g} m.</p>
<table><tr><th>user</th><th>lat [deg]</th><th>lon [deg]</th><th>alt [m]</th><th>95 % bound [m]</th>
<th>error [m]</th><th>bias [m]</th><th>ranges</th><th>ambiguous</th></tr>
{"".join(rows)}
</table>
{imgs}
</body></html>
"""
