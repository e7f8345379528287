"""The gNB seam: everything uavloc says to an OpenAirInterface gNB and reads back from it.

- `client`: :class:`OaiGnbClient` (telnet or REST, the rtt and stock modes) and the
  :class:`GnbClient` protocol the mission depends on;
- `config`: the adapter's settings; `transport`: telnet and REST wires;
- `oai`, `oai_ra`: pure parsers of OAI's telnet answers and log lines;
- `log_follower`: the gNB log followed like ``tail -f`` (stock modes);
- `probe`: ``uavloc gnb probe`` and the mission's preflight.
"""

from mission.gnb.client import (
    O1_MIN_INTERVAL_S,
    O1_SETTLE_REQUEST,
    GnbClient,
    OaiGnbClient,
)
from mission.gnb.config import FORBIDDEN_CI, GnbConfig, check_ci_line, parse_host_port
from mission.gnb.log_follower import LogFollower
from mission.gnb.oai import RttSample
from mission.gnb.transport import GnbAddress, parse_gnb_address

__all__ = ["FORBIDDEN_CI", "O1_MIN_INTERVAL_S", "O1_SETTLE_REQUEST", "GnbAddress", "GnbClient", "GnbConfig",
           "LogFollower", "OaiGnbClient", "RttSample", "check_ci_line", "parse_gnb_address", "parse_host_port"]
