"""report.html: one self-contained page (figures inlined as base64 PNG) of a report document."""

from __future__ import annotations

import base64
import html

from estimator.noise import NoiseModel
from mission.report.statistics import sigma_text

#: the rows of the page's mission table: (report.json `mission` key, label)
MISSION_ROWS = (("command_line", "command"), ("scenario", "scenario"), ("mission_file", "mission file"),
                ("mission", "mission"), ("seed", "seed"), ("planner", "planner"), ("start_utc", "date (UTC)"),
                ("log_file", "mission log"), ("uavloc_version", "uavloc version"))


def html_page(doc: dict, pngs: dict[str, bytes], captions: dict[str, str] | None = None) -> str:
    """The page of a report document (mission.report.document): its summary and users are the
    result document's (mission.result.Result.to_document), as `--json` prints them; the mission
    table its `mission` section; each figure captioned (and its alt text) by `captions[name]`
    (mission.report.figures.figure_title), else by its name."""
    esc = html.escape
    captions = captions or {}
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
    mission = doc.get("mission") or {}
    facts = "".join(f'<tr><th>{esc(label)}</th><td class="l">{esc(str(mission[key]))}</td></tr>'
                    for key, label in MISSION_ROWS if mission.get(key) is not None)
    facts_table = f'<table class="facts">{facts}</table>' if facts else ""

    def figure(name: str, data: bytes) -> str:
        text = esc(captions.get(name, name.replace("_", " ")))
        return (f'<figure id="{esc(name)}"><img alt="{text}" '
                f'src="data:image/png;base64,{base64.b64encode(data).decode("ascii")}">'
                f"<figcaption>{esc(name)}.png: {text}</figcaption></figure>")

    imgs = "\n".join(figure(name, data) for name, data in pngs.items())
    noise = NoiseModel.from_log_dict(doc["noise"])
    flown = doc["flown_m"]
    o = doc["origin"]
    duration = "" if doc["duration_s"] is None else f" in {doc['duration_s']:.0f} s"
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{esc(doc["title"])}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; max-width: 1000px; }}
table {{ border-collapse: collapse; }} td, th {{ border: 1px solid #bbb; padding: 3px 8px; text-align: right; }}
table.facts th {{ text-align: left; }} td.l {{ text-align: left; font-family: monospace; }}
figure {{ margin: 1em 0; }} img {{ max-width: 100%; border: 1px solid #ddd; }}
</style></head><body>
<h1>{esc(doc["title"])}</h1>
{facts_table}
<p>Status: <b>{esc(str(doc["status"]))}</b> ({esc(str(doc["reason"]))}); {doc["measurements"]} ranges at
{doc["keyframes"]} keyframes; {"–" if flown is None else f"{flown:.0f}"} m flown{duration}.
Origin {o["lat_deg"]:.7f}, {o["lon_deg"]:.7f}, {o["alt_m"]:.1f} m.
Noise model {esc(sigma_text(noise))}, σ<sub>GPS</sub> = {noise.sigma_gps_m:.3g} m.</p>
<table><tr><th>user</th><th>lat [deg]</th><th>lon [deg]</th><th>alt [m]</th><th>95 % bound [m]</th>
<th>error [m]</th><th>bias [m]</th><th>ranges</th><th>ambiguous</th></tr>
{"".join(rows)}
</table>
{imgs}
</body></html>
"""
