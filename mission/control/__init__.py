"""The mission controller, split by responsibility (see mission/controller.py for the map)."""
