"""Workers with compiled NLP functions (``PLANNER_NATIVE_CACHE``): the warm-up starts the
default robot's build in the background, and once built the workers' shooting plans use it."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import shutil
import time
from pathlib import Path
from typing import AsyncIterator

import pytest

from optimizer.native import default_cache_dir
from service.settings import Settings
from service.workers import WorkerPool

OPP_A = {"start": [math.radians(x) for x in (10, 20, 30)],
         "goal": [math.radians(x) for x in (40, 25, 15)], "method": "shooting"}


def pending_builds(cache: Path) -> set[str]:
    """Libraries whose source is written but which are neither built nor failed."""
    done = {p.stem for p in cache.glob("*.so")} | {p.stem for p in cache.glob("*.failed")}
    return {p.stem for p in cache.glob("*.c")} - done


@contextlib.asynccontextmanager
async def ready_pool(cache: Path) -> AsyncIterator[tuple[WorkerPool, dict]]:
    """One warmed-up worker with ``cache`` as its compiled-function cache, and its warm-up
    information."""
    pool = WorkerPool(1, 4, warmup=True, native_cache=str(cache))
    await pool.start()
    try:
        for _ in range(1200):
            if pool.ready:
                break
            await asyncio.sleep(0.05)
        yield pool, next(iter(pool._all)).ready_info
    finally:
        await pool.close()


def test_native_cache_setting(monkeypatch, tmp_path):
    assert Settings().native_cache_dir == str(default_cache_dir())
    monkeypatch.setenv("PLANNER_NATIVE_CACHE", "off")
    assert Settings().native_cache_dir is None
    monkeypatch.setenv("PLANNER_NATIVE_CACHE", str(tmp_path))
    assert Settings().native_cache_dir == str(tmp_path)


@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                    reason="no C compiler")
def test_workers_build_in_the_background_then_plan_with_compiled_functions(tmp_path: Path):
    async def main() -> tuple[dict, list[bool]]:
        async with ready_pool(tmp_path) as (pool, info):
            compiled = []
            for _ in range(2):
                out = await pool.run("plan", OPP_A, 30.0)
                assert out["ok"], out
                compiled.append(json.loads(out["body"])["diagnostics"]["shooting"]["compiled"])
                # the warm-up started the builds: wait for them, then plan again
                deadline = time.monotonic() + 180
                while pending_builds(tmp_path) and time.monotonic() < deadline:
                    await asyncio.sleep(0.2)
                await asyncio.sleep(1.1)  # a worker looks for the library once a second
            return info, compiled

    info, compiled = asyncio.run(main())
    # the quadrature's kernel built at the workers' start, the NLP's in the background
    assert info.get("native") is True and info.get("cascade_kernel") is True
    assert info.get("shooting_compiled") is False
    assert not pending_builds(tmp_path) and not list(tmp_path.glob("*.failed"))
    built = sorted(tmp_path.glob("*.so"))
    # the kernel, the 3-joint NLP and (started by the warm-up of 4 to 8 joints) the chained
    # form's maps
    assert len(built) > 2
    assert compiled[-1] is True
    # a restarted service finds the libraries at its workers' warm-up and builds nothing
    info, compiled = asyncio.run(main())
    assert info.get("shooting_compiled") is True and compiled == [True, True]
    assert sorted(tmp_path.glob("*.so")) == built and not list(tmp_path.glob("*.c"))


def test_an_unsafe_cache_directory_leaves_the_workers_on_the_virtual_machine(tmp_path: Path):
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)

    async def main() -> tuple[dict, dict]:
        async with ready_pool(shared) as (pool, info):
            return info, await pool.run("plan", OPP_A, 30.0)

    info, out = asyncio.run(main())
    assert info.get("native") is False and info.get("shooting_compiled") is False
    assert out["ok"] and json.loads(out["body"])["diagnostics"]["shooting"]["compiled"] is False
    assert not list(shared.iterdir())
