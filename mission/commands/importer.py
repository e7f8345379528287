"""`uavloc import --tlog FLIGHT.tlog (--gnb-log GNB.log | --t-trace REC.raw) --users ID:RNTI ... -o
mission.jsonl`: build a mission log from a MAVLink telemetry log and a gNB log or a recording of the
gNB's T tracer (see mission/importer.py for the time-stamp convention of the gNB log)."""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

log = logging.getLogger(__name__)

HELP = "build a mission log from a MAVLink tlog (GPS track) and a gNB log (ranges), aligned by time"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tlog", type=Path, required=True, help="MAVLink telemetry log with GLOBAL_POSITION_INT")
    p.add_argument("--gnb-log", type=Path,
                   help="gNB log: lines starting with a UTC time stamp (UNIX seconds or ISO 8601), then an rtt "
                        "reply, an OAI Msg2 timing_offset line or an SRS ToA line")
    p.add_argument("--t-trace", type=Path, metavar="REC.raw",
                   help="a recording of the gNB's T tracer made with OAI's `record` (trace mode: RAR TA, TA commands "
                        "and SRS peak, started before the UEs attached)")
    p.add_argument("--t-messages", type=Path, metavar="FILE",
                   help="the gNB's T_messages.txt, for a recording that lacks the server's own (a recording "
                        "that has its own is decoded with it; a different FILE is then warned about and ignored)")
    p.add_argument("--t-interval", type=float, default=0.25, metavar="S",
                   help="--t-trace: one range per UE every S seconds of the gNB's clock (default 0.25)")
    p.add_argument("--users", nargs="+", required=True, metavar="ID:RNTI[:GROUND_ALT_M]",
                   help="users to keep: id, RNTI in hex as OAI prints it, optional ground altitude AMSL [m] "
                        "(default: the origin's); a user without any range is a warning naming it, an error "
                        "when no user has one")
    p.add_argument("-o", "--out", type=Path, required=True, help="mission log to write (replaced)")
    p.add_argument("--origin", metavar="LAT,LON,ALT", help="mission origin (default: HOME_POSITION, else first fix)")
    p.add_argument("--time-base", choices=("auto", "system", "tlog"), default="auto",
                   help="UTC of the autopilot clock from SYSTEM_TIME (system) or the tlog's receive stamps "
                        "(tlog); auto: system when present")
    p.add_argument("--gnb-time-offset", type=float, default=0.0, metavar="S",
                   help="seconds added to every gNB log time stamp")
    p.add_argument("--mu", type=int, choices=(0, 1, 2, 3), help="numerology of Msg2 lines (they do not print it)")
    p.add_argument("--fs", type=float, metavar="HZ", help="sampling rate of SRS peak lines [Hz]")
    p.add_argument("--max-speed", type=float, default=60.0, metavar="M/S",
                   help="a faster move between two fixes is a GPS jump (error); default 60")
    p.add_argument("--max-gap", type=float, default=3.0, metavar="S",
                   help="drop measurements in a track gap longer than this [s]; default 3")
    p.add_argument("--truth", nargs="+", metavar="ID=LAT,LON,ALT", help="known user positions (writes a truth line)")
    p.add_argument("--noise", type=Path, metavar="FILE.json",
                   help="noise section for the header (JSON written by `uavloc calibrate --format json`)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")


def parse_users(specs: list[str]):
    """`ID:RNTI[:GROUND_ALT_M]` -> ImportUser list (RNTI in hex, optional 0x)."""
    from mission.importer import ImportUser
    from uavloc.errors import ImportDataError

    users = []
    for spec in specs:
        parts = spec.split(":")
        if len(parts) not in (2, 3) or not parts[0]:
            raise ImportDataError(f"--users {spec!r}: expected ID:RNTI[:GROUND_ALT_M], e.g. ue1:4601")
        try:
            rnti = int(parts[1], 16)
        except ValueError:
            raise ImportDataError(f"--users {spec!r}: RNTI {parts[1]!r} is not hexadecimal") from None
        if not 0 < rnti <= 0xFFFF:
            raise ImportDataError(f"--users {spec!r}: RNTI must be 0x0001..0xFFFF")
        ground = None
        if len(parts) == 3:
            ground = _finite(parts[2], f"--users {spec!r} ground altitude")
        users.append(ImportUser(parts[0], rnti, ground))
    return users


def _finite(text: str, what: str) -> float:
    from uavloc.errors import ImportDataError

    try:
        v = float(text)
    except ValueError:
        raise ImportDataError(f"{what}: {text!r} is not a number") from None
    if not math.isfinite(v):
        raise ImportDataError(f"{what}: {text!r} is not finite")
    return v


def parse_lla(text: str, what: str) -> tuple[float, float, float]:
    """`LAT,LON,ALT` -> floats, range-checked."""
    from uavloc.errors import ImportDataError

    parts = text.split(",")
    if len(parts) != 3:
        raise ImportDataError(f"{what} {text!r}: expected LAT,LON,ALT")
    lat, lon, alt = (_finite(p, what) for p in parts)
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise ImportDataError(f"{what} {text!r}: latitude or longitude out of range")
    return lat, lon, alt


def parse_positions(specs: list[str] | None, what: str) -> dict[str, tuple[float, float, float]]:
    """`ID=LAT,LON,ALT` ... -> {id: (lat, lon, alt)}."""
    from uavloc.errors import ImportDataError

    out = {}
    for spec in specs or []:
        uid, sep, rest = spec.partition("=")
        if not sep or not uid:
            raise ImportDataError(f"{what} {spec!r}: expected ID=LAT,LON,ALT")
        out[uid] = parse_lla(rest, f"{what} {uid}")
    return out


def run(args: argparse.Namespace) -> int:
    from estimator.geodesy import Origin
    from estimator.noise import NoiseModel
    from mission.importer import import_flight, read_gnb_log, read_t_trace, read_tlog_gps
    from uavloc.errors import ImportDataError, UavlocError

    for name in ("max_speed", "max_gap"):
        v = getattr(args, name)
        if not (v > 0 and math.isfinite(v)):
            raise ImportDataError(f"--{name.replace('_', '-')} must be a positive number, got {v}")
    if args.fs is not None and not (args.fs > 0 and math.isfinite(args.fs)):
        raise ImportDataError(f"--fs must be a positive number, got {args.fs}")
    if (args.gnb_log is None) == (args.t_trace is None):
        raise ImportDataError("give the ranges as either --gnb-log FILE or --t-trace REC.raw (one of them)")
    if not (args.t_interval > 0 and math.isfinite(args.t_interval)):
        raise ImportDataError(f"--t-interval must be a positive number, got {args.t_interval}")
    if not math.isfinite(args.gnb_time_offset):
        raise ImportDataError("--gnb-time-offset must be finite")
    users = parse_users(args.users)
    origin = Origin(*parse_lla(args.origin, "--origin")) if args.origin else None
    truth = parse_positions(args.truth, "--truth")
    noise = None
    if args.noise is not None:
        try:
            doc = json.loads(args.noise.read_text(encoding="utf-8"))
            noise = NoiseModel.from_log_dict(doc.get("noise", doc))
        except (OSError, ValueError, AttributeError, RecursionError) as exc:
            raise ImportDataError(f"--noise {args.noise}: not a JSON noise section ({exc})") from exc
        except UavlocError as exc:
            raise ImportDataError(f"--noise {args.noise}: {exc}") from exc

    track = read_tlog_gps(args.tlog, time_base=args.time_base, max_speed_mps=args.max_speed)
    why_absent = None
    if args.t_trace is not None:
        tt = read_t_trace(args.t_trace, mu=1 if args.mu is None else args.mu,
                          fs_hz=46.08e6 if args.fs is None else args.fs, interval_s=args.t_interval,
                          time_offset_s=args.gnb_time_offset, t_messages=args.t_messages)
        meas, counts, why_absent = tt.measurements, tt.counts, tt.why_no_range
        log.info("%s: %d events (T_messages.txt: %s), %d SRS (%d stale), %d TA commands (%d applied), %d RTTs; "
                 "%d ranges kept", args.t_trace, counts.events, tt.t_messages, counts.srs, counts.srs_stale,
                 counts.ta_commands, counts.ta_applied, counts.rtts, len(meas))
        if not meas:
            raise ImportDataError(f"{args.t_trace}: no round trip in the recording: {tt.why_empty()}")
    else:
        if args.t_messages is not None:
            raise ImportDataError("--t-messages goes with --t-trace (the T-tracer recording it decodes)")
        meas, gsum = read_gnb_log(args.gnb_log, mu=args.mu, fs_hz=args.fs, time_offset_s=args.gnb_time_offset)
        log.info("%s: %s measurements, %d error replies, %d SRS lines without a Msg2 before them",
                 args.gnb_log, dict(gsum.counts) or 0, gsum.errors, gsum.unpaired_srs)
    source = args.t_trace if args.t_trace is not None else args.gnb_log
    config = {"importer": "uavloc import", "tlog": args.tlog.name,
              ("t_trace" if args.t_trace is not None else "gnb_log"): source.name,
              "time_base": track.time_base, "clock_offset_s": track.clock_offset_s,
              "gnb_time_offset_s": args.gnb_time_offset}
    summary = import_flight(track, meas, users, args.out, origin=origin, fs_hz=args.fs, noise=noise,
                            truth_lla=truth, max_gap_s=args.max_gap, config=config, why_absent=why_absent,
                            source="T-tracer recording" if args.t_trace is not None else "gNB log")
    doc = {"out": str(summary.path), "fixes": summary.fixes, "measurements": summary.measurements,
           "per_user": summary.per_user, "dropped_outside_track": summary.dropped_outside,
           "dropped_unknown_rnti": {f"{k:04x}": v for k, v in summary.dropped_unknown_rnti.items()},
           "start_utc": summary.start_utc, "duration_s": summary.duration_s, "time_base": summary.time_base,
           "users_without_ranges": summary.users_without_ranges}
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        print(f"{summary.path}: {summary.fixes} GPS fixes, {summary.measurements} ranges "
              f"({', '.join(f'{k}: {v}' for k, v in summary.per_user.items())}) over {summary.duration_s:.0f} s "
              f"from {summary.start_utc}")
        for uid, why in summary.users_without_ranges.items():
            print(f"  user {uid}: no range ({why})")
    return 0
