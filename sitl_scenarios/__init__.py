"""Scenarios (TOML), the built-in MAVLink vehicle simulator and the simulated OAI gNB."""
