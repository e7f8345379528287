"""``python -m sitl_scenarios.gnb``: the simulated gNB standalone (sitl_scenarios.gnb.server.main)."""

from sitl_scenarios.gnb.server import main

raise SystemExit(main())
