r"""ABAQUS input text: material cards (``*MATERIAL`` with ``*HYPERELASTIC``,
``*VISCOELASTIC``, ``*DENSITY``) and the few mesh keywords later stages need.

Conventions (ABAQUS Analysis User's Guide, "Hyperelastic behavior of rubberlike
materials"; also what CalculiX implements, ``src/rubber.f``, and how it reads the data
lines, ``src/hyperelastics.f``):

* ``*HYPERELASTIC, OGDEN, N=n``:
  :math:`U = \sum_i \frac{2\mu_i}{\alpha_i^2}(\bar\lambda_1^{\alpha_i} + \bar\lambda_2^{\alpha_i}
  + \bar\lambda_3^{\alpha_i} - 3) + \sum_i \frac{1}{D_i}(J - 1)^{2i}`, exactly bsipipe's
  convention, so ``mu_i`` pass through (unit conversion only).  Data lines: ``mu1, alpha1,
  ..., mun, alphan, D1, ..., Dn``, eight values a line.
* ``*HYPERELASTIC, NEO HOOKE``: :math:`U = C_{10}(\bar I_1 - 3) + (J-1)^2/D_1`, ``C10 = mu/2``.
* ``*HYPERELASTIC, MOONEY-RIVLIN``: :math:`U = C_{10}(\bar I_1 - 3) + C_{01}(\bar I_2 - 3)
  + (J-1)^2/D_1`.
* :math:`K_0 = 2/D_1`.  ``D2 .. Dn`` are written as 0 (no higher-order volumetric terms in
  ABAQUS).  CalculiX replaces a zero ``D_i`` (i > 1) by :math:`(0.1/\mu_0)^i` with a
  warning; that adds :math:`(J-1)^{2i}/D_i`, below 1e-9 of the stress at the volume
  changes of a nearly incompressible solid.
* ``*VISCOELASTIC, TIME=PRONY``: data lines ``g_i, k_i, tau_i`` with ``g_i`` the shear
  relaxation moduli normalised by the instantaneous modulus; ``k_i = 0`` (the bulk
  modulus does not relax).  ``*HYPERELASTIC, ..., MODULI=INSTANTANEOUS`` says the
  hyperelastic constants are the instantaneous ones (``MODULI=LONG TERM``, ABAQUS's
  default, that they are :math:`G_\infty = G_0(1 - \sum g_i)`); the card states which.
  CalculiX ignores ``MODULI`` (with a warning) and has no ``*VISCOELASTIC``.  ABAQUS
  relaxes only in a ``*VISCO`` step (``*STATIC`` uses the instantaneous moduli), so the
  hand-off deck's steps are ``*VISCO`` with a Prony series; CalculiX runs ``*VISCO`` as a
  quasi-static step (verified: the same increments and displacements as ``*STATIC``).

Every card starts with ``**`` comment lines naming the unit system and what each number
is.  Numbers carry 14 significant digits in at most 20 characters (CalculiX reads
``f20.0`` fields).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from bsipipe.io._fe_material import (
    DEFAULT_DENSITY_KG_M3,
    FEMaterial,
    number,
    ogden_terms_text,
    prepare_material,
    stiffness_groups,
    unit_system,
)

__all__ = ["abaqus_material", "abaqus_hyperelastic_data", "abaqus_nodes", "abaqus_elements",
           "abaqus_nset"]


def _lines_of(values: Sequence[float], per_line: int = 8) -> list[str]:
    return [", ".join(number(v) for v in values[i:i + per_line])
            for i in range(0, len(values), per_line)]


def abaqus_hyperelastic_data(mat: FEMaterial, units: str = "mm-N-s-MPa", *,
                             moduli: str = "instantaneous",
                             d1: float | None = None) -> tuple[str, list[float]]:
    """The ``*HYPERELASTIC`` option and its data values for ``mat`` in ``units``.

    Returns
    -------
    option : str
        ``"OGDEN, N=n"``, ``"NEO HOOKE"`` or ``"MOONEY-RIVLIN"``.
    values : list of float
        The data values in the deck's units, in ABAQUS's order (``D_i`` last).
    """
    u = unit_system(units)
    scale = mat.moduli(moduli) * u.per_pa
    d1_deck = 2.0 / (mat.bulk_modulus_pa * u.per_pa) if d1 is None else float(d1)
    if mat.law == "neo-hookean":
        return "NEO HOOKE", [mat.law_params[0] / 2.0 * scale, d1_deck]
    if mat.law == "mooney-rivlin":
        return "MOONEY-RIVLIN", [mat.law_params[0] * scale, mat.law_params[1] * scale, d1_deck]
    n = len(mat.mus_pa)
    if n > 3:
        raise ValueError("ABAQUS/CalculiX Ogden cards are written for N <= 3 here")
    values: list[float] = []
    for mu, a in zip(mat.mus_pa, mat.alphas):
        values += [mu * scale, float(a)]
    values += [d1_deck] + [0.0] * (n - 1)
    return f"OGDEN, N={n}", values


def abaqus_material(law_name: str, params, prony=None, name: str = "BRAIN",
                    d1: float | None = None, units: str = "mm-N-s-MPa", *,
                    params_moduli: str = "instantaneous", moduli: str = "instantaneous",
                    bulk_modulus_pa: float | None = None,
                    density_kg_m3: float | None = DEFAULT_DENSITY_KG_M3) -> str:
    """ABAQUS ``*MATERIAL`` card for a fitted law.

    Parameters
    ----------
    law_name, params, prony
        As for :func:`bsipipe.io._fe_material.prepare_material` (``params`` in Pa, a
        ``fit.json`` ``params`` mapping works as is).
    name : str
        Material name.
    d1 : float, optional
        ``D1`` in the deck's units (1/stress); overrides ``bulk_modulus_pa``.
    units : str
        Unit system of the deck (``mm-N-s-MPa`` default; ``mm-kg-s-kPa``, forces in mN,
        recommended for brain meshes in implicit solvers; ``mm-kg-ms-GPa``,
        ``mm-g-ms-MPa``, ``m-kg-s-Pa``).
    params_moduli : {"instantaneous", "long-term"}
        What ``params`` describe when a Prony series is given.
    moduli : {"instantaneous", "long-term"}
        What the written hyperelastic constants describe (``MODULI=`` on the card).
    bulk_modulus_pa : float, optional
        Default ``1000 * G0`` (Poisson's ratio 0.4995).
    density_kg_m3 : float or None
        Written as ``*DENSITY``; ``None`` leaves it out.

    Examples
    --------
    >>> card = abaqus_material("ogden", {"mu_pa": 720.0, "alpha": -4.7})
    >>> [l for l in card.splitlines() if not l.startswith("**")][:3]
    ['*MATERIAL, NAME=BRAIN', '*HYPERELASTIC, OGDEN, N=1', '0.00072, -4.7, 2.7777777777778']
    """
    mat = prepare_material(law_name, params, prony, params_moduli=params_moduli,
                           bulk_modulus_pa=bulk_modulus_pa,
                           density_kg_m3=DEFAULT_DENSITY_KG_M3 if density_kg_m3 is None
                           else density_kg_m3)
    u = unit_system(units)
    option, values = abaqus_hyperelastic_data(mat, units, moduli=moduli, d1=d1)
    k_deck = mat.bulk_modulus_pa * u.per_pa if d1 is None else 2.0 / float(d1)
    lines = [
        f"** bsipipe material {name}: model {mat.law}; {u.describe()}",
        f"** instantaneous Ogden terms (W = sum 2 mu_i/alpha_i^2 (l1^a + l2^a + l3^a - 3)): "
        f"{ogden_terms_text(mat.mus_pa, mat.alphas)}",
        f"** D1 = 2/K0 with K0 = {k_deck:.6g} {u.stress} "
        f"({k_deck / (mat.shear_modulus_pa * u.per_pa):.6g} x G0; nearly incompressible)",
    ]
    hyper = f"*HYPERELASTIC, {option}"
    if mat.prony:
        lines.append(f"** hyperelastic constants are {moduli} moduli; Prony g_i normalised by "
                     f"the instantaneous shear modulus, bulk does not relax (k_i = 0), "
                     f"tau_i in {u.time}")
        hyper += ", MODULI=" + {"instantaneous": "INSTANTANEOUS",
                                "long-term": "LONG TERM"}[moduli]
    lines += [f"*MATERIAL, NAME={name}", hyper, *_lines_of(values)]
    if mat.prony:
        lines.append("*VISCOELASTIC, TIME=PRONY")
        lines += [", ".join(number(v) for v in (g, 0.0, tau * u.per_s)) for g, tau in mat.prony]
    if density_kg_m3 is not None:
        lines += [f"** density {mat.density_kg_m3:g} kg/m^3 in {u.mass}/{u.length}^3",
                  "*DENSITY", number(mat.density_kg_m3 * u.per_kg_m3)]
    return "\n".join(lines) + "\n"


def abaqus_nodes(node_ids: Sequence[int], xyz, nset: str | None = None) -> str:
    """``*NODE`` block: one line ``id, x, y, z`` per node (coordinates in deck length)."""
    xyz = np.asarray(xyz, dtype=float)
    head = "*NODE" + (f", NSET={nset}" if nset else "")
    body = [f"{int(i)}, " + ", ".join(number(c) for c in p) for i, p in zip(node_ids, xyz)]
    return "\n".join([head, *body]) + "\n"


def abaqus_elements(element_type: str, element_ids: Sequence[int], connectivity,
                    elset: str | None = None) -> str:
    """``*ELEMENT`` block (ABAQUS node ordering is the caller's responsibility)."""
    head = f"*ELEMENT, TYPE={element_type}" + (f", ELSET={elset}" if elset else "")
    body = [", ".join(str(int(v)) for v in (e, *conn))
            for e, conn in zip(element_ids, connectivity)]
    return "\n".join([head, *body]) + "\n"


def abaqus_nset(name: str, node_ids: Sequence[int]) -> str:
    """``*NSET`` block, 16 ids a line (ABAQUS's limit for data lines)."""
    ids = [str(int(i)) for i in node_ids]
    body = [", ".join(ids[i:i + 16]) for i in range(0, len(ids), 16)]
    return "\n".join([f"*NSET, NSET={name}", *body]) + "\n"


# --- the FE hand-off deck (bsipipe export-fe) ----------------------------------------------

def abaqus_amplitude(name: str, time, value, *, time_kind: str = "STEP TIME") -> str:
    """``*AMPLITUDE`` (tabular, linear between points): four ``time, value`` pairs a line
    (ABAQUS's layout).  Times are step times (the default of ABAQUS and CalculiX, which
    rejects ``TIME=STEP TIME`` as a parameter) unless ``time_kind="TOTAL TIME"``."""
    time = np.asarray(time, dtype=float)
    value = np.asarray(value, dtype=float)
    if time.shape != value.shape or time.ndim != 1 or len(time) < 2:
        raise ValueError("an amplitude needs two equal 1-D arrays of at least two points")
    if np.any(np.diff(time) <= 0):
        raise ValueError("amplitude times must increase")
    if time_kind not in ("STEP TIME", "TOTAL TIME"):
        raise ValueError(f"time_kind must be 'STEP TIME' or 'TOTAL TIME', not {time_kind!r}")
    flat = np.column_stack([time, value]).ravel()
    head = f"*AMPLITUDE, NAME={name}" + (", TIME=TOTAL TIME" if time_kind == "TOTAL TIME" else "")
    return "\n".join([head, *_lines_of(list(flat))]) + "\n"


def abaqus_springa(element_ids: Sequence[int], node_pairs, stiffness, elset: str) -> str:
    """Axial springs: ``*ELEMENT, TYPE=SPRINGA`` (``id, n1, n2`` a line) and their
    ``*SPRING, ELSET=`` card.

    For ``SPRINGA`` the card's first data line (the degrees of freedom of ``SPRING1/2``) is
    left blank, the second holds the stiffness (force per length, deck units).  ``stiffness``
    is one value, or one per spring: springs of equal stiffness then share an element set
    ``{elset}_K{j}`` and its ``*SPRING`` card, and ``elset`` holds them all.
    """
    def real(v) -> str:
        # with a decimal point: CalculiX takes a data line of whole numbers after *SPRING for
        # the degrees of freedom (SPRING1/2), then finds no stiffness ("card without data")
        s = number(v)
        return s if any(c in s for c in ".eEnN") else s + "."

    values, group = stiffness_groups(stiffness, len(element_ids))
    if len(values) == 1:
        head = abaqus_elements("SPRINGA", element_ids, node_pairs, elset=elset)
        return head + "\n".join([f"*SPRING, ELSET={elset}", "", real(values[0])]) + "\n"
    ids, pairs = np.asarray(element_ids), np.asarray(node_pairs)
    out, names = [], []
    for j, v in enumerate(values):
        sel = group == j
        name = f"{elset}_K{j + 1}"
        names.append(name)
        out.append(abaqus_elements("SPRINGA", ids[sel], pairs[sel], elset=name))
        out.append("\n".join([f"*SPRING, ELSET={name}", "", real(v)]) + "\n")
    out.append(f"*ELSET, ELSET={elset}\n" + "\n".join(", ".join(names[i:i + 8]) for i in range(0, len(names), 8))
               + "\n")
    return "".join(out)


def abaqus_boundary(nset: str, dofs: Sequence[int], values: Sequence[float] | None = None,
                    amplitude: str | None = None) -> str:
    """``*BOUNDARY`` lines ``nset, dof, dof[, value]`` (one per dof), optionally scaled by
    ``*AMPLITUDE`` ``amplitude`` (values are then multiplied by it)."""
    head = "*BOUNDARY" + (f", AMPLITUDE={amplitude}" if amplitude else "")
    if values is None:
        body = [f"{nset}, {int(d)}, {int(d)}" for d in dofs]
    else:
        body = [f"{nset}, {int(d)}, {int(d)}, {number(v)}" for d, v in zip(dofs, values)]
    return "\n".join([head, *body]) + "\n"


def abaqus_equations(rows) -> str:
    """``*EQUATION``: per row of ``(node, dof, coefficient)`` terms (the first is the
    dependent dof), the number of terms, then the terms, four a line (ABAQUS's limit)."""
    lines = ["*EQUATION"]
    for terms in rows:
        lines.append(str(len(terms)))
        for i in range(0, len(terms), 4):
            lines.append(", ".join(f"{int(n)}, {int(d)}, {number(c)}" for n, d, c in terms[i:i + 4]))
    return "\n".join(lines) + "\n"


def abaqus_indentation_deck(*, comments: Sequence[str], node_ids, node_xyz, blocks, nsets,
                            material_card: str, material_name: str, spring_ids, spring_pairs,
                            skull_ids, skull_xyz, spring_stiffness, axis, amplitude_time,
                            amplitude_value, initial_increment: float, max_increment: float,
                            anchor_equations=None, step_ends=None, print_nsets: Sequence[str] = (),
                            visco_cetol: float | None = None,
                            min_increment: float | None = None, max_increments: int = 10000,
                            file_frequency: int = 1, solid_elset: str = "EBRAIN",
                            indentor_nset: str = "INDENTOR", skull_nset: str = "SKULL",
                            spring_elset: str = "SPRINGS") -> str:
    """A complete ABAQUS/CalculiX deck of the in situ indentation, every number already in
    the deck's units.

    * the brain mesh (``node_ids`` (n,), ``node_xyz`` (n, 3); ``blocks`` a list of
      ``(element_type, element_ids, connectivity)``), its node sets ``nsets`` (name -> ids),
      the material card and a ``*SOLID SECTION``;
    * the brain-skull interface: skull nodes ``skull_ids``/``skull_xyz`` (set
      ``skull_nset``) joined to brain nodes by ``SPRINGA`` elements ``spring_ids`` with
      ``spring_pairs`` (m, 2) (brain, skull) and one stiffness; the skull nodes are fixed,
      or, with ``anchor_equations`` (rows for :func:`abaqus_equations`), tied to their brain
      nodes by those linear constraints;
    * the indentor: the nodes of ``indentor_nset`` (which must be in ``nsets``) follow the
      indentor, ``u = axis * A(t)`` with ``A`` the ``*AMPLITUDE`` ``INDENT``
      (``amplitude_time``, ``amplitude_value`` in deck time and length): the three
      components are prescribed with magnitudes ``axis`` (a bonded flat punch);
    * ``*STEP, NLGEOM`` (``*STATIC`` with automatic increments) steps that end at
      ``step_ends`` (deck times; default one step over the amplitude's span): a step ends
      exactly at its time, so steps ending at the amplitude's turning points make the solver
      reach the deepest indentation, which automatic increments would step over.  The
      amplitude is in total time and the indentor's boundary is restated in every step.
      With ``visco_cetol`` (a material with a Prony series) the steps are ``*VISCO, CETOL=``
      instead: ABAQUS's ``*STATIC`` uses the instantaneous moduli only and ignores
      ``*VISCOELASTIC``; CalculiX runs ``*VISCO`` as a quasi-static step (it drops
      ``*VISCOELASTIC`` with a warning either way).
      Output: ``U`` and ``RF`` of every node to the ``.frd`` file every ``file_frequency``
      increments, the indentor's ``U`` and total ``RF`` and the ``U`` of the nodes of
      ``print_nsets`` (each in ``nsets``: e.g. the nodes of the elements holding the markers,
      what ``bsipipe compare`` interpolates) to the ``.dat`` file at every increment.
    """
    axis = np.asarray(axis, dtype=float)
    missing = [n for n in print_nsets if n not in nsets]
    if missing:
        raise ValueError(f"print_nsets {missing} are not in nsets")
    t_end = float(np.asarray(amplitude_time, dtype=float)[-1])
    ends = [t_end] if step_ends is None else [float(v) for v in step_ends]
    if abs(ends[-1] - t_end) > 1e-9 * max(1.0, t_end) or np.any(np.diff([0.0, *ends]) <= 0):
        raise ValueError("step_ends must increase and end at the amplitude's last time")
    parts = [f"** {c}" for c in comments]
    parts.append(abaqus_nodes(node_ids, node_xyz, nset="NBRAIN"))
    for etype, eids, conn in blocks:
        parts.append(abaqus_elements(etype, eids, conn, elset=solid_elset))
    for name, ids in nsets.items():
        parts.append(abaqus_nset(name, ids))
    parts.append(abaqus_nodes(skull_ids, skull_xyz, nset=skull_nset))
    parts.append(abaqus_springa(spring_ids, spring_pairs, spring_stiffness, spring_elset))
    parts.append(material_card)
    parts.append(f"*SOLID SECTION, ELSET={solid_elset}, MATERIAL={material_name}")
    parts.append(abaqus_amplitude("INDENT", amplitude_time, amplitude_value, time_kind="TOTAL TIME"))
    if anchor_equations is None:
        parts.append("** the skull nodes are fixed")
        parts.append(abaqus_boundary(skull_nset, (1, 2, 3)))
    else:
        parts.append("** each skull node follows its brain node along the skull: u_s = (I - n n^T) u_b")
        parts.append(abaqus_equations(anchor_equations))
    if visco_cetol is not None:
        parts.append("** *VISCO steps: ABAQUS includes the *VISCOELASTIC relaxation (under *STATIC it would use the "
                     "instantaneous moduli only); CalculiX has no *VISCOELASTIC: it warns, drops the card and "
                     "solves with the instantaneous moduli")
    start = 0.0
    for k, end in enumerate(ends, start=1):
        period = end - start
        dt0 = min(float(initial_increment), period)
        dt_max = min(float(max_increment), period)
        # CalculiX raises a smaller minimum to 1e-6 of the step time (with a warning)
        dt_min = min_increment if min_increment is not None else max(dt_max * 1e-4, period * 1e-5)
        procedure = "*STATIC" if visco_cetol is None else f"*VISCO, CETOL={number(visco_cetol)}"
        parts += [
            f"** step {k}: total time {number(start)} to {number(end)}",
            f"*STEP, NLGEOM, INC={int(max_increments)}",
            procedure,
            ", ".join(number(v) for v in (dt0, period, dt_min, dt_max)),
            f"** the indentor's nodes follow u = A(t) * ({', '.join(f'{a:.9g}' for a in axis)})",
            abaqus_boundary(indentor_nset, (1, 2, 3), axis, amplitude="INDENT"),
            f"*NODE FILE, FREQUENCY={int(file_frequency)}", "U, RF",
            f"*NODE PRINT, NSET={indentor_nset}", "U",
            f"*NODE PRINT, NSET={indentor_nset}, TOTALS=ONLY", "RF",
        ]
        for name in print_nsets:
            parts += [f"*NODE PRINT, NSET={name}", "U"]
        parts.append("*END STEP")
        start = end
    return "\n".join(p.rstrip("\n") for p in parts) + "\n"


def abaqus_node_sets(path) -> dict[str, np.ndarray]:
    """Node sets of an ABAQUS input file (``*INCLUDE`` followed): ``*NSET, NSET=name`` (plain
    lists or ``GENERATE`` triples ``first, last, step``; names of other sets expand to their
    nodes; with ``ELSET=name``, the nodes of that element set's elements) and ``*NODE,
    NSET=name``.  Names are upper case (ABAQUS is case-insensitive).

    Raises
    ------
    InputError
        A data line that is not a list of integers (naming the file and line).
    """
    from ..errors import InputError
    from .fe_results import _inp_lines, element_line_continues

    sets: dict[str, list[int]] = {}
    elsets: dict[str, list[int]] = {}
    elements: dict[int, list[int]] = {}     # element -> its nodes (every type)
    from_elsets: list[tuple] = []            # (node set, element set, file, line): filled at the end
    mode, name, generate = None, None, False
    elem: list[int] = []                     # the element being read (its line may continue)
    for f, no, raw in _inp_lines(path):
        line = raw.strip()
        if not line or line.startswith("**"):
            continue
        if line.startswith("*"):
            parts = [q.strip() for q in line[1:].split(",")]
            kw = parts[0].upper()
            params = {}
            for q in parts[1:]:
                k, _, v = q.partition("=")
                params[k.strip().upper()] = v.strip()
            mode, name, generate, elem = None, None, False, []
            if kw == "NSET" and params.get("NSET"):
                mode, name, generate = "nset", params["NSET"].upper(), "GENERATE" in params
                sets.setdefault(name, [])
                if params.get("ELSET"):
                    # the nodes of an element set's elements (no data lines); it had read as
                    # an empty set, "node set INTERFACE is not in the mesh (it has [INTERFACE])"
                    from_elsets.append((name, params["ELSET"].upper(), f, no))
                    mode = None
            elif kw == "NODE" and params.get("NSET"):
                mode, name = "node", params["NSET"].upper()
                sets.setdefault(name, [])
            elif kw == "ELEMENT":
                mode, name = "element", (params.get("ELSET") or "").upper() or None
                if name:
                    elsets.setdefault(name, [])
            elif kw == "ELSET" and params.get("ELSET"):
                mode, name, generate = "elset", params["ELSET"].upper(), "GENERATE" in params
                elsets.setdefault(name, [])
            continue
        if mode == "node":
            head = line.split(",")[0].strip()
            try:
                sets[name].append(int(head))
            except ValueError:
                raise InputError(f"a node line needs an integer id, got {head!r}", path=f, line=no) from None
        elif mode == "element":
            try:
                vals = [int(v) for v in line.split(",") if v.strip()]
            except ValueError:
                raise InputError(f"element data must be integers, got {line!r}", path=f, line=no) from None
            elem.extend(vals)
            if elem and not element_line_continues(line, vals):
                elements[elem[0]] = elem[1:]
                if name:
                    elsets[name].append(elem[0])
                elem = []
        elif mode in ("nset", "elset"):
            target = sets if mode == "nset" else elsets
            vals = [v.strip() for v in line.split(",") if v.strip()]
            if generate:
                try:
                    a, b, *step = [int(v) for v in vals]
                except ValueError:
                    raise InputError(f"*{mode.upper()}, GENERATE needs 'first, last[, step]'", path=f,
                                     line=no) from None
                target[name].extend(range(a, b + 1, step[0] if step else 1))
                continue
            for v in vals:
                if v.upper() in target:
                    target[name].extend(target[v.upper()])
                    continue
                try:
                    target[name].append(int(v))
                except ValueError:
                    raise InputError(f"*{mode.upper()} {name}: {v!r} is neither an id nor a set defined before",
                                     path=f, line=no) from None
    for nset, eset, f, no in from_elsets:
        if eset not in elsets:
            raise InputError(f"*NSET {nset}: element set {eset} is not defined", path=f, line=no)
        for e in elsets[eset]:
            sets[nset].extend(elements.get(e, []))
    return {k: np.unique(np.array(v, dtype=np.int64)) for k, v in sets.items()}


#: ``** bsipipe: key = value``: values export-fe states in its decks for later stages (``compare``).
HEADER_PREFIX = "bsipipe:"


def abaqus_header_line(key: str, value) -> str:
    """The comment text (without ``**``) that :func:`abaqus_header_values` reads back."""
    return f"{HEADER_PREFIX} {key} = {value}"


def abaqus_header_values(path) -> dict[str, str]:
    """``** bsipipe: key = value`` comment lines before the first keyword of an ABAQUS input
    file (what export-fe states for ``compare``: the FE clock, the coordinate system); an
    empty dict for any other deck.

    Raises
    ------
    InputError
        The file cannot be read.
    """
    from ..errors import InputError

    out: dict[str, str] = {}
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            for raw in f:
                line = raw.strip()
                if not line:
                    continue
                if not line.startswith("**"):
                    break
                text = line[2:].strip()
                if text.startswith(HEADER_PREFIX):
                    key, sep, value = text[len(HEADER_PREFIX):].partition("=")
                    if sep:
                        out[key.strip()] = value.strip()
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except OSError as e:
        raise InputError(f"cannot read the file: {e}", path=path) from None
    return out


__all__ += ["HEADER_PREFIX", "abaqus_header_line", "abaqus_header_values", "abaqus_amplitude", "abaqus_springa",
            "abaqus_boundary", "abaqus_equations", "abaqus_indentation_deck", "abaqus_node_sets"]
