"""Mission control: the asyncio controller, vehicle and gNB adapters, mission log, replay, CLI.

The only package that does I/O with the outside world (docs/design.md §1, §2).
"""
