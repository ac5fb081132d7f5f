"""The compiled sub-pixel fits against their NumPy versions on the track benchmark's twin.

    python scripts/kernels_ab.py [N_FRAMES] [REPEATS]       (after ``make bench`` rendered the twin)

Tracks the first ``N_FRAMES`` (default 50) frames of both views of
``results/bench_cache/twin200``, decoded beforehand, seeded and without seeds, with
``bsipipe.imaging._kernels`` and with ``bsipipe.imaging.detect``'s NumPy fits, interleaved in
one process; prints the fastest of ``REPEATS`` (default 6) runs of each and the speed-up.
"""

import sys
import time
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import bsipipe.imaging.detect as D  # noqa: E402
from bench.track import VIEWS, _bsipipe_track  # noqa: E402
from bsipipe.io.images import iter_frames  # noqa: E402


def main(n: int = 50, repeats: int = 6) -> None:
    src = ROOT / "results" / "bench_cache" / "twin200"
    if not (src / "seeds.csv").exists():
        sys.exit(f"{src} not found: run make bench (or bench/run.py --only track) first")
    if D._kernels is None:
        sys.exit("bsipipe.imaging._kernels is not built: pip install -e . (make install)")
    frames = {v: [fr.image for _, fr in zip(range(n), iter_frames(src / "sequence" / v))] for v in VIEWS}
    seeds = pd.read_csv(src / "seeds.csv")
    compiled, best = D._kernels, {}
    for rep in range(repeats):
        for mode in ("seeded", "auto"):
            for kern in (True, False):
                D._kernels = compiled if kern else None
                if rep == 0:                     # warm-up
                    _bsipipe_track(frames, seeds, auto=mode == "auto")
                t = time.perf_counter()
                _bsipipe_track(frames, seeds, auto=mode == "auto")
                key = (mode, kern)
                best[key] = min(best.get(key, float("inf")), time.perf_counter() - t)
    D._kernels = compiled
    total = n * len(VIEWS)
    for mode in ("seeded", "auto"):
        c, p = total / best[(mode, True)], total / best[(mode, False)]
        print(f"{mode:7s} compiled {c:7.1f} frames/s, NumPy {p:7.1f} frames/s: {c / p:.2f}x")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]))
