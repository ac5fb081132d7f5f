r"""FEBio XML: the ``<Material>`` section for a fitted law.

Conventions, from FEBio's source (``FEBioMech/FEOgdenMaterial.cpp``,
``FEMooneyRivlin``, ``FEUncoupledViscoElasticMaterial.cpp``) and user manual (4.1.2.9
"Ogden"):

* ``type="Ogden"`` is uncoupled:
  :math:`W = \sum_i \frac{c_i}{m_i^2}(\tilde\lambda_1^{m_i} + \tilde\lambda_2^{m_i}
  + \tilde\lambda_3^{m_i} - 3) + U(J)` (its deviatoric Cauchy stress is
  :math:`\sum_i \frac{c_i}{m_i}\,\mathrm{dev}(\tilde\lambda^{m_i})/J`), so
  :math:`c_i = 2\mu_i`, :math:`m_i = \alpha_i`; ``k`` is the bulk modulus of
  :math:`U(J) = \tfrac{k}{2}(\ln J)^2`, equal to :math:`K_0` at small strain.
* Neo-Hookean and Mooney-Rivlin are written as the uncoupled ``type="Mooney-Rivlin"``,
  :math:`W = c_1(\tilde I_1 - 3) + c_2(\tilde I_2 - 3) + U(J)`: ``c1 = C10 = mu/2``
  (neo-Hookean, ``c2 = 0``) and ``c1 = C10``, ``c2 = C01``.
* A Prony series wraps the law in ``type="uncoupled viscoelastic"``: FEBio relaxes the
  deviatoric second Piola-Kirchhoff stress,
  :math:`S = g_0 S^e + \sum_i g_i H_i`, with :math:`H_i \to S^e` at :math:`t = 0` and
  :math:`H_i \to 0` as :math:`t \to \infty`, and adds the elastic material's bulk
  response unrelaxed.  With the elastic part holding the *instantaneous* moduli, ``g_i``
  are bsipipe's (ABAQUS's) normalised moduli, ``t_i = tau_i`` and
  :math:`g_0 = 1 - \sum g_i`.

FEBio has no built-in units; numbers are written in the chosen unit system, stated in a
comment.  The result is a standalone document ``<febio_spec version="4.0"><Material>``
to merge into a model.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from bsipipe.io._fe_material import (
    DEFAULT_DENSITY_KG_M3,
    number,
    ogden_terms_text,
    prepare_material,
    stiffness_groups,
    unit_system,
)

__all__ = ["febio_material", "febio_ogden_terms"]


def febio_ogden_terms(mus, alphas) -> tuple[np.ndarray, np.ndarray]:
    """Convert Ogden terms from bsipipe/ABAQUS to FEBio: ``c = 2 mu``, ``m = alpha``.

    >>> febio_ogden_terms([720.0], [-4.7])
    (array([1440.]), array([-4.7]))
    """
    return 2.0 * np.asarray(mus, dtype=float), np.asarray(alphas, dtype=float).copy()


def _param(parent: ET.Element, tag: str, value: float) -> None:
    ET.SubElement(parent, tag).text = number(value)


def febio_material(law_name: str, params, prony=None, name: str = "BRAIN", mat_id: int = 1,
                   units: str = "mm-N-s-MPa", *, params_moduli: str = "instantaneous",
                   bulk_modulus_pa: float | None = None,
                   density_kg_m3: float = DEFAULT_DENSITY_KG_M3) -> str:
    """FEBio 4 ``<Material>`` section as a standalone XML document.

    Parameters as for :func:`bsipipe.io.abaqus.abaqus_material`; ``mat_id`` is the
    material id.

    >>> root = ET.fromstring(febio_material("ogden", {"mu_pa": 720.0, "alpha": -4.7}))
    >>> root.find("Material/material").get("type"), root.find("Material/material/c1").text
    ('Ogden', '0.00144')
    """
    mat = prepare_material(law_name, params, prony, params_moduli=params_moduli,
                           bulk_modulus_pa=bulk_modulus_pa, density_kg_m3=density_kg_m3)
    u = unit_system(units)
    if len(mat.mus_pa) > 6:
        raise ValueError("FEBio's Ogden material takes at most 6 terms")

    root = ET.Element("febio_spec", version="4.0")
    section = ET.SubElement(root, "Material")
    section.append(ET.Comment(f" bsipipe material {name}: model {mat.law}; {u.describe()} "))
    section.append(ET.Comment(f" instantaneous Ogden terms, W = sum 2 mu_i/alpha_i^2 (...): "
                              f"{ogden_terms_text(mat.mus_pa, mat.alphas)}; FEBio c_i = 2 mu_i "))
    section.append(ET.Comment(f" k = K0 = {mat.bulk_modulus_pa:.6g} Pa = "
                              f"{mat.bulk_modulus_pa / mat.shear_modulus_pa:.6g} x G0 "
                              f"(nearly incompressible); density {mat.density_kg_m3:g} kg/m^3 "))
    top = ET.SubElement(section, "material", id=str(int(mat_id)), name=name)
    if mat.prony:
        top.set("type", "uncoupled viscoelastic")
        top.append(ET.Comment(f" g_i normalised by the instantaneous shear modulus, t_i in "
                              f"{u.time}; elastic part holds instantaneous moduli "))
        _param(top, "density", mat.density_kg_m3 * u.per_kg_m3)
        _param(top, "g0", mat.long_term_factor)
        for i, (g, tau) in enumerate(mat.prony, start=1):
            _param(top, f"g{i}", g)
            _param(top, f"t{i}", tau * u.per_s)
        elastic = ET.SubElement(top, "elastic")
    else:
        elastic = top
        _param(elastic, "density", mat.density_kg_m3 * u.per_kg_m3)
    _param(elastic, "k", mat.bulk_modulus_pa * u.per_pa)
    if mat.law in ("neo-hookean", "mooney-rivlin"):
        elastic.set("type", "Mooney-Rivlin")
        c10 = mat.law_params[0] / 2.0 if mat.law == "neo-hookean" else mat.law_params[0]
        c01 = 0.0 if mat.law == "neo-hookean" else mat.law_params[1]
        _param(elastic, "c1", c10 * u.per_pa)
        _param(elastic, "c2", c01 * u.per_pa)
    else:
        elastic.set("type", "Ogden")
        cs, ms = febio_ogden_terms(mat.mus_pa * u.per_pa, mat.alphas)
        for i, (c, m) in enumerate(zip(cs, ms), start=1):
            _param(elastic, f"c{i}", c)
            _param(elastic, f"m{i}", m)
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


# --- the FE hand-off model (bsipipe export-fe) ---------------------------------------------

_FEBIO_ELEMENT = {"C3D8": ("hex8", 8), "C3D4": ("tet4", 4)}


def febio_loadcurve(parent: ET.Element, lc_id: int, time, value, name: str = "indent") -> ET.Element:
    """``<load_controller type="loadcurve">`` (FEBio 4), linear, held constant outside."""
    lc = ET.SubElement(parent, "load_controller", id=str(int(lc_id)), name=name, type="loadcurve")
    ET.SubElement(lc, "interpolate").text = "LINEAR"
    ET.SubElement(lc, "extend").text = "CONSTANT"
    pts = ET.SubElement(lc, "points")
    for t, v in zip(np.asarray(time, float), np.asarray(value, float)):
        ET.SubElement(pts, "pt").text = f"{number(t)},{number(v)}"
    return lc


def febio_indentation_model(*, comments, node_ids, node_xyz, blocks, material_xml: str, anchor_ids, anchor_xyz,
                            spring_pairs, spring_stiffness, indentor_nodes, axis, curve_time,
                            curve_value, time_steps: int, step_size: float, dt_max: float) -> str:
    """A complete FEBio 4 model (``febio_spec version="4.0"``) of the in situ indentation,
    every number already in the model's units.

    ``<Mesh>``: the brain's nodes and ``hex8``/``tet4`` elements (``blocks``: ``(ABAQUS base
    type C3D8/C3D4, element ids, connectivity)``), the skull nodes, node sets ``indentor`` and
    ``skull``, the ``DiscreteSet`` ``interface`` (brain node, skull node); the material of
    ``material_xml`` (:func:`febio_material`'s document) on the solid domain; ``linear
    spring`` discrete material of stiffness ``spring_stiffness`` on the interface set (one
    value, or one per spring: a set ``interface_k{j}`` and its material per distinct value);
    ``zero displacement`` on the skull, ``prescribed displacement`` of the indentor's nodes
    ``u = axis * curve(t)`` component by component (load controller 1); a static analysis
    of ``time_steps`` x ``step_size`` with automatic time stepping up to ``dt_max``.
    FEBio's linear springs act along the line joining their nodes (they turn with them).
    """
    root = ET.Element("febio_spec", version="4.0")
    for c in comments:
        root.append(ET.Comment(f" {c} "))
    ET.SubElement(root, "Module", type="solid")
    control = ET.SubElement(root, "Control")
    ET.SubElement(control, "analysis").text = "STATIC"
    ET.SubElement(control, "time_steps").text = str(int(time_steps))
    _param(control, "step_size", step_size)
    stepper = ET.SubElement(control, "time_stepper", type="default")
    ET.SubElement(stepper, "max_retries").text = "10"
    ET.SubElement(stepper, "opt_iter").text = "10"
    _param(stepper, "dtmin", dt_max * 1e-5)
    _param(stepper, "dtmax", dt_max)
    solver = ET.SubElement(control, "solver", type="solid")
    ET.SubElement(solver, "max_refs").text = "25"
    material = ET.fromstring(material_xml).find("Material")
    mat = material.find("material")
    mat_name = mat.get("name")
    root.append(material)
    mesh = ET.SubElement(root, "Mesh")
    nodes = ET.SubElement(mesh, "Nodes", name="brain")
    for n, p in zip(node_ids, np.asarray(node_xyz, float)):
        ET.SubElement(nodes, "node", id=str(int(n))).text = ",".join(number(v) for v in p)
    skull = ET.SubElement(mesh, "Nodes", name="skull")
    for n, p in zip(anchor_ids, np.asarray(anchor_xyz, float)):
        ET.SubElement(skull, "node", id=str(int(n))).text = ",".join(number(v) for v in p)
    for k, (base, eids, conn) in enumerate(blocks):
        kind, nn = _FEBIO_ELEMENT[base]
        el = ET.SubElement(mesh, "Elements", type=kind, name="brain" if k == 0 else f"brain{k + 1}")
        for e, row in zip(eids, np.asarray(conn)):
            ET.SubElement(el, "elem", id=str(int(e))).text = ",".join(str(int(v)) for v in row[:nn])
    ET.SubElement(mesh, "NodeSet", name="indentor").text = ",".join(str(int(v)) for v in indentor_nodes)
    ET.SubElement(mesh, "NodeSet", name="skull").text = ",".join(str(int(v)) for v in anchor_ids)
    values, group = stiffness_groups(spring_stiffness, len(spring_pairs))
    set_names = ["interface"] if len(values) == 1 else [f"interface_k{j + 1}" for j in range(len(values))]
    pairs = np.asarray(spring_pairs)
    for j, name in enumerate(set_names):
        dset = ET.SubElement(mesh, "DiscreteSet", name=name)
        for a, b in pairs[group == j]:
            ET.SubElement(dset, "delem").text = f"{int(a)},{int(b)}"
    domains = ET.SubElement(root, "MeshDomains")
    for k in range(len(blocks)):
        ET.SubElement(domains, "SolidDomain", name="brain" if k == 0 else f"brain{k + 1}", mat=mat_name)
    boundary = ET.SubElement(root, "Boundary")
    fixed = ET.SubElement(boundary, "bc", name="skull", node_set="skull", type="zero displacement")
    for d in ("x_dof", "y_dof", "z_dof"):
        ET.SubElement(fixed, d).text = "1"
    for dof, a in zip("xyz", np.asarray(axis, float)):
        bc = ET.SubElement(boundary, "bc", name=f"indentor_{dof}", node_set="indentor",
                           type="prescribed displacement")
        ET.SubElement(bc, "dof").text = dof
        ET.SubElement(bc, "value", lc="1").text = number(a)
        ET.SubElement(bc, "relative").text = "0"
    discrete = ET.SubElement(root, "Discrete")
    for j, (name, v) in enumerate(zip(set_names, values)):
        dmat = ET.SubElement(discrete, "discrete_material", id=str(j + 1), name=name, type="linear spring")
        _param(dmat, "E", float(v))
    for j, name in enumerate(set_names):
        ET.SubElement(discrete, "discrete", dmat=str(j + 1), discrete_set=name)
    febio_loadcurve(ET.SubElement(root, "LoadData"), 1, curve_time, curve_value)
    output = ET.SubElement(root, "Output")
    plot = ET.SubElement(output, "plotfile", type="febio")
    for var in ("displacement", "reaction forces", "stress"):
        ET.SubElement(plot, "var", type=var)
    logfile = ET.SubElement(output, "logfile")
    ET.SubElement(logfile, "node_data", data="ux;uy;uz;Rx;Ry;Rz", delim=",").text = ",".join(
        str(int(v)) for v in indentor_nodes)
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


__all__ += ["febio_loadcurve", "febio_indentation_model"]
