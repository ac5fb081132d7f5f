"""How often the register loop's ``label-swap`` effect gives back mixed-up reference labels.

    python scripts/relabel_probe.py [--seeds 6]

Random layouts of N = 4, 5, 6, 7, 8 and 10 references (x, y uniform over +-15 mm, z over
+-1.5 mm: the corners of a craniotomy on a curved skull), five implanted markers 5 mm below,
0.005 mm of noise on every CT and X-ray coordinate, a known rigid transform; the CT labels
mixed up four ways: one exchange (R1 <-> R2), a cycle of three (the CT file calls R1 R2,
R2 R3, R3 R1), a cycle of four, two exchanges at once (R1 <-> R2, R3 <-> R4).  Prints, per N
and kind, how many of the seeds' layouts the loop (:func:`close_registration_loop`, no
tracks) gave back exactly.  The loop has ``bsipipe register``'s noise ceiling for that noise
(:func:`bsipipe.commands.register._noise_ceiling`: a FRE above it is not noise whatever the
residual's pattern); ``--no-ceiling`` leaves it out (the loop as it was before the ceiling).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation

from bsipipe.commands.register import _noise_ceiling
from bsipipe.geometry.registration import Similarity
from bsipipe.geometry.registration_effects import RegistrationData, RegistrationSpec, close_registration_loop

T_TRUE = Similarity(Rotation.from_rotvec([0.2, -0.4, 0.9]).as_matrix(), np.array([-5.0, 10.0, -90.0]), 1.0)
KINDS = {"exchange": [1, 0], "cycle of 3": [1, 2, 0], "cycle of 4": [1, 2, 3, 0], "two exchanges": [1, 0, 3, 2]}
SIZES = (4, 5, 6, 7, 8, 10)
NOISE_MM = 0.005        # on every CT coordinate (the X-ray positions are exact)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--no-ceiling", action="store_true", help="no noise ceiling")
    a = ap.parse_args()
    hits: dict = {}
    ceiling = None if a.no_ceiling else _noise_ceiling({"sigma_mm": NOISE_MM})
    t0 = time.perf_counter()
    for seed in range(a.seeds):
        rng = np.random.default_rng(seed)
        for n in SIZES:
            for kind, head in KINDS.items():
                x = rng.uniform(-15, 15, (n, 3))
                x[:, 2] *= 0.1
                y = T_TRUE.apply(x) + rng.normal(0, NOISE_MM, x.shape)
                cx = rng.uniform(-10, 10, (5, 3))
                cx[:, 2] -= 5
                cy = T_TRUE.apply(cx) + rng.normal(0, NOISE_MM, cx.shape)
                names = [f"R{i + 1}" for i in range(n)]
                perm = head + list(range(len(head), n))        # the CT file's label i holds marker perm[i]
                data = RegistrationData(names, x, y[perm], check_x_mm=cx, check_y_mm=cy)
                rep = close_registration_loop(data, RegistrationSpec(), noise_ceiling=ceiling)
                got = {}
                for step in rep.steps:
                    for c in step.after.spec.swapped:
                        got.update({names.index(p): names.index(q) for p, q in zip(c, c[1:] + c[:1])})
                want = {p: i for i, p in enumerate(perm) if p != i}     # X-ray marker -> its CT label
                hits.setdefault(kind, {}).setdefault(n, 0)
                hits[kind][n] += got == want
    how = "no noise ceiling" if ceiling is None else f"noise ceiling {ceiling:.3g} mm per coordinate"
    print(f"given back exactly, of {a.seeds} layouts each ({how}; {time.perf_counter() - t0:.0f} s)")
    print(f"{'':15s}" + "".join(f"N={n:<5d}" for n in SIZES) + "  all")
    for kind, row in hits.items():
        print(f"{kind:15s}" + "".join(f"{row[n]:<7d}" for n in SIZES) + f"  {sum(row.values())} / {a.seeds * len(SIZES)}")


if __name__ == "__main__":
    main()
