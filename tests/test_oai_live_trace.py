"""Trace mode against the user's own OAI gNB and nrUE build (`UAVLOC_OAI`, marker `oai`): a gNB with
SRS and its T tracer, its own pair of processes (tests/test_oai_live.py runs the SA pair of the
recorded transcripts). Skipped with a sentence naming UAVLOC_OAI when it is unset."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mission.gnb import GnbConfig, OaiGnbClient
from mission.gnb.probe import probe_gnb
from tests.test_oai_live import (
    BUILD_ENV,
    CONF,
    GNB_ARGS,
    OaiRun,
    _conf_with_ports,
    _free_tcp_port,
    _port_open,
    oai_build_missing,
    run,
)
from uavloc.errors import GnbNoMeasurementError

pytestmark = pytest.mark.oai


#: OAI's no-core test mode, where periodic SRS is configured from the start (the UE reads the
#: gNB's reconfig.raw / rbconfig.raw), and the T tracer on a port of this run
TRACE_GNB_ARGS = (*GNB_ARGS, "--do-ra", "--T_stdout", "2", "--T_nowait")
TRACE_UE_ARGS = ("-E", "--rfsim", "--do-ra", "--reconfig-file", "reconfig.raw", "--rbconfig-file", "rbconfig.raw",
                 "--rfsimulator.serveraddr", "127.0.0.1", "--telnetsrv", "--telnetsrv.shrmod", "ciUE")
#: the gNB's line when a --do-ra UE is attached ("(rnti 0x6940) CFRA procedure succeeded!")
_CFRA_DONE = re.compile(r"\(rnti 0x([0-9a-f]{4})\) CFRA procedure succeeded")


def _start_trace_gnb(bundle: OaiRun, run_dir: Path, extra: tuple[str, ...] = ()) -> tuple[int, int]:
    """Write the configuration files (do_SRS = 1, ports of this run) into `run_dir`, start the gNB
    with --do-ra and its T tracer (plus `extra`) and wait until its telnet listens and it wrote
    the UE's rbconfig.raw; returns (telnet port, T port)."""
    run_dir.mkdir()
    gnb_port, ue_port, rfsim_port, t_port = (_free_tcp_port() for _ in range(4))
    gnb_conf = _conf_with_ports((CONF / "gnb.conf").read_text(), gnb_port, rfsim_port)
    gnb_conf = re.sub(r"(gNBs\s*=\s*\(\s*\{)", r"\1\n    do_SRS = 1;", gnb_conf, count=1) if "do_SRS" not in gnb_conf \
        else gnb_conf
    (run_dir / "gnb.conf").write_text(gnb_conf)
    (run_dir / "ue.conf").write_text(_conf_with_ports((CONF / "ue.conf").read_text(), ue_port, rfsim_port))
    bundle.info.update(GNB_LOG=str(run_dir / "gnb.log"), UE_LOG=str(run_dir / "ue.log"))
    bundle._start("gnb", "nr-softmodem", run_dir / "gnb.conf", (*TRACE_GNB_ARGS, "--T_port", str(t_port), *extra),
                  run_dir / "gnb.log")
    # never probe the T port with a bare connect: OAI's T server takes a client that leaves
    # without its event mask as fatal ("T tracer: fatal: T tracer disabled")
    deadline = time.monotonic() + 180.0
    while True:
        ready = {"telnet": _port_open(gnb_port), "rbconfig.raw": (run_dir / "rbconfig.raw").is_file()}
        if all(ready.values()):
            return gnb_port, t_port
        assert time.monotonic() < deadline and not bundle.exited, (
            f"the gNB did not start (exited: {bundle.exited}; ready: {ready}); log {run_dir / 'gnb.log'}")
        time.sleep(0.2)


def _one_telnet_request(port: int, line: str, timeout_s: float = 5.0) -> bytes:
    """What the gNB's telnet server sends back for one request on a fresh connection (no retry)
    within timeout_s [s]: the prompt and the answer, until the server goes quiet for 1 s."""
    answer = b""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout_s) as sock:
        sock.sendall(line.encode() + b"\n")
        sock.settimeout(1.0)
        deadline = time.monotonic() + timeout_s
        with contextlib.suppress(TimeoutError):
            while time.monotonic() < deadline and (got := sock.recv(4096)):
                answer += got
    return answer


def test_trace_mode_probes_the_live_gnb_at_a_distance_the_recordings_lack(tmp_path):
    """A gNB with do_SRS = 1, --do-ra and its T tracer, the nrUE at 225 m from the start (rfsim
    offset 35 samples: an RTT of 70, which no shared recording holds): the trace client, connected
    before the UE attaches, gives its round trip to the sample and its probe passes; `uavloc gnb
    probe --mode trace` started after the attach waits (--wait 4), exits 1 and says why (the RAR, the
    only absolute TA, came before it connected) and how to re-attach, and OAI's T server serves
    that second client after the first."""
    why = oai_build_missing()
    if why is not None:
        pytest.skip(why)
    bundle = OaiRun(build=Path(os.environ[BUILD_ENV]).expanduser(), workdir=tmp_path)
    run_dir = tmp_path / "trace"
    offset = "35"  # samples at 46.08 Msps: 227.9 m one way
    try:
        gnb_port, t_port = _start_trace_gnb(bundle, run_dir, ("--rfsimulator.offset", offset))

        async def body():
            cfg_trace = GnbConfig(port=gnb_port, t_port=t_port, mode="trace", request_timeout_s=5.0,
                                  connect_timeout_s=5.0, trace_max_age_s=5.0)
            async with OaiGnbClient(cfg_trace) as g:
                bundle._start("ue", "nr-uesoftmodem", run_dir / "ue.conf",
                              (*TRACE_UE_ARGS, "--rfsimulator.offset", offset), run_dir / "ue.log")
                rnti = None
                async with asyncio.timeout(240):
                    while rnti is None:
                        assert not bundle.exited, f"OAI exited: {bundle.exited}"
                        m = _CFRA_DONE.search((run_dir / "gnb.log").read_text(errors="replace"))
                        rnti = int(m.group(1), 16) if m else None
                        await asyncio.sleep(0.5)
                    sample = None
                    while sample is None:
                        await g.tracer.wait_for_events(1.0)
                        with contextlib.suppress(GnbNoMeasurementError):
                            sample = await g.measure(rnti)
                probe = await probe_gnb(g, rntis=[rnti], count=3)
                return rnti, sample, g.tracer.status(), probe

        rnti, sample, status, probe = run(body(), timeout_s=300)
        assert probe.ok, probe.lines()
        assert all(abs(s.ta * 12 + s.srs_peak - 70) < 0.5 for s in probe.ues[0].samples), probe.lines()
        rtt = sample.ta * 12 + sample.srs_peak
        assert round(rtt) == 70 and abs(rtt - 70) < 0.5, (sample, status)
        assert status.srs > 0 and not status.missing_events
        proc = subprocess.run([sys.executable, "-m", "mission", "gnb", "probe", "--gnb", f"127.0.0.1:{gnb_port}",
                               "--mode", "trace", "--t-port", str(t_port), "--count", "2", "--wait", "4", "--json"],
                              capture_output=True, text=True, timeout=120)
        doc = json.loads(proc.stdout)
        assert proc.returncode == 1, proc.stdout + proc.stderr
        assert doc["trace"]["connected"] and doc["trace"]["srs"] > 0 and doc["trace"]["rtts"] == 0
        assert "attached before the T trace began" in doc["message"]
        assert "restart the nrUE" in doc["message"] and "waiting for UEs" in proc.stderr, proc.stderr
        assert doc["modes"]["trace"]["served"] and doc["recommended"] == "trace"
        print(f"trace mode at 227.9 m: UE {rnti:04x} TA {sample.ta} peak {sample.srs_peak:+.2f} -> "
              f"RTT {rtt:.2f} samples, range {sample.range_m:.1f} m")
    finally:
        bundle.stop()


def test_the_probe_started_before_the_ue_gives_half_the_downlink_offset(tmp_path):
    """`uavloc gnb probe --mode trace --count 3 --wait 120` started before the nrUE, which starts at
    an rfsim offset of 20 samples on its side only (the gNB's uplink at 0): the probe waits, the UE
    attaches while its T client is connected, and every range is half the round trip of 20
    samples, 65.06 m; an offset set on one side only is the whole round trip. While it waits, the
    gNB's telnet is free: `rfsimu getdistance` on it answers at once."""
    why = oai_build_missing()
    if why is not None:
        pytest.skip(why)
    bundle = OaiRun(build=Path(os.environ[BUILD_ENV]).expanduser(), workdir=tmp_path)
    run_dir = tmp_path / "before"
    probe: subprocess.Popen | None = None
    try:
        gnb_port, t_port = _start_trace_gnb(bundle, run_dir)
        probe = subprocess.Popen([sys.executable, "-m", "mission", "gnb", "probe", "--gnb", f"127.0.0.1:{gnb_port}",
                                  "--mode", "trace", "--t-port", str(t_port), "--count", "3", "--wait", "120",
                                  "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(3.0)
        assert probe.poll() is None, probe.communicate()
        answer = _one_telnet_request(gnb_port, "rfsimu getdistance rfsimu_channel_ue0")
        assert b"softmodem_gnb> " in answer, answer
        bundle._start("ue", "nr-uesoftmodem", run_dir / "ue.conf", (*TRACE_UE_ARGS, "--rfsimulator.offset", "20"),
                      run_dir / "ue.log")
        out, err = probe.communicate(timeout=240)
        doc = json.loads(out)
        assert probe.returncode == 0, out + err
        ranges_m = [s["range_m"] for u in doc["ues"] for s in u["samples"]]
        assert len(ranges_m) == 3 and all(abs(r - 10 * 6.5062) < 0.5 for r in ranges_m), (ranges_m, err)
        print(f"probe before the UE, UE offset 20 samples (130.1 m one side): ranges {ranges_m}; {answer!r}")
    finally:
        if probe is not None and probe.poll() is None:
            probe.kill()
        bundle.stop()
