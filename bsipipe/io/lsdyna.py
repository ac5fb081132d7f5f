r"""LS-DYNA keyword text: ``*MAT_OGDEN_RUBBER`` (``*MAT_077_O``) for a fitted law.

Convention.  LS-DYNA's Ogden rubber uses Ogden's original form,

.. math::

    W^* = \sum_{i=1}^{3}\sum_{j=1}^{n} \frac{\mu_j}{\alpha_j}\left(\lambda_i^{*\alpha_j} - 1\right)
          + K (J - 1 - \ln J),

whose initial shear modulus is :math:`\tfrac12 \sum_j \mu_j \alpha_j` (the LS-DYNA
Keyword User's Manual, ``*MAT_OGDEN_RUBBER``; OpenRadioss reads this keyword into its
LAW42 and computes the shear modulus as ``(MU1*AL1 + ... + MU5*AL5)/2``,
``starter/source/materials/mat/mat042/hm_read_mat42.F``).  bsipipe's (and ABAQUS's)
:math:`W = \sum_j \frac{2\mu_j}{\alpha_j^2}(\ldots)` therefore maps as
:math:`\mu_j^{\mathrm{DYNA}} = 2\mu_j/\alpha_j`, same :math:`\alpha_j`.  Neo-Hookean and
Mooney-Rivlin are written as their exact Ogden series (``alpha = 2`` and ``2, -2``).

Card layout (fixed format, 8 fields of 10 characters; field positions as in the
keyword manual and ANSYS PyDyna's ``Mat077O``): card 1 ``MID RO PR N NV G SIGF REF``
(``N = 0``: constants given directly); card 3 ``MU1 .. MU8``; card 4 ``ALPHA1 .. ALPHA8``;
then one card ``GI BETAI`` per Prony term.

Bulk modulus.  The card has no ``K``; LS-DYNA derives it from ``PR`` and the shear modulus
of the hyperelastic part, :math:`K = 2G(1+\nu)/(3(1-2\nu))`, so ``PR`` is chosen to give
bsipipe's :math:`K_0` with :math:`G` = the shear modulus written on the card.

Viscoelasticity.  LS-DYNA adds a viscous stress :math:`\int g(t-\tau)\,\dot E\,d\tau`,
:math:`g(t) = \sum_i G_i e^{-\beta_i t}`, to the hyperelastic (equilibrium) stress, so
the card carries the *long-term* Ogden moduli :math:`\mu_j (1 - \sum g_i)`, the shear
relaxation moduli :math:`G_i = g_i G_0` in stress units and :math:`\beta_i = 1/\tau_i`.
This matches bsipipe's Prony series exactly in the small-strain limit; at finite strain
LS-DYNA's viscous term is linear in Green strain rather than a scaled hyperelastic
response (quasi-linear viscoelasticity), a difference of formulation, not of parameters.
"""

from __future__ import annotations

import textwrap
from typing import Sequence

import numpy as np

from bsipipe.io._fe_material import (
    DEFAULT_DENSITY_KG_M3,
    ogden_terms_text,
    poisson_ratio,
    prepare_material,
    unit_system,
)

__all__ = ["lsdyna_material", "lsdyna_ogden_terms", "field10", "parse_fixed_card",
           "field_rounding_bound", "FIELD_WIDTH"]

FIELD_WIDTH = 10


def lsdyna_ogden_terms(mus, alphas) -> tuple[np.ndarray, np.ndarray]:
    """Convert Ogden terms from bsipipe/ABAQUS to LS-DYNA: ``mu_dyna = 2 mu / alpha``.

    >>> lsdyna_ogden_terms([720.0], [-4.7])[0].round(4)
    array([-306.383])
    """
    mus = np.asarray(mus, dtype=float)
    alphas = np.asarray(alphas, dtype=float)
    return 2.0 * mus / alphas, alphas.copy()


def field10(x: float) -> str:
    """A real right-justified in 10 characters, with as many significant digits as fit.

    Tries fixed-point and E-notation (exponent without leading zeros, ``-3.0638E-4``) and
    keeps the text whose value is closest to ``x``.

    >>> field10(0.4995001665)
    '0.49950017'
    >>> field10(-3.0638297872e-4)
    '-3.0638E-4'
    >>> field10(1.04e-9)
    '   1.04E-9'
    """
    return field_real(x, FIELD_WIDTH)


def _trim(s: str) -> str:
    """Drop trailing zeros after the decimal point (keeping one digit): same value, easier
    to read."""
    if "." in s:
        s = s.rstrip("0")
        if s.endswith("."):
            s += "0"
    return s


def _card(values: Sequence) -> str:
    out = []
    for v in values:
        if v is None:
            out.append(" " * FIELD_WIDTH)
        elif isinstance(v, (int, np.integer)):
            out.append(f"{int(v):>{FIELD_WIDTH}d}")
        else:
            out.append(field10(v))
    return "".join(out).rstrip()


def _comment(names: Sequence[str]) -> str:
    """``$#`` header naming the fields, aligned right over them."""
    return "$#" + "".join(f"{n:>{FIELD_WIDTH}}" for n in names)[2:]


def lsdyna_material(law_name: str, params, prony=None, name: str = "BRAIN", mid: int = 1,
                    units: str = "mm-N-s-MPa", *, params_moduli: str = "instantaneous",
                    bulk_modulus_pa: float | None = None,
                    density_kg_m3: float = DEFAULT_DENSITY_KG_M3) -> str:
    """``*MAT_OGDEN_RUBBER_TITLE`` card (an include fragment, no ``*KEYWORD``/``*END``).

    Parameters as for :func:`bsipipe.io.abaqus.abaqus_material`; ``mid`` is the material
    id.  ``RO`` is the density in the deck's units (LS-DYNA requires it).
    """
    mat = prepare_material(law_name, params, prony, params_moduli=params_moduli,
                           bulk_modulus_pa=bulk_modulus_pa, density_kg_m3=density_kg_m3)
    u = unit_system(units)
    if len(mat.mus_pa) > 8:
        raise ValueError("*MAT_OGDEN_RUBBER takes at most 8 Ogden terms")
    long_term = mat.long_term_factor
    mus_dyna, alphas = lsdyna_ogden_terms(mat.mus_pa * long_term * u.per_pa, mat.alphas)
    g_card = float(np.sum(mat.mus_pa)) * long_term  # shear modulus of the hyperelastic part
    pr = poisson_ratio(mat.bulk_modulus_pa, g_card)
    notes = [
        f"bsipipe material {name}: model {mat.law}; {u.describe()}",
        "LS-DYNA Ogden: W = sum_j MU_j/ALPHA_j (l1^a_j + l2^a_j + l3^a_j - 3) + K(J-1-lnJ);",
        "MU_j = 2 mu_j/alpha_j from bsipipe's W = sum 2 mu_j/alpha_j^2 (...), G0 = sum mu_j",
        f"instantaneous terms: {ogden_terms_text(mat.mus_pa, mat.alphas)}",
        f"PR gives K0 = {mat.bulk_modulus_pa:.6g} Pa = "
        f"{mat.bulk_modulus_pa / mat.shear_modulus_pa:.6g} x G0 (nearly incompressible)",
    ]
    if mat.prony:
        notes.append(f"long-term moduli on MU cards (x {long_term:.6g}); GI = g_i G0 in "
                     f"{u.stress}, BETAI = 1/tau_i in 1/{u.time}")
    notes.append(f"RO = {mat.density_kg_m3:g} kg/m^3 in {u.mass}/{u.length}^3")
    # LS-DYNA reads 80 columns
    lines = [f"$ {part}" for note in notes for part in textwrap.wrap(note, 76,
                                                                      subsequent_indent="  ")]
    lines += [
        "*MAT_OGDEN_RUBBER_TITLE",
        name[:80],
        _comment(["mid", "ro", "pr", "n", "nv", "g", "sigf", "ref"]),
        _card([int(mid), mat.density_kg_m3 * u.per_kg_m3, pr, 0]),
        _comment([f"mu{i}" for i in range(1, 9)]),
        _card(list(mus_dyna)),
        _comment([f"alpha{i}" for i in range(1, 9)]),
        _card(list(alphas)),
    ]
    if mat.prony:
        g0_deck = mat.shear_modulus_pa * u.per_pa
        lines.append(_comment(["gi", "betai"]))
        for g, tau in mat.prony:
            lines.append(_card([g * g0_deck, 1.0 / (tau * u.per_s)]))
    return "\n".join(lines) + "\n"


def parse_fixed_card(line: str, n_fields: int = 8) -> list[float | None]:
    """Split a fixed-format card into its 10-character fields (``None`` where blank)."""
    out: list[float | None] = []
    for i in range(n_fields):
        text = line[i * FIELD_WIDTH:(i + 1) * FIELD_WIDTH].strip()
        out.append(float(text) if text else None)
    return out


def field_rounding_bound(text: str) -> float:
    """Half a unit in the last printed digit of a field: how far the printed value may
    be from the number it stands for.

    >>> field_rounding_bound("-3.0638E-4")
    5e-09
    """
    text = text.strip().upper()
    mant, _, exp = text.partition("E")
    decimals = len(mant.split(".")[1]) if "." in mant else 0
    return 0.5 * 10.0 ** (-decimals + (int(exp) if exp else 0))



# --- the FE hand-off deck (bsipipe export-fe) ----------------------------------------------

def field_real(x: float, width: int) -> str:
    """A real right-justified in ``width`` characters, as many significant digits as fit
    (fixed-point or E-notation, whichever is closer to ``x``).

    >>> field_real(-3.0638297872e-4, 16)
    '-3.0638297872E-4'
    >>> field_real(12.5, 8)
    '    12.5'
    """
    x = float(x)
    if not np.isfinite(x):
        raise ValueError(f"{x!r} cannot be written in a keyword field")
    if x == 0.0:
        return f"{'0.0':>{width}}"
    candidates = []
    for dec in range(width, -1, -1):
        s = f"{x:.{dec}f}"
        if len(s) <= width:
            if float(s) != 0.0:
                candidates.append(_trim(s))
            break
    for dig in range(width, -1, -1):
        mant, exp = f"{x:.{dig}E}".split("E")
        s = f"{_trim(mant)}E{int(exp)}"
        if len(s) <= width:
            candidates.append(s)
            break
    if not candidates:
        raise ValueError(f"{x!r} does not fit in {width} characters")
    best = min(candidates, key=lambda s: (abs(float(s) - x), len(s)))
    return f"{best:>{width}}"


def _fixed(values: Sequence, widths: Sequence[int]) -> str:
    out = []
    for v, w in zip(values, widths):
        if v is None:
            out.append(" " * w)
        elif isinstance(v, (int, np.integer)):
            s = f"{int(v):>{w}d}"
            if len(s) > w:
                raise ValueError(f"{v} does not fit in {w} columns")
            out.append(s)
        else:
            # one column short of the field, right-justified: a blank before every real, so
            # two full-width numbers never run together (LS-DYNA reads the columns either
            # way; a person, a diff or a free-format reader needs the gap)
            out.append(f"{field_real(v, w - 1):>{w}}")
    return "".join(out).rstrip()


def lsdyna_nodes(node_ids, xyz) -> str:
    """``*NODE``: ``NID`` (8 columns), ``X Y Z`` (16 each), 56 columns a line."""
    xyz = np.asarray(xyz, dtype=float)
    lines = ["*NODE", "$#   nid               x               y               z"]
    lines += [_fixed([int(n), *p], (8, 16, 16, 16)) for n, p in zip(node_ids, xyz)]
    return "\n".join(lines) + "\n"


def lsdyna_solids(element_ids, connectivity, pid: int) -> str:
    """``*ELEMENT_SOLID``: ``EID PID N1 .. N8`` (8 columns each, 80 a line); a 4-node
    tetrahedron repeats its last node (``N4`` to ``N8``), LS-DYNA's degenerate form."""
    lines = ["*ELEMENT_SOLID", "$#   eid     pid      n1      n2      n3      n4      n5      n6      n7      n8"]
    for e, conn in zip(element_ids, np.asarray(connectivity)):
        c = list(conn[:8]) if len(conn) >= 8 else list(conn[:4]) + [conn[3]] * 4
        lines.append(_fixed([int(e), int(pid), *[int(v) for v in c]], (8,) * 10))
    return "\n".join(lines) + "\n"


def lsdyna_node_set(sid: int, node_ids, title: str | None = None) -> str:
    """``*SET_NODE_LIST[_TITLE]``: eight node ids (10 columns each) a line."""
    ids = [int(i) for i in node_ids]
    lines = ["*SET_NODE_LIST" + ("_TITLE" if title else "")]
    if title:
        lines.append(title[:80])
    lines.append(_fixed([int(sid)], (10,)))
    lines += [_fixed(ids[i:i + 8], (10,) * 8) for i in range(0, len(ids), 8)]
    return "\n".join(lines) + "\n"


def lsdyna_curve(lcid: int, abscissa, ordinate, title: str | None = None) -> str:
    """``*DEFINE_CURVE[_TITLE]``: ``LCID`` card, then ``A O`` pairs (20 columns each)."""
    a = np.asarray(abscissa, dtype=float)
    o = np.asarray(ordinate, dtype=float)
    lines = ["*DEFINE_CURVE" + ("_TITLE" if title else "")]
    if title:
        lines.append(title[:80])
    lines += ["$#    lcid      sidr       sfa       sfo      offa      offo    dattyp",
              _fixed([int(lcid), 0, 1.0, 1.0, 0.0, 0.0, 0], (10,) * 7),
              "$#                a1                  o1"]
    lines += [_fixed([x, y], (20, 20)) for x, y in zip(a, o)]
    return "\n".join(lines) + "\n"


def lsdyna_discrete_springs(element_ids, node_pairs, normals, stiffness, *, pid: int, secid: int,
                            mid: int, first_vid: int = 1, title: str = "brain-skull interface",
                            fixed_direction: bool = True) -> str:
    """Linear springs between node pairs, each acting along its own fixed direction (or,
    ``fixed_direction=False``, along the line joining its nodes, which turns with them).

    ``*MAT_SPRING_ELASTIC`` (``MID``, ``K``), ``*SECTION_DISCRETE`` (translational), a
    ``*PART``, one ``*DEFINE_SD_ORIENTATION`` per spring (``IOP = 0``: deflection measured and
    force applied along the fixed vector, the interface normal; none when not
    ``fixed_direction``) and ``*ELEMENT_DISCRETE``
    (``EID PID N1 N2 VID S PF OFFSET``; 8/8/8/8/8/16/8/16 columns).  ``stiffness``: one value,
    or one per spring: the material then holds the largest and each element's scale factor
    ``S`` its share (LS-DYNA scales the spring's force by ``S``).
    """
    normals = np.asarray(normals, dtype=float)
    k = np.broadcast_to(np.asarray(stiffness, dtype=float), (len(element_ids),))
    k_mat = float(k.max()) if len(k) else float(np.asarray(stiffness, dtype=float).max())
    scale = k / k_mat if k_mat > 0 else np.ones(len(k))
    lines = ["*MAT_SPRING_ELASTIC_TITLE", title[:80], "$#     mid         k",
             _fixed([int(mid), k_mat], (10, 10)),
             "*SECTION_DISCRETE_TITLE", title[:80],
             "$#   secid       dro        kd        v0        cl        fd",
             _fixed([int(secid), 0, 0.0, 0.0, 0.0, 0.0], (10,) * 6),
             "*PART", title[:80], "$#     pid     secid       mid",
             _fixed([int(pid), int(secid), int(mid)], (10, 10, 10))]
    if fixed_direction:
        lines += ["*DEFINE_SD_ORIENTATION",
                  "$#     vid       iop        xt        yt        zt      nid1      nid2"]
        for k, n in enumerate(normals):
            lines.append(_fixed([int(first_vid + k), 0, *n], (10, 10, 10, 10, 10)))
    lines += ["*ELEMENT_DISCRETE", "$#   eid     pid      n1      n2     vid               s      pf          offset"]
    for k, (e, (a, b)) in enumerate(zip(element_ids, np.asarray(node_pairs))):
        vid = int(first_vid + k) if fixed_direction else 0
        lines.append(_fixed([int(e), int(pid), int(a), int(b), vid, float(scale[k])], (8, 8, 8, 8, 8, 16)))
    return "\n".join(lines) + "\n"


def lsdyna_indentation_deck(*, comments: Sequence[str], node_ids, node_xyz, blocks, material_card: str,
                            mid: int, anchor_ids, anchor_xyz, spring_ids, spring_pairs, spring_normals,
                            spring_stiffness, indentor_nodes, axis, curve_time, curve_value,
                            end_time: float, dt_initial: float, dt_max: float, output_dt: float,
                            element_formulation: int = 2, fixed_direction: bool = True) -> str:
    """A complete LS-DYNA keyword deck (implicit, static) of the in situ indentation, every
    number already in the deck's units.

    Parts: 1 the brain (``*SECTION_SOLID``, ``ELFORM`` ``element_formulation``, material
    ``mid``), 2 the interface springs (:func:`lsdyna_discrete_springs`, to fixed skull nodes,
    each along its fixed normal unless not ``fixed_direction``).  Node sets: 1 the
    indentor's nodes, prescribed ``u = axis * curve(t)`` component by component (``*BOUNDARY_PRESCRIBED_MOTION_SET``,
    displacement, ``SF`` = the axis component of curve 1); 2 the skull nodes, fixed
    (``*BOUNDARY_SPC_SET``).  Every line is at most 80 columns.
    """
    spring_mid = mid + 1
    parts = ["*KEYWORD"]
    parts += [f"$ {part}" for c in comments for part in textwrap.wrap(c, 76, subsequent_indent="  ")]
    parts.append("*TITLE\nbsipipe export-fe: in situ indentation of the brain")
    parts.append("\n".join([
        "*CONTROL_TERMINATION", "$#  endtim", _fixed([float(end_time)], (10,)),
        "*CONTROL_IMPLICIT_GENERAL", "$#  imflag       dt0", _fixed([1, float(dt_initial)], (10, 10)),
        "*CONTROL_IMPLICIT_SOLUTION", "$#  nsolvr", _fixed([12], (10,)),
        "*CONTROL_IMPLICIT_AUTO", "$#   iauto    iteopt    itewin     dtmin     dtmax",
        _fixed([1, 11, 5, float(dt_max) * 1e-4, float(dt_max)], (10,) * 5),
        "*DATABASE_BINARY_D3PLOT", "$#      dt", _fixed([float(output_dt)], (10,)),
        "*DATABASE_NODOUT", "$#      dt", _fixed([float(output_dt)], (10,)),
        "*DATABASE_HISTORY_NODE_SET", "$#     id1", _fixed([1], (10,)),
    ]))
    parts.append(material_card.rstrip("\n"))
    parts.append("\n".join(["*SECTION_SOLID_TITLE", "brain", "$#   secid    elform",
                            _fixed([1, int(element_formulation)], (10, 10)),
                            "*PART", "brain", "$#     pid     secid       mid",
                            _fixed([1, 1, int(mid)], (10, 10, 10))]))
    parts.append(lsdyna_nodes(node_ids, node_xyz).rstrip("\n"))
    parts.append(lsdyna_nodes(anchor_ids, anchor_xyz).rstrip("\n"))
    for _, eids, conn in blocks:
        parts.append(lsdyna_solids(eids, conn, 1).rstrip("\n"))
    parts.append(lsdyna_discrete_springs(spring_ids, spring_pairs, spring_normals, spring_stiffness,
                                         pid=2, secid=2, mid=spring_mid,
                                         fixed_direction=fixed_direction).rstrip("\n"))
    parts.append(lsdyna_node_set(1, indentor_nodes, "indentor").rstrip("\n"))
    parts.append(lsdyna_node_set(2, anchor_ids, "skull").rstrip("\n"))
    parts.append(lsdyna_curve(1, curve_time, curve_value, "indentor depth after contact").rstrip("\n"))
    pm = ["*BOUNDARY_PRESCRIBED_MOTION_SET",
          "$#    nsid       dof       vad      lcid        sf       vid     death     birth"]
    for dof, a in zip((1, 2, 3), np.asarray(axis, float)):
        pm.append(_fixed([1, dof, 2, 1, float(a)], (10,) * 5))
    parts.append("\n".join(pm))
    parts.append("\n".join(["*BOUNDARY_SPC_SET", "$#    nsid       cid      dofx      dofy      dofz",
                            _fixed([2, 0, 1, 1, 1, 0, 0, 0], (10,) * 8)]))
    parts.append("*END")
    return "\n".join(parts) + "\n"


__all__ += ["field_real", "lsdyna_nodes", "lsdyna_solids", "lsdyna_node_set", "lsdyna_curve",
            "lsdyna_discrete_springs", "lsdyna_indentation_deck"]
