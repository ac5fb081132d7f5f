"""The compiled kernels of bsipipe (everything else is in pyproject.toml).

``bsipipe.imaging._kernels``: the per-frame sub-pixel fits (C, the Python headers only).  The
extension is optional: where it cannot be built, bsipipe runs the same fits in NumPy
(``bsipipe.imaging.detect``), about a fifth slower per tracked frame.
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("bsipipe.imaging._kernels", ["bsipipe/imaging/_kernels.c"], optional=True,
                             extra_compile_args=["-O2", "-std=c99"])])
