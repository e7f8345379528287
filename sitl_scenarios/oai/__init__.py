"""A real OAI gNB and nrUE in the loop of `uavloc sim --oai` (docs/oai-in-the-loop.md)."""
