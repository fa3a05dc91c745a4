"""``python -m service.prebuild [--joints N ...]``: compile, into the compiled-function cache
(``$XDG_CACHE_HOME/chained-planner/native``, :mod:`optimizer.native`), the shooting NLPs of the
default robot of every joint count the warm-up prepares (:data:`service.jobs.WARM_JOINTS`) and
the proofs' quadrature kernel and, from 4 joints, the chained form's maps, and wait for them: the image build runs it, so that a worker's
first plan of any joint count loads a library instead of starting a compiler. An NLP whose C
is too large to compile (:data:`optimizer.native.MAX_SOURCE_BYTES`: 8 joints) stays on
CasADi's virtual machine, as it would at run time. Prints what was compiled."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from optimizer import cascade_kernel, native
from optimizer.chained_form import prepare_maps
from optimizer.model import Robot
from optimizer.planner.shooting import prepare

from .jobs import WARM_JOINTS


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m service.prebuild", description=__doc__)
    parser.add_argument("--joints", type=int, nargs="+", default=list(WARM_JOINTS),
                        help="joint counts of the default robots (default: %(default)s)")
    args = parser.parse_args(argv)
    if native.configure(native.default_cache_dir()) is None:
        print("no C compiler: nothing compiled")
        return 1
    robots = {n: Robot.default(n) for n in args.joints}
    compiled = {n: prepare(r.gains, r.exponents, wait=True).compiled for n, r in robots.items()}
    kernel = cascade_kernel.prepare(wait=True)
    # (3 joints: the chained form's closed form, no maps to compile)
    maps = {n: prepare_maps(r.exponents, wait=True) for n, r in robots.items() if n > 3}
    print("compiled:", " ".join(f"{n}={'yes' if ok else 'no'}" for n, ok in compiled.items()),
          f"kernel={'yes' if kernel else 'no'}",
          "chained maps:", " ".join(f"{n}={'yes' if ok else 'no'}" for n, ok in maps.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
