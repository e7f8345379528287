"""Monte-Carlo campaigns: scenarios × planners × estimators × fleet sizes × seeds, run on Dask distributed.

    campaign = load_spec("benchmarks/planner_campaign.toml")      # strict TOML (spec.py)
    done = run_campaign(campaign, "out/", workers=2)               # LocalCluster, resume, Parquet
    write_summary(done.records, campaign.targets_m, "out/")        # table and figures

- spec.py: the spec and the RunSpecs it expands to; families.py: generated scenario families;
- fast.py: a run with a kinematic vehicle and channel (the real estimator and planner in the loop);
  full.py: a run against the built-in MAVLink vehicle and the simulated gNB;
- task.py: `run_one`, the pure per-run task; results.py: Parquet parts, resume;
- execute.py: Dask execution (LocalCluster, an existing scheduler, or in-process);
- summary.py: the summary table, the fleet speed-up and figures.
"""

from sitl_scenarios.campaign.execute import CampaignRun, quiet_logs, run_campaign
from sitl_scenarios.campaign.results import ResultsStore, same_value
from sitl_scenarios.campaign.spec import Campaign, RunSpec, load_spec, spec_from_dict
from sitl_scenarios.campaign.summary import (
    fleet_speedup_rows,
    format_table,
    summary_rows,
    summary_text,
    write_summary,
)
from sitl_scenarios.campaign.task import TIMING_FIELDS, run_one

__all__ = [
    "TIMING_FIELDS",
    "Campaign",
    "CampaignRun",
    "ResultsStore",
    "RunSpec",
    "fleet_speedup_rows",
    "format_table",
    "load_spec",
    "quiet_logs",
    "run_campaign",
    "run_one",
    "same_value",
    "spec_from_dict",
    "summary_rows",
    "summary_text",
    "write_summary",
]
