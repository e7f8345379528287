"""`rtt` mode against the user's own OAI build patched with patches/oai-2025.w36 (`UAVLOC_OAI`,
marker `oai`): the gNB answers `rtt pdcch_order <rnti>` by ordering the UE to a random access.

A gNB with do_SRS = 1, `--do-ra` and the `rtt` telnet module, and OAI's nrUE with
NRUE_PDCCH_ORDER_CSS=1 (patches/oai-2025.w36/README.md), both on free loopback ports. Skipped with
a sentence naming UAVLOC_OAI when it is unset, and with one naming the patch when the build lacks it.
"""

from __future__ import annotations

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

from tests.test_oai_live import BUILD_ENV, CONF, GNB_ARGS, OaiRun, _conf_with_ports, _free_tcp_port, _port_open
from tests.test_oai_live import oai_build_missing as _stock_build_missing
from tests.test_oai_live_trace import _CFRA_DONE, TRACE_UE_ARGS

pytestmark = pytest.mark.oai

#: the patched gNB's telnet modules and the string its nr-softmodem carries
RTT_GNB_ARGS = (*("ci,o1,rtt" if a == "ci,o1" else a for a in GNB_ARGS), "--do-ra")
PATCH_MARK = b"rtt: PDCCH order for UE"
#: one rfsim sample at 46.08 Msps, one way [m]
SAMPLE_M = 299_792_458.0 / 46.08e6
GNB_PROMPT = b"softmodem_gnb> "


def oai_rtt_build_missing(env: dict[str, str] | None = None) -> str | None:
    """Why the patched-OAI tests cannot run (a sentence naming UAVLOC_OAI or the patch), or None."""
    why = _stock_build_missing(env)
    if why is not None:
        return why
    build = Path((os.environ if env is None else env)[BUILD_ENV]).expanduser()
    if not (build / "libtelnetsrv_rtt.so").is_file() or PATCH_MARK not in (build / "nr-softmodem").read_bytes():
        return (f"{BUILD_ENV}={build} is not patched with patches/oai-2025.w36/uavloc-rtt-pdcch-order.patch "
                "(no libtelnetsrv_rtt.so, or nr-softmodem without the PDCCH order): see its README")
    return None


def telnet(port: int, *lines: str, timeout_s: float = 30.0) -> list[bytes]:
    """Send each line on one connection; each answer up to the gNB's prompt."""
    out = []
    with socket.create_connection(("127.0.0.1", port), timeout=timeout_s) as sock:
        for line in lines:
            sock.sendall(line.encode() + b"\n")
            buf = b""
            while GNB_PROMPT not in buf and b"softmodem_5Gue> " not in buf:
                got = sock.recv(65536)
                assert got, f"connection closed after {line!r}: {buf!r}"
                buf += got
            if line.startswith("rfsimu"):  # the rfsimulator's line comes after the prompt
                sock.settimeout(0.5)
                with contextlib.suppress(TimeoutError):
                    while got := sock.recv(65536):
                        buf += got
                sock.settimeout(timeout_s)
            out.append(buf)
    return out


@pytest.fixture(scope="module")
def patched(tmp_path_factory):
    why = oai_rtt_build_missing()
    if why is not None:
        pytest.skip(why)
    work = tmp_path_factory.mktemp("oai_rtt")
    bundle = OaiRun(build=Path(os.environ[BUILD_ENV]).expanduser(), workdir=work)
    run_dir = work / "run"
    run_dir.mkdir()
    gnb_port, ue_port, rfsim_port, t_port = _free_tcp_port(), _free_tcp_port(), _free_tcp_port(), _free_tcp_port()
    gnb_conf = _conf_with_ports((CONF / "gnb.conf").read_text(), gnb_port, rfsim_port)
    (run_dir / "gnb.conf").write_text(re.sub(r"(gNBs\s*=\s*\(\s*\{)", r"\1\n    do_SRS = 1;", gnb_conf, count=1))
    (run_dir / "ue.conf").write_text(_conf_with_ports((CONF / "ue.conf").read_text(), ue_port, rfsim_port))
    bundle.info.update(GNB_LOG=str(run_dir / "gnb.log"), UE_LOG=str(run_dir / "ue.log"),
                       GNB_TELNET_PORT=str(gnb_port), UE_TELNET_PORT=str(ue_port), T_PORT=str(t_port))
    old = os.environ.get("NRUE_PDCCH_ORDER_CSS")
    os.environ["NRUE_PDCCH_ORDER_CSS"] = "1"
    try:
        # its T server too (nobody connects before the UE attached: the trace test's late UE)
        bundle._start("gnb", "nr-softmodem", run_dir / "gnb.conf",
                      (*RTT_GNB_ARGS, "--T_stdout", "2", "--T_nowait", "--T_port", str(t_port)), run_dir / "gnb.log")
        deadline = time.monotonic() + 180
        while not ((run_dir / "rbconfig.raw").is_file() and _port_open(gnb_port)):
            assert time.monotonic() < deadline and not bundle.exited, f"the gNB did not start: {bundle.exited}"
            time.sleep(0.3)
        bundle._start("ue", "nr-uesoftmodem", run_dir / "ue.conf", TRACE_UE_ARGS, run_dir / "ue.log")
        deadline = time.monotonic() + 300
        while True:
            m = _CFRA_DONE.search((run_dir / "gnb.log").read_text(errors="replace"))
            if m:
                bundle.info["UE_RNTI"] = m.group(1)
                break
            assert time.monotonic() < deadline and not bundle.exited, f"the UE did not attach: {bundle.exited}"
            time.sleep(0.5)
        yield bundle
    finally:
        if old is None:
            os.environ.pop("NRUE_PDCCH_ORDER_CSS", None)
        else:
            os.environ["NRUE_PDCCH_ORDER_CSS"] = old
        bundle.stop()


def _alive(bundle: OaiRun) -> None:
    assert bundle.gnb_process_alive() and "ue" not in bundle.exited, bundle.exited
    stats = telnet(bundle.gnb_port, "o1 stats")[0]
    assert int(bundle.info["UE_RNTI"], 16) in json.loads(stats[: stats.index(b"\nOK\n")])["O1-Operational"]["ues"]


def _set_distance(bundle: OaiRun, samples: int) -> float:
    """Both sides to `samples` rfsim samples (0.5 m more: the rfsimulator floors); the distance
    the gNB's rfsimulator says it set [m]."""
    metres = samples * SAMPLE_M + 0.5
    got = telnet(bundle.gnb_port, f"rfsimu setdistance rfsimu_channel_ue0 {metres:.3f}")[0]
    telnet(bundle.ue_port, f"rfsimu setdistance rfsimu_channel_enB0 {metres:.3f}")
    m = re.search(rb"new \(exact\) distance ([0-9.]+) m", got)
    assert m, got
    return float(m.group(1))


def test_the_order_ranges_the_ue_to_the_sample_at_three_distances(patched):
    """`uavloc gnb probe --mode rtt --count 5` at 45.5, 97.6 and 136.6 m (7, 15 and 21 samples,
    reached in steps of at most 4 samples, 26 m, on both sides): every range within half a sample
    of the distance the rfsimulator set; the gNB and the UE still attached."""
    rnti = patched.info["UE_RNTI"]
    samples = 0
    for target in (7, 15, 21):
        while samples < target:
            samples = min(target, samples + 4)
            here = _set_distance(patched, samples)
            time.sleep(1.0)
        proc = subprocess.run([sys.executable, "-m", "mission", "gnb", "probe", "--gnb",
                               f"127.0.0.1:{patched.gnb_port}", "--mode", "rtt", "--rnti", rnti, "--count", "5",
                               "--json"], capture_output=True, text=True, timeout=300)
        doc = json.loads(proc.stdout)
        ranges = [s["range_m"] for u in doc["ues"] for s in u["samples"]]
        assert proc.returncode == 0 and len(ranges) == 5, proc.stdout + proc.stderr
        assert all(abs(r - here) <= SAMPLE_M / 2 + 1e-6 for r in ranges), (here, ranges)
        print(f"rfsim {here:.2f} m: ranges {ranges}")
    _alive(patched)


def test_unknown_bad_and_missing_rnti_are_error_lines_and_the_gnb_lives(patched):
    rnti = int(patched.info["UE_RNTI"], 16)
    other = (rnti + 1) % 0xFFFD or 1
    answers = telnet(patched.gnb_port, f"rtt pdcch_order {other:04x}", "rtt pdcch_order zz", "rtt pdcch_order",
                     f"rtt pdcch_order {rnti:04x} {other:04x}")
    assert answers[0] == f"error rnti {other:04x} not connected\n".encode() + GNB_PROMPT
    assert answers[1] == b"error bad rnti 'zz'\n" + GNB_PROMPT
    assert answers[2].startswith(b"error missing rnti")
    lines = answers[3].decode().splitlines()
    assert re.fullmatch(rf"rnti {rnti:04x} ta \d+ mu 1 srs_peak \d+\.0000 fs 46080000", lines[0]), lines
    assert lines[1] == f"error rnti {other:04x} not connected"
    _alive(patched)


def test_auto_finds_the_order_served_and_prefers_it(patched):
    """`uavloc gnb probe --mode auto` on the patched gNB: rtt served (it answered), recommended."""
    proc = subprocess.run([sys.executable, "-m", "mission", "gnb", "probe", "--gnb", f"127.0.0.1:{patched.gnb_port}",
                           "--mode", "auto", "--count", "2", "--json"], capture_output=True, text=True, timeout=300)
    doc = json.loads(proc.stdout)
    assert doc["modes"]["rtt"]["served"] and doc["recommended"] == "rtt", proc.stdout + proc.stderr
    assert doc["mode"] == "rtt" and proc.returncode == 0, proc.stdout + proc.stderr
    _alive(patched)


def test_trace_mode_orders_a_ue_that_attached_before_its_t_client(patched):
    """`uavloc gnb probe --mode trace` on the patched gNB whose UE attached before any T client:
    the probe sends it one PDCCH order, the ordered access's RAR comes on the T trace with its
    absolute TA, and the trace ranges the UE within one sample of the rfsim distance."""
    here = _set_distance(patched, 21)  # where the first test left it (136.62 m), or set now
    time.sleep(1.0)
    gnb_log = Path(patched.info["GNB_LOG"])
    orders_before = gnb_log.read_text(errors="replace").count(PATCH_MARK.decode())
    proc = subprocess.run([sys.executable, "-m", "mission", "gnb", "probe", "--gnb", f"127.0.0.1:{patched.gnb_port}",
                           "--mode", "trace", "--t-port", patched.info["T_PORT"], "--rnti", patched.info["UE_RNTI"],
                           "--count", "3", "--wait", "20", "--json"], capture_output=True, text=True, timeout=300)
    doc = json.loads(proc.stdout)
    ranges = [s["range_m"] for u in doc["ues"] for s in u["samples"]]
    assert proc.returncode == 0 and len(ranges) == 3, proc.stdout + proc.stderr
    assert all(abs(r - here) <= SAMPLE_M + 1e-6 for r in ranges), (here, ranges)
    assert gnb_log.read_text(errors="replace").count(PATCH_MARK.decode()) > orders_before  # the probe ordered it
    print(f"trace mode after a PDCCH order: rfsim {here:.2f} m, ranges {ranges}")
    _alive(patched)
