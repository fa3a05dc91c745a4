"""Benchmarks of the planner against the direct multiple-shooting baseline.

Run ``.venv/bin/python -m bench`` (see :mod:`bench.__main__` and docs/benchmarks.md).

Modules
-------
``cases``
    The benchmark cases (prototype robot and assumed 4-/5-joint robots).
``reintegrate``
    The ORIGINAL kinematic model (its own right-hand side, written here), re-integrated with
    scipy for the planner's and the baseline's inputs, and the path metrics.
``stats``
    Repeated timing in-process (median, quartiles, min/max).
``inprocess``
    Every planner method and the baseline on every case.
``http_load``
    The service under uvicorn: cold start, latency and throughput, worker memory.
``scaling``
    Cost against samples and against joints.
``report``
    The printed table and the targets.
``profile_plan``
    A profile of the polynomial plan's hot path (``python bench/profile_plan.py``).
"""
