"""The mission seen live in a browser (`--view`) or recorded (`uavloc view LOG`): a pure state model
fed with mission-log records (`state`), an aiohttp server in the mission's event loop (`server`),
and one page whose script and style ship in this package (`static/`)."""
