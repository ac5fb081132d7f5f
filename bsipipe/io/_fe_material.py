r"""What the three FE writers (ABAQUS, LS-DYNA, FEBio) share: unit systems and one
normalised description of a fitted material.

bsipipe stores stresses in Pa and times in s, and its Ogden moduli follow

.. math::

    W = \sum_i \frac{2\mu_i}{\alpha_i^2}
        \left(\bar\lambda_1^{\alpha_i} + \bar\lambda_2^{\alpha_i} + \bar\lambda_3^{\alpha_i} - 3\right)
        + U(J),

(``mu_i`` sum to the initial shear modulus, :mod:`bsipipe.mechanics.hyperelastic`).
Each writer converts from this one description to its code's convention and units.

Choices made here, stated once for all three formats:

* **Viscoelasticity.** A Prony series is a list of ``(g_i, tau_i)``: ``g_i`` are shear
  relaxation moduli normalised by the *instantaneous* shear modulus (ABAQUS's
  :math:`g_i^P`), so :math:`G(t)/G_0 = 1 - \sum_i g_i (1 - e^{-t/\tau_i})` and
  :math:`G_\infty = G_0 (1 - \sum_i g_i)`.  The hyperelastic moduli passed in are the
  instantaneous ones (``params_moduli="instantaneous"``, the quasi-linear viscoelastic
  convention, reduced relaxation function with :math:`G(0) = 1`) unless the caller says
  ``"long-term"``.  Only the shear response relaxes; the bulk modulus is constant.
* **Near-incompressibility.** Brain tissue is nearly incompressible (bulk modulus of
  water, about 2 GPa, so :math:`K/\mu \sim 10^6`), but such ratios make explicit time
  steps tiny and implicit solves ill-conditioned.  Unless the caller states a bulk
  modulus, :math:`K_0 = 1000\,\mu_0` (Poisson's ratio 0.4995): in a 30 % uniaxial
  compression the volume changes by about 0.07 % and the force is within 0.15 % of
  the incompressible value (measured with CalculiX in ``tests/test_calculix.py``).
  :math:`K_0` is the same small-strain bulk modulus in every format (ABAQUS
  :math:`D_1 = 2/K_0`, LS-DYNA's PR, FEBio's ``k``).
* **Units.**  Decks default to mm-N-s-MPa.  For brain tissue its forces are small
  (720 Pa on a 1 mm^2 face is 7e-4 N), and implicit solvers have absolute floors:
  CalculiX 2.20 treats residual forces below about 1e-5 (deck force units) as zero and
  stops Newton early (measured: a 3 mm C3D8 cube's first increment ends 0.3 % short).
  ``mm-kg-s-kPa`` (force in mN) puts brain numbers near 1 and avoids it.
* **Density.** FE codes need a mass density for dynamic analyses (LS-DYNA always).
  Default 1040 kg/m^3, a typical value for brain tissue; not a measurement of the
  specimen.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from bsipipe.mechanics.hyperelastic import get_law

DEFAULT_BULK_TO_SHEAR = 1000.0
DEFAULT_DENSITY_KG_M3 = 1040.0


@dataclass(frozen=True)
class UnitSystem:
    """A consistent set of FE units and the factors that take SI values into it."""

    name: str
    length: str
    mass: str
    time: str
    force: str
    stress: str
    per_m: float  # deck length = m * per_m
    per_n: float  # deck force = N * per_n
    per_pa: float  # deck stress = Pa * per_pa
    per_s: float  # deck time = s * per_s
    per_kg_m3: float  # deck density = kg/m^3 * per_kg_m3

    def describe(self) -> str:
        """One line for a comment in the deck."""
        return (
            f"units {self.name}: length {self.length}, mass {self.mass}, time {self.time}, "
            f"force {self.force}, stress {self.stress}"
        )


UNIT_SYSTEMS: dict[str, UnitSystem] = {
    u.name: u
    for u in (
        # the common implicit/explicit system: N and MPa with tonne as mass
        UnitSystem("mm-N-s-MPa", "mm", "tonne", "s", "N", "MPa", 1e3, 1.0, 1e-6, 1.0, 1e-12),
        # LS-DYNA's habitual crash units
        UnitSystem("mm-kg-ms-GPa", "mm", "kg", "ms", "kN", "GPa", 1e3, 1e-3, 1e-9, 1e3, 1e-9),
        UnitSystem("mm-g-ms-MPa", "mm", "g", "ms", "N", "MPa", 1e3, 1.0, 1e-6, 1e3, 1e-6),
        UnitSystem("m-kg-s-Pa", "m", "kg", "s", "N", "Pa", 1.0, 1.0, 1.0, 1.0, 1.0),
        # brain-sized numbers: stresses of order 1 kPa, forces in mN (see the note above)
        UnitSystem("mm-kg-s-kPa", "mm", "kg", "s", "mN", "kPa", 1e3, 1e3, 1e-3, 1.0, 1e-9),
    )
}
_UNIT_ALIASES = {"mm-N-MPa": "mm-N-s-MPa", "mm-t-s": "mm-N-s-MPa", "SI": "m-kg-s-Pa",
                 "mm-kg-ms": "mm-kg-ms-GPa", "mm-g-ms": "mm-g-ms-MPa"}


def unit_system(name: str) -> UnitSystem:
    """Look up a unit system by name (or a documented alias)."""
    key = _UNIT_ALIASES.get(name, name)
    try:
        return UNIT_SYSTEMS[key]
    except KeyError:
        known = sorted(set(UNIT_SYSTEMS) | set(_UNIT_ALIASES))
        raise ValueError(f"unknown unit system {name!r}; expected one of {known}") from None


@dataclass(frozen=True)
class FEMaterial:
    """A fitted isotropic hyper(visco)elastic material in bsipipe's conventions (SI).

    ``mus_pa``/``alphas`` are the *instantaneous* Ogden terms (ABAQUS convention);
    ``prony`` holds ``(g_i, tau_s)`` with ``g_i`` normalised by the instantaneous modulus.
    """

    law: str
    law_params: tuple[float, ...]  # instantaneous, in the law's own parameters (Pa)
    mus_pa: np.ndarray
    alphas: np.ndarray
    bulk_modulus_pa: float
    prony: tuple[tuple[float, float], ...]
    density_kg_m3: float

    @property
    def shear_modulus_pa(self) -> float:
        """Instantaneous initial shear modulus ``G0 = sum mu_i``."""
        return float(np.sum(self.mus_pa))

    @property
    def long_term_factor(self) -> float:
        """``G_inf / G0 = 1 - sum g_i`` (1 without a Prony series)."""
        return 1.0 - sum(g for g, _ in self.prony)

    def moduli(self, which: str) -> float:
        """Factor taking the instantaneous moduli to ``which`` ('instantaneous'|'long-term')."""
        return {"instantaneous": 1.0, "long-term": self.long_term_factor}[_check_moduli(which)]


def _check_moduli(which: str) -> str:
    if which not in ("instantaneous", "long-term"):
        raise ValueError(f"moduli must be 'instantaneous' or 'long-term', not {which!r}")
    return which


def _prony_terms(prony) -> tuple[tuple[float, float], ...]:
    out = []
    for term in prony or ():
        if isinstance(term, Mapping):
            g, tau = term["g"], term["tau_s"]
        else:
            g, tau = term
        g, tau = float(g), float(tau)
        if not (0.0 < g < 1.0) or not tau > 0.0:
            raise ValueError(f"Prony term (g={g}, tau_s={tau}) needs 0 < g < 1 and tau_s > 0")
        out.append((g, tau))
    if sum(g for g, _ in out) >= 1.0:
        raise ValueError("Prony g_i must sum to less than 1 (a positive long-term modulus)")
    return tuple(out)


def prepare_material(
    law_name: str,
    params,
    prony=None,
    *,
    params_moduli: str = "instantaneous",
    bulk_modulus_pa: float | None = None,
    density_kg_m3: float = DEFAULT_DENSITY_KG_M3,
) -> FEMaterial:
    """Normalise a fit result into an :class:`FEMaterial`.

    Parameters
    ----------
    law_name : str
        A name from :data:`bsipipe.mechanics.hyperelastic.LAWS`.
    params : mapping or sequence
        The law's parameters in Pa (``fit.json`` ``params``: ``mu_pa``, ``alpha``, ...;
        keys that are not the law's parameters are ignored, except the Prony terms,
        ``"prony": [{"g", "tau_s"}]`` or flat ``g1, tau1_s, ...``, used when ``prony`` is
        not given), or a sequence in the law's parameter order.
    prony : sequence of (g, tau_s) or of {"g": .., "tau_s": ..}, optional
    params_moduli : {"instantaneous", "long-term"}
        Whether ``params`` describe the instantaneous or the long-term response.
    bulk_modulus_pa : float, optional
        Small-strain bulk modulus; default ``1000 * G0`` (see the module notes).
    density_kg_m3 : float
    """
    law = get_law(law_name)
    if isinstance(params, Mapping):
        missing = [k for k in law.param_names if k not in params]
        if missing:
            raise ValueError(f"model {law_name!r} needs parameters {missing}")
        vec = np.array([float(params[k]) for k in law.param_names])
        if prony is None:
            prony = params.get("prony")
        if prony is None:  # the flat form g1, tau1_s, g2, ... also used by the fit
            prony = [(params[f"g{i}"], params[f"tau{i}_s"])
                     for i in range(1, 100) if f"g{i}" in params]
    else:
        vec = np.asarray(params, dtype=float)
        if vec.shape != (len(law.param_names),):
            raise ValueError(f"model {law_name!r} takes {len(law.param_names)} parameters "
                             f"{law.param_names}, got {vec.size}")
    if not np.all(np.isfinite(vec)):
        # Infinity (what Python's json writes for inf) had reached the deck writer: "internal
        # error: nan cannot be written in a keyword field", exit 1
        bad = [f"{n} = {v}" for n, v in zip(law.param_names, vec) if not np.isfinite(v)]
        raise ValueError(f"model {law_name!r}: parameters must be finite numbers, got {', '.join(bad)}")
    terms = _prony_terms(prony)
    if not all(np.isfinite(g) and np.isfinite(t) for g, t in terms):
        raise ValueError(f"Prony terms must be finite numbers, got {terms}")
    g_sum = sum(g for g, _ in terms)
    if _check_moduli(params_moduli) == "long-term":
        vec = vec.copy()
        # moduli scale, exponents do not
        is_modulus = np.array([n.endswith("_pa") for n in law.param_names])
        vec[is_modulus] /= 1.0 - g_sum
    mus, alphas = law.ogden_terms(vec)
    if np.any(alphas == 0.0):
        raise ValueError("Ogden exponents must be non-zero")
    g0 = float(np.sum(mus))
    if not g0 > 0.0:
        raise ValueError(f"initial shear modulus sum(mu_i) = {g0} Pa must be positive")
    k0 = DEFAULT_BULK_TO_SHEAR * g0 if bulk_modulus_pa is None else float(bulk_modulus_pa)
    if not k0 > 0.0:
        raise ValueError("bulk modulus must be positive")
    return FEMaterial(law.name, tuple(float(v) for v in vec), np.asarray(mus, float),
                      np.asarray(alphas, float), k0, terms, float(density_kg_m3))


def poisson_ratio(bulk_modulus: float, shear_modulus: float) -> float:
    """Small-strain Poisson's ratio from K and G: ``(3K - 2G) / (2 (3K + G))``."""
    return (3.0 * bulk_modulus - 2.0 * shear_modulus) / (2.0 * (3.0 * bulk_modulus + shear_modulus))


def number(x: float) -> str:
    """A float in at most 20 characters with 14 significant digits.

    CalculiX reads each data field as ``f20.0`` (the first 20 characters), so longer
    numbers would be cut; 14 digits keep round-off far below any fitted uncertainty.
    """
    s = f"{float(x):.14g}"
    if len(s) > 20:  # pragma: no cover - '.14g' never exceeds 20 characters
        raise ValueError(f"cannot write {x!r} in 20 characters")
    return s


def stiffness_groups(stiffness, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Springs of equal stiffness: ``stiffness`` (one value, or ``n``) to the distinct values
    and each spring's index into them.  Values equal to 12 significant digits are one (a
    deck writes 14; nodes of equal tributary area differ in the last bits of their sums).

    >>> values, group = stiffness_groups([2.0, 1.0, 2.0 + 1e-14], 3)
    >>> values.tolist(), group.tolist()
    ([1.0, 2.0], [1, 0, 1])
    """
    k = np.broadcast_to(np.asarray(stiffness, dtype=float), (n,))
    _, first, group = np.unique(np.array([float(f"{v:.12g}") for v in k]), return_index=True, return_inverse=True)
    return k[first], group                 # each group's value as given (its first member's)


def ogden_terms_text(mus: Sequence[float], alphas: Sequence[float]) -> str:
    """Human-readable list of terms for comment lines."""
    return "; ".join(f"mu{i + 1}={m:.6g} Pa, alpha{i + 1}={a:.6g}"
                     for i, (m, a) in enumerate(zip(mus, alphas)))
