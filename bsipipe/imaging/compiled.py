"""The compiled sub-pixel fits, ``bsipipe.imaging._kernels`` (``_kernels.c``, built by
``setup.py`` at install time; optional), loaded once: :data:`kernels` is the module, or None
where it was not built or was built from another version of ``_kernels.c`` than this code
calls (then with a warning to rebuild).  :mod:`bsipipe.imaging.detect` calls it where it is
there and runs the same fits in NumPy where not; :mod:`bsipipe.provenance` says which, without
loading the detector."""

from __future__ import annotations

import warnings

#: The version of ``_kernels.c`` this code calls (its ``KERNELS_VERSION``).
KERNELS_VERSION = 1

try:
    from . import _kernels as kernels
except ImportError:                    # pragma: no cover - not built: the NumPy versions
    kernels = None
if kernels is not None and getattr(kernels, "VERSION", None) != KERNELS_VERSION:   # pragma: no cover
    warnings.warn(f"{kernels.__file__} was built from another version of _kernels.c: the sub-pixel fits run in "
                  f"NumPy (slower) until it is rebuilt (pip install -e . or make install)", RuntimeWarning,
                  stacklevel=1)
    kernels = None


def subpixel_fits() -> str:
    """Which sub-pixel fits run: ``compiled (bsipipe.imaging._kernels N)`` or ``numpy``."""
    return f"compiled (bsipipe.imaging._kernels {kernels.VERSION})" if kernels is not None else "numpy"
