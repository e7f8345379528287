"""What a real OAI pair of `uavloc sim --oai` is started with: configuration files and command lines.

The configuration files are the recorded ones of OAI 2025.w36 (sitl_scenarios/data/oai-2025.w36/,
the same as ../shared/data/oai-2025.w36/conf: OAI's `gnb.sa.band78.106prb.rfsim.conf` and
`nrue.uicc.conf`, 106 PRB, μ = 1, n78 at 3319.68 MHz) with the ports of this run, and on the gNB
`do_SRS = 1` (periodic SRS: the trace mode's fine round trip). They serve scenarios whose radio
is that carrier: μ = 1 and fs = 46.08 Msps (`-E`); others are refused (:func:`check_scenario`).

Without a core the UE's capabilities never reach the gNB and SRS is never configured, so both run
OAI's no-core test mode `--do-ra` (the nrUE reads the gNB's `reconfig.raw` / `rbconfig.raw`).
That mode pre-configures ONE UE per gNB (its RRC adds one default UE, its MAC ignores any other
random access): several users get a gNB + nrUE pair each (docs/oai-in-the-loop.md).

A build patched with patches/oai-2025.w36 (:func:`rtt_missing` says whether it is) serves the
`rtt` mode too: the gNB loads the telnet module `rtt` (`rtt pdcch_order <rnti>`) and the nrUE runs
with NRUE_PDCCH_ORDER_CSS=1 (it then hears the order, a DCI 1_0 in its common search space).
"""

from __future__ import annotations

import mmap
import re
from dataclasses import dataclass
from pathlib import Path

from uavloc.errors import ScenarioError

#: the recorded configuration files (OAI Public License v1.1, LICENSE.OAI beside them)
CONF_DIR = Path(__file__).resolve().parents[1] / "data" / "oai-2025.w36"
#: what the build folder must hold (build_oai --gNB --nrUE -w SIMU --build-lib telnetsrv)
BUILD_FILES = ("nr-softmodem", "nr-uesoftmodem", "librfsimulator.so", "libtelnetsrv.so", "libtelnetsrv_ci.so",
               "libtelnetsrv_o1.so", "libtelnetsrv_ciUE.so")
#: what a build patched with patches/oai-2025.w36 has besides: the telnet module `rtt`, and the
#: string nr-softmodem carries when its MAC has the PDCCH order (the live tests look for the same)
RTT_MODULE_FILE = "libtelnetsrv_rtt.so"
RTT_PATCH_MARK = b"rtt: PDCCH order for UE"
RTT_PATCH_README = "patches/oai-2025.w36/README.md"
#: the patched nrUE monitors its common search space for a PDCCH order only with this set
NRUE_ORDER_ENV = {"NRUE_PDCCH_ORDER_CSS": "1"}
#: the only carrier the recorded files describe
FS_HZ = 46.08e6
MU = 1
#: the most users (gNB + nrUE pairs) --oai starts: three ran rfsim at 0.40–0.49 × on 2 loaded cores
MAX_USERS = 3


@dataclass(frozen=True)
class OaiPorts:
    """The loopback ports of one run: the gNB's telnet and T servers, the rfsim server, each nrUE's
    telnet (one per UE)."""

    gnb_telnet: int
    t: int
    rfsim: int
    ue_telnet: tuple[int, ...]


def build_missing(build: Path) -> str | None:
    """Why `build` is not an OAI build folder uavloc can run (a sentence), or None."""
    if not build.is_dir():
        return f"--oai {build}: no such folder (an OAI build folder: openairinterface5g/cmake_targets/ran_build/build)"
    missing = [f for f in BUILD_FILES if not (build / f).is_file()]
    if missing:
        return (f"--oai {build} lacks {', '.join(missing)} (build it with `./build_oai --gNB --nrUE -w SIMU "
                "--build-lib telnetsrv`)")
    return None


def rtt_missing(build: Path) -> str | None:
    """Why `build` cannot serve the `rtt` mode (a sentence naming the patch's README), or None: it
    lacks the telnet module libtelnetsrv_rtt.so, or its nr-softmodem lacks the PDCCH order."""
    module = build / RTT_MODULE_FILE
    if not module.is_file():
        return (f"--oai {build} has no {RTT_MODULE_FILE}: --gnb-mode rtt needs OAI patched with "
                f"patches/oai-2025.w36/uavloc-rtt-pdcch-order.patch (how to apply and build it: {RTT_PATCH_README}); "
                "without it use --gnb-mode trace")
    if not _holds(build / "nr-softmodem", RTT_PATCH_MARK):
        return (f"--oai {build} has {RTT_MODULE_FILE} but its nr-softmodem has no PDCCH order (built before the "
                f"patch?): rebuild it as {RTT_PATCH_README} says, or use --gnb-mode trace")
    return None


def _holds(path: Path, mark: bytes) -> bool:
    """Whether the file holds the bytes `mark` (mapped, not read: nr-softmodem is some 30 MB)."""
    if path.stat().st_size < len(mark):
        return False
    with path.open("rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        return mm.find(mark) >= 0


def check_scenario(scenario) -> None:
    """ScenarioError naming what real OAI pairs cannot fly: a radio other than μ = 1 at 46.08 Msps,
    a fleet, more than MAX_USERS users (a pair each)."""
    where = f"--oai: scenario {scenario.name!r}"
    if scenario.radio.mu != MU or abs(scenario.radio.fs_hz - FS_HZ) > 1.0:
        raise ScenarioError(f"{where} has [radio] mu = {scenario.radio.mu}, fs_hz = {scenario.radio.fs_hz:g}: the OAI "
                            f"configuration uavloc writes is μ = {MU} at {FS_HZ:g} Hz (106 PRB, n78)")
    if scenario.mission.fleet_size > 1:
        raise ScenarioError(f"{where} flies {scenario.mission.fleet_size} vehicles: --oai runs one gNB")
    if len(scenario.users) > MAX_USERS:
        raise ScenarioError(f"{where} has {len(scenario.users)} users: OAI's no-core mode (--do-ra) pre-configures one "
                            f"UE per gNB, so each user runs a gNB + nrUE pair (about 1.3 cores each); --oai runs at "
                            f"most {MAX_USERS} (docs/oai-in-the-loop.md)")


def with_telnet_and_rfsim(text: str, telnet_port: int, rfsim_port: int) -> str:
    """A recorded conf file with its telnet server's `listenport` and the rfsimulator's
    `serverport` set; ScenarioError when the file has no telnetsrv section."""
    text, n = re.subn(r"(telnetsrv\s*=\s*\{[^}]*?listenport\s*=\s*)\d+", rf"\g<1>{int(telnet_port)}", text,
                      flags=re.S)
    if n != 1:
        raise ScenarioError("the OAI configuration file has no `telnetsrv = { ... listenport = N; }` section")
    if re.search(r"rfsimulator\s*:\s*\{", text):
        text = re.sub(r"(rfsimulator\s*:\s*\{)", rf"\1\n    serverport = {int(rfsim_port)};", text, count=1)
    else:
        text += f"\nrfsimulator: {{\n  serverport = {int(rfsim_port)};\n}};\n"
    return text


def with_srs(text: str) -> str:
    """A gNB conf file with `do_SRS = 1` in gNBs.[0] (set, or added first in the block)."""
    if re.search(r"do_SRS\s*=", text):
        return re.sub(r"do_SRS\s*=\s*\d+", "do_SRS = 1", text)
    text, n = re.subn(r"(gNBs\s*=\s*\(\s*\{)", r"\1\n    do_SRS = 1;", text, count=1)
    if n != 1:
        raise ScenarioError("the OAI gNB configuration file has no `gNBs = ( { ...` block")
    return text


def gnb_conf(ports: OaiPorts, recorded: str | None = None) -> str:
    """The gNB's configuration file of this run."""
    text = recorded if recorded is not None else (CONF_DIR / "gnb.conf").read_text()
    return with_srs(with_telnet_and_rfsim(text, ports.gnb_telnet, ports.rfsim))


def ue_conf(ports: OaiPorts, index: int, recorded: str | None = None) -> str:
    """nrUE `index`'s configuration file of this run."""
    text = recorded if recorded is not None else (CONF_DIR / "ue.conf").read_text()
    return with_telnet_and_rfsim(text, ports.ue_telnet[index], ports.rfsim)


#: OAI is started with no CAP_SYS_NICE at nice 19: as root it makes SCHED_FIFO threads that starve
#: a shared 2-core machine (../shared/peer-builds.md); each command execs the next, the pid is OAI's
UNPRIVILEGED = ("setpriv", "--bounding-set", "-sys_nice", "--inh-caps", "-sys_nice", "nice", "-n", "19")


def gnb_command(build: Path, conf: Path, ports: OaiPorts, rtt: bool = False) -> list[str]:
    """nr-softmodem: rfsim server, telnet (ci, o1, and with `rtt` the patch's module rtt), no-core
    `--do-ra`, its T server on ports.t."""
    return [*UNPRIVILEGED, str(build / "nr-softmodem"), "-O", str(conf), "-E", "--rfsim",
            "--rfsimulator.serveraddr", "server", "--telnetsrv", "--telnetsrv.shrmod", "ci,o1,rtt" if rtt else "ci,o1",
            "--log_config.global_log_options", "level,nocolor,wall_clock", "--do-ra",
            "--T_stdout", "2", "--T_nowait", "--T_port", str(ports.t)]


def ue_command(build: Path, conf: Path) -> list[str]:
    """nr-uesoftmodem: rfsim client at offset 0 (it attaches near; the bridge walks it out), its
    telnet (ciUE, rfsimu), `--do-ra` with the gNB's reconfig/rbconfig files (the run folder)."""
    return [*UNPRIVILEGED, str(build / "nr-uesoftmodem"), "-O", str(conf), "-E", "--rfsim", "--do-ra",
            "--reconfig-file", "reconfig.raw", "--rbconfig-file", "rbconfig.raw",
            "--rfsimulator.serveraddr", "127.0.0.1", "--telnetsrv", "--telnetsrv.shrmod", "ciUE",
            "--log_config.global_log_options", "level,nocolor,wall_clock"]
