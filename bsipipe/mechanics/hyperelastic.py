r"""Incompressible isotropic hyperelastic laws and their nominal stress in each loading mode.

Every law here is an Ogden series in disguise,

.. math::

    W = \sum_{i=1}^{N} \frac{2\mu_i}{\alpha_i^2}
        \left(\lambda_1^{\alpha_i} + \lambda_2^{\alpha_i} + \lambda_3^{\alpha_i} - 3\right),

the convention of the brain papers and of ABAQUS (``mu_i`` sum to the initial shear
modulus).  Neo-Hookean, :math:`W = \frac{\mu}{2}(I_1 - 3)`, is one term with
:math:`\alpha = 2`; Mooney-Rivlin, :math:`W = C_{10}(I_1 - 3) + C_{01}(I_2 - 3)`, is two
terms with :math:`\mu_1 = 2C_{10}, \alpha_1 = 2` and :math:`\mu_2 = 2C_{01}, \alpha_2 = -2`.

Stresses are nominal (first Piola-Kirchhoff, force per undeformed area) in the direction
of the imposed stretch, in the units of ``mu``.  Compression is ``stretch < 1`` with a
negative stress.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MODES = ("uniaxial", "equibiaxial", "pure-shear", "simple-shear")


def ogden_nominal_stress(stretch, mus, alphas, mode: str = "uniaxial") -> np.ndarray:
    r"""Nominal stress of an incompressible N-term Ogden solid.

    .. math::

        P_{\text{uniaxial}} &= \sum_i \frac{2\mu_i}{\alpha_i}
            \left(\lambda^{\alpha_i - 1} - \lambda^{-\alpha_i/2 - 1}\right) \\
        P_{\text{equibiaxial}} &= \sum_i \frac{2\mu_i}{\alpha_i}
            \left(\lambda^{\alpha_i - 1} - \lambda^{-2\alpha_i - 1}\right) \\
        P_{\text{pure shear}} &= \sum_i \frac{2\mu_i}{\alpha_i}
            \left(\lambda^{\alpha_i - 1} - \lambda^{-\alpha_i - 1}\right) \\
        \tau_{\text{simple shear}} &= \sum_i \frac{2\mu_i}{\alpha_i}
            \frac{\lambda^{\alpha_i + 1} - \lambda^{1 - \alpha_i}}{\lambda^2 + 1},
            \quad \lambda = \frac{\gamma}{2} + \sqrt{1 + \gamma^2 / 4}

    Uniaxial: :math:`\lambda_2 = \lambda_3 = \lambda^{-1/2}`; equibiaxial:
    :math:`\lambda_1 = \lambda_2 = \lambda`; pure shear: :math:`\lambda_2 = 1`.  For simple
    shear the first argument is the amount of shear :math:`\gamma`, not a stretch, and the
    result is the shear stress.

    Parameters
    ----------
    stretch : array_like, shape (n,)
        Stretch in the loading direction (``gamma`` for simple shear).
    mus, alphas : sequence of float, length N
        Ogden moduli (stress units) and exponents; ``alpha`` must not be 0.
    mode : {"uniaxial", "equibiaxial", "pure-shear", "simple-shear"}

    Returns
    -------
    ndarray, shape (n,)

    Examples
    --------
    Small-strain limit: Young's modulus is 3 mu in uniaxial loading.

    >>> round(float(ogden_nominal_stress(1.001, [720.0], [-4.7]) / 0.001 / (3 * 720.0)), 2)
    1.0
    >>> round(float(ogden_nominal_stress(0.001, [1.0], [2.0], "simple-shear") / 0.001), 6)  # shear modulus
    1.0
    """
    lam = np.asarray(stretch, dtype=float)
    if mode == "simple-shear":
        gamma = lam
        lam = gamma / 2.0 + np.sqrt(1.0 + gamma**2 / 4.0)
    out = np.zeros_like(lam)
    for mu, a in zip(mus, alphas):
        c = 2.0 * mu / a
        if mode == "uniaxial":
            out = out + c * (lam ** (a - 1.0) - lam ** (-a / 2.0 - 1.0))
        elif mode == "equibiaxial":
            out = out + c * (lam ** (a - 1.0) - lam ** (-2.0 * a - 1.0))
        elif mode == "pure-shear":
            out = out + c * (lam ** (a - 1.0) - lam ** (-a - 1.0))
        elif mode == "simple-shear":
            out = out + c * (lam ** (a + 1.0) - lam ** (1.0 - a)) / (lam**2 + 1.0)
        else:
            raise ValueError(f"unknown loading mode {mode!r}; expected one of {MODES}")
    return out


def ogden_energy(stretches, mus, alphas) -> np.ndarray:
    r"""Strain energy density :math:`W` for principal stretches ``stretches`` (shape (..., 3)).

    >>> round(float(ogden_energy([1.0, 1.0, 1.0], [720.0], [-4.7])), 12)
    0.0
    """
    lam = np.asarray(stretches, dtype=float)
    w = 0.0
    for mu, a in zip(mus, alphas):
        w = w + 2.0 * mu / a**2 * (np.sum(lam**a, axis=-1) - 3.0)
    return np.asarray(w)


@dataclass(frozen=True)
class Law:
    """A named hyperelastic law: its parameter names (with units) and their Ogden form."""

    name: str
    param_names: tuple[str, ...]

    @property
    def n_terms(self) -> int:
        return {"neo-hookean": 1, "mooney-rivlin": 2}.get(self.name, len(self.param_names) // 2)

    def ogden_terms(self, params) -> tuple[np.ndarray, np.ndarray]:
        """``(mus, alphas)`` of the equivalent Ogden series for a parameter vector."""
        p = np.asarray(params, dtype=float)
        if self.name == "neo-hookean":
            return p[:1], np.array([2.0])
        if self.name == "mooney-rivlin":
            return np.array([2.0 * p[0], 2.0 * p[1]]), np.array([2.0, -2.0])
        return p[0::2], p[1::2]

    def nominal_stress(self, stretch, params, mode: str = "uniaxial") -> np.ndarray:
        mus, alphas = self.ogden_terms(params)
        return ogden_nominal_stress(stretch, mus, alphas, mode)

    def shear_modulus(self, params) -> float:
        """Initial shear modulus, sum of the Ogden ``mu_i``."""
        return float(np.sum(self.ogden_terms(params)[0]))

    def as_dict(self, params) -> dict[str, float]:
        return {k: float(v) for k, v in zip(self.param_names, params)}


def _ogden_names(n: int) -> tuple[str, ...]:
    if n == 1:
        return ("mu_pa", "alpha")
    return tuple(x for i in range(1, n + 1) for x in (f"mu{i}_pa", f"alpha{i}"))


LAWS: dict[str, Law] = {
    "ogden": Law("ogden", _ogden_names(1)),
    "ogden2": Law("ogden2", _ogden_names(2)),
    "ogden3": Law("ogden3", _ogden_names(3)),
    "neo-hookean": Law("neo-hookean", ("mu_pa",)),
    "mooney-rivlin": Law("mooney-rivlin", ("c10_pa", "c01_pa")),
}


def get_law(name: str) -> Law:
    try:
        return LAWS[name]
    except KeyError:
        raise ValueError(f"unknown model {name!r}; expected one of {sorted(LAWS)}") from None
