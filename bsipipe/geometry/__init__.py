"""Geometry: point-based registration (X-ray frame to CT frame) and isoparametric elements.

``registration`` -- rigid / similarity transforms (Kabsch, Umeyama), FRE, FLE, TRE;
``registration_effects`` -- the register stage's loop (effects ``scale``, ``moving-reference``, ``label-swap``,
``ct-axis-scale``, ``ct-gantry-shear``);
``shape_functions`` -- C3D4, C3D10, C3D6, C3D15, C3D8, C3D20 shape functions, inverse mapping, point location.

The public names are re-exported here and imported on first use, so importing one module
does not import the others.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "registration": ["Similarity", "fit_similarity", "fre", "estimate_fle", "tre_fitzpatrick", "tre_linearized",
                     "tre_perturbation", "leave_one_out", "reference_motion", "tracking_noise", "skull_motion",
                     "point_configuration", "AxisScaledSimilarity", "fit_axis_scaled", "axis_scale_se",
                     "ShearedSimilarity", "fit_sheared", "factor_se", "registration_transform",
                     "rigid_tracking_noise", "skull_tracking_noise"],
    "registration_effects": ["RegistrationSpec", "RegistrationData", "RegistrationFit", "fit_registration",
                             "close_registration_loop", "reference_checks", "ct_positions"],
    "shape_functions": ["ELEMENTS", "ElementType", "element_type", "shape_functions", "shape_derivatives",
                        "inverse_map", "interpolate", "PointLocator", "Location"],
}
_WHERE = {name: mod for mod, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
