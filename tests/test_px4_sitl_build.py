"""sitl_scenarios.px4_sitl without PX4: the skip sentences naming UAVLOC_PX4, the start-up of a
build laid out like `build/px4_sitl_default` (a stand-in `bin/px4` shell script that reports what
it was started with, then prints PX4's ready line), and the pausing UDP relay."""

from __future__ import annotations

import os
import socket
import stat
import time

import pytest

from sitl_scenarios.px4_sitl import (
    BUILD_ENV,
    Px4Sitl,
    UdpRelay,
    api_port,
    build_from_env,
    missing_requirement,
)
from uavloc.errors import SimulatorError

#: stands in for PX4's binary: prints its arguments, environment and working directory as PX4's
#: start-up would see them, then the ready line, and waits for SIGTERM like `px4 -d`
FAKE_PX4 = """#!/bin/sh
echo "ARGS $*"
echo "MODEL $PX4_SIM_MODEL SIMULATOR $PX4_SIMULATOR SPEED $PX4_SIM_SPEED_FACTOR HOME $PX4_HOME_LAT"
echo "CWD $(pwd)"
trap 'echo "PX4 Exiting..."; exit 0' TERM
echo "INFO  [commander] Ready for takeoff!"
while :; do sleep 0.05; done
"""


def _build(root, rcs: str = "#!/bin/sh\n"):
    """A folder laid out like PX4-Autopilot/build/px4_sitl_default."""
    (root / "bin").mkdir(parents=True)
    init = root / "etc" / "init.d-posix"
    (init / "airframes").mkdir(parents=True)
    (init / "rcS").write_text(rcs)
    (init / "airframes" / "10040_sihsim_quadx").write_text("#!/bin/sh\n")
    px4 = root / "bin" / "px4"
    px4.write_text(FAKE_PX4)
    px4.chmod(px4.stat().st_mode | stat.S_IXUSR)
    os.symlink("px4", root / "bin" / "px4-commander")
    return root


def test_unset_or_wrong_build_is_a_reason_to_skip_naming_the_variable(tmp_path, monkeypatch):
    assert build_from_env({}) is None
    assert build_from_env({BUILD_ENV: "  "}) is None
    assert build_from_env({BUILD_ENV: str(tmp_path)}) == tmp_path
    why = missing_requirement(None)
    assert why.startswith("UAVLOC_PX4 is not set") and "build/px4_sitl_default" in why
    assert "UAVLOC_PX4" in missing_requirement(tmp_path / "nowhere")
    assert "bin/px4" in missing_requirement(tmp_path / "nowhere")
    build = _build(tmp_path / "build")
    assert missing_requirement(build) is None
    (build / "etc" / "init.d-posix" / "airframes" / "10040_sihsim_quadx").unlink()
    assert "sihsim_quadx" in missing_requirement(build)
    with pytest.raises(SimulatorError, match="UAVLOC_PX4"):
        Px4Sitl(tmp_path / "nowhere", 1, 4.0, tmp_path / "w").start()


def test_bc_is_asked_for_only_where_the_start_up_scripts_use_it(tmp_path, monkeypatch):
    monkeypatch.setattr("shutil.which", lambda name: None)
    assert missing_requirement(_build(tmp_path / "a")) is None
    assert "bc" in missing_requirement(_build(tmp_path / "b", rcs='x=$(echo "1+1" | bc)\n'))


def test_started_like_make_px4_sitl_sihsim_quadx_one_instance_per_workdir(tmp_path):
    build = _build(tmp_path / "build")
    sitl = Px4Sitl(build, 3, 4.0, tmp_path / "work", home=(43.6143, 7.0716, 150.0), output=tmp_path / "px4.log")
    argv, env = sitl.command_line()
    assert argv == [str(build.resolve() / "bin" / "px4"), "-d", "-i", "3", "-w", str((tmp_path / "work").resolve()),
                    str(build.resolve() / "etc")]
    assert env["PX4_SIM_MODEL"] == "sihsim_quadx" and env["PX4_SIMULATOR"] == "sihsim"
    assert (sitl.api_url, sitl.gcs_url) == ("udpin://127.0.0.1:14543", "udpout://127.0.0.1:18573")
    with sitl:
        assert sitl.wait_ready(10.0), sitl.text()
        assert sitl.running()
    text = sitl.text()
    assert f"ARGS -d -i 3 -w {(tmp_path / 'work').resolve()} {build.resolve() / 'etc'}" in text
    assert "MODEL sihsim_quadx SIMULATOR sihsim SPEED 4 HOME 43.6143" in text
    assert f"CWD {(tmp_path / 'work').resolve()}" in text
    assert "PX4 Exiting..." in text  # stopped with SIGTERM, which PX4 answers by shutting down
    assert (tmp_path / "px4.log").read_text() == text
    assert not sitl.running()


def test_api_ports_are_px4s_stock_ones():
    assert [api_port(i) for i in (0, 1, 8, 9, 10, 17)] == [14540, 14541, 14548, 14549, 14549, 14549]


def test_relay_forwards_both_ways_and_drops_while_paused():
    px4 = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    px4.bind(("127.0.0.1", 0))
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.bind(("127.0.0.1", 0))
    for s in (px4, client):
        s.settimeout(5.0)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        listen_port = probe.getsockname()[1]
    with UdpRelay(listen_port, client.getsockname()[1]) as relay:
        px4.sendto(b"heartbeat", ("127.0.0.1", listen_port))
        data, relay_addr = client.recvfrom(100)
        assert data == b"heartbeat"
        client.sendto(b"command", relay_addr)
        assert px4.recvfrom(100)[0] == b"command"
        relay.pause()
        px4.sendto(b"lost", ("127.0.0.1", listen_port))
        client.sendto(b"lost too", relay_addr)
        deadline = time.monotonic() + 5.0
        while relay.dropped < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert relay.dropped == 2
        relay.resume()
        px4.sendto(b"back", ("127.0.0.1", listen_port))
        assert client.recvfrom(100)[0] == b"back"  # nothing from the pause came through
    px4.close()
    client.close()
