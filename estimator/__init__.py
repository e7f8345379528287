"""Pure estimation maths: ranging, measurement models, the SLAM solver, covariance, CRLB.

No asyncio, sockets, files or clocks in here (docs/design.md §2).
"""
