r"""Solid meshes for the FE hand-off: the demonstration brain block and the brain-skull
interface springs on any mesh.

:func:`demo_block_mesh` builds a graded C3D8 brick of brain under the indentor, in the CT
(FE) frame.  In its local frame (origin at the contact point, the centre of the indentor's
flat end on the brain surface; :math:`\mathbf e_3 = -\mathbf a` with :math:`\mathbf a` the
unit direction of indentation) the block is
:math:`[-W, W]^2 \times [-H, 0]`.  The grid lines in :math:`x` and :math:`y` are uniform over
the indentor's footprint :math:`[-r, r]` (``n_footprint`` cells), then grow geometrically to
the craniotomy's half side :math:`c/2` (``n_ring`` cells) and on to :math:`W` (``n_outer``
cells); in depth they start at the footprint spacing and grow geometrically to :math:`H`.
The footprint square is mapped onto the disc of radius :math:`r` by the elliptical grid
mapping

.. math::

    E(u, v) = \big(u\sqrt{1 - v^2/2},\; v\sqrt{1 - u^2/2}\big),

and each square ring of "radius" :math:`s = \max(|x|, |y|)` between :math:`r` and
:math:`c/2` is blended from that rounded shape to the square,
:math:`\mathbf p' = (1 - w)\, s\,E(\mathbf p / s) + w\,\mathbf p`,
:math:`w = (s - r)/(c/2 - r)`, so the indentor's nodes (``INDENTOR``: top nodes with
:math:`s \le r`) cover exactly the disc of its flat end and the craniotomy opening (the top
faces with :math:`s \le c/2`) is exactly the square of side :math:`c`.  Every other boundary
face (the rest of the top, the four sides and the bottom) lies against the skull
(``INTERFACE``).

:func:`interface_springs` puts one axial spring (ABAQUS ``SPRINGA``) at every node of an
interface node set, from the node to a skull node ``length_mm`` outside along the node's
outward normal (the area-weighted mean normal of its interface faces); a node on an edge or a
corner of the interface (faces whose normals differ by more than ``CREASE_DEG``) gets one
spring per side, along that side's normal, since an axial spring resists its own direction
only.  The interface
faces are the mesh's boundary faces whose nodes are all in the set; their total area is the
interface area, and each face's area is shared equally among its nodes (the node's
tributary area).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq

__all__ = ["ElementBlock", "SolidMesh", "demo_block_mesh", "boundary_faces", "InterfaceSprings",
           "interface_springs", "graded_spacing", "local_frame"]

#: Corner faces of the supported element types, ABAQUS numbering (S1, S2, ...), 0-based.
_FACES = {
    "C3D8": ((0, 1, 2, 3), (4, 7, 6, 5), (0, 4, 5, 1), (1, 5, 6, 2), (2, 6, 7, 3), (3, 7, 4, 0)),
    "C3D4": ((0, 1, 2), (0, 3, 1), (1, 3, 2), (2, 3, 0)),
}


@dataclass
class ElementBlock:
    """Elements of one type: ``element_type`` as written (``C3D8``, ``C3D8R``, ``C3D4`` ...),
    ``base`` its corner-node family (``C3D8`` or ``C3D4``), ``element_ids`` (ne,) and
    ``connectivity`` (ne, k) node labels (the first 8 or 4 are the corners)."""

    element_type: str
    base: str
    element_ids: np.ndarray
    connectivity: np.ndarray


@dataclass
class SolidMesh:
    """Nodes (labels ``node_ids`` (n,), ``coords_mm`` (n, 3) in the CT frame), element blocks
    and named node sets (name -> labels)."""

    node_ids: np.ndarray
    coords_mm: np.ndarray
    blocks: list[ElementBlock]
    nsets: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = ""
    info: dict = field(default_factory=dict)

    @property
    def n_elements(self) -> int:
        return int(sum(len(b.element_ids) for b in self.blocks))

    def coords_of(self, labels) -> np.ndarray:
        """Coordinates (m, 3) of the nodes with ``labels``."""
        index = {int(n): i for i, n in enumerate(self.node_ids)}
        return self.coords_mm[[index[int(n)] for n in np.asarray(labels).ravel()]]


def local_frame(axis) -> np.ndarray:
    """Rows ``e1, e2, e3`` of a right-handed frame with ``e3 = -axis / |axis|`` (the brain
    surface's outward normal when ``axis`` is the direction of indentation)."""
    a = np.asarray(axis, dtype=float)
    e3 = -a / np.linalg.norm(a)
    helper = np.array([1.0, 0.0, 0.0]) if abs(e3[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - (helper @ e3) * e3
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(e3, e1)
    return np.stack([e1, e2, e3])


def graded_spacing(start: float, stop: float, n: int, first: float) -> np.ndarray:
    """``n + 1`` coordinates from ``start`` to ``stop`` whose first cell is ``first`` long and
    each next cell ``q`` times the last (``q`` solved; uniform when ``first * n`` fits exactly).

    >>> graded_spacing(0.0, 7.0, 3, 1.0).round(6).tolist()
    [0.0, 1.0, 3.0, 7.0]
    """
    length = float(stop - start)
    if n < 1 or length <= 0 or first <= 0:
        raise ValueError("graded_spacing needs n >= 1, stop > start and first > 0")
    if n == 1:
        return np.array([start, stop], dtype=float)

    def total(q: float) -> float:
        return first * n if abs(q - 1.0) < 1e-12 else first * (q ** n - 1.0) / (q - 1.0)

    if abs(total(1.0) - length) < 1e-12 * length:
        q = 1.0
    else:
        q = brentq(lambda q: total(q) - length, 1e-6, 1e3, xtol=1e-14, rtol=1e-14)
    cells = first * q ** np.arange(n)
    x = start + np.concatenate([[0.0], np.cumsum(cells)])
    x[-1] = stop
    return x


def _disc_map(p: np.ndarray) -> np.ndarray:
    """Elliptical grid mapping of the unit square onto the unit disc, (m, 2) -> (m, 2)."""
    u, v = p[:, 0], p[:, 1]
    return np.stack([u * np.sqrt(1.0 - v ** 2 / 2.0), v * np.sqrt(1.0 - u ** 2 / 2.0)], axis=1)


def demo_block_mesh(contact_point_mm, axis, *, indentor_radius_mm: float, craniotomy_mm: float = 20.0,
                    half_width_mm: float = 20.0, depth_mm: float = 20.0, n_footprint: int = 4,
                    n_ring: int = 3, n_outer: int = 3, n_depth: int = 8) -> SolidMesh:
    """A graded C3D8 brick of brain under the indentor (the module docstring gives the
    geometry), in the CT frame.

    Parameters
    ----------
    contact_point_mm : (3,)
        Centre of the indentor's flat end where it meets the brain surface (CT frame).
    axis : (3,)
        Direction of indentation (into the brain), CT frame; need not be unit.
    indentor_radius_mm, craniotomy_mm, half_width_mm, depth_mm : float
        ``r``, ``c``, ``W``, ``H`` above; ``2 r < c < 2 W``.
    n_footprint, n_ring, n_outer, n_depth : int
        Cells across the footprint, from the footprint to the craniotomy edge, from there
        to the block's side, and through the depth.

    Returns
    -------
    SolidMesh
        Node sets ``NALL``, ``INDENTOR`` (the footprint's top nodes), ``INTERFACE`` (nodes of
        the faces against the skull), ``OPENING`` (top nodes inside the craniotomy, not on
        its edge); ``info`` records the parameters and counts.
    """
    r, c2, W, H = float(indentor_radius_mm), float(craniotomy_mm) / 2.0, float(half_width_mm), float(depth_mm)
    if not (0.0 < r < c2 < W):
        raise ValueError(f"the demo mesh needs 0 < indentor radius ({r:g}) < craniotomy/2 ({c2:g}) "
                         f"< half width ({W:g}) mm")
    if min(n_footprint, n_ring, n_outer, n_depth) < 1 or n_footprint % 2:
        raise ValueError("the demo mesh needs at least one cell per region and an even n_footprint")
    h = 2.0 * r / n_footprint
    if H <= h:
        raise ValueError(f"depth_mm ({H:g}) must exceed the footprint cell ({h:g} mm)")
    ring = graded_spacing(r, c2, n_ring, h)
    outer = graded_spacing(c2, W, n_outer, ring[-1] - ring[-2])
    half = np.concatenate([np.linspace(0.0, r, n_footprint // 2 + 1), ring[1:], outer[1:]])
    xs = np.concatenate([-half[:0:-1], half])
    zs = -graded_spacing(0.0, H, n_depth, h)[::-1]          # bottom (-H) to top (0)
    nx, nz = len(xs), len(zs)

    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    p = np.stack([gx.ravel(), gy.ravel()], axis=1)          # (nx*nx, 2), index i*nx + j
    s = np.max(np.abs(p), axis=1)
    mapped = p.copy()
    inner = s <= r * (1 + 1e-12)
    mapped[inner] = r * _disc_map(p[inner] / r)
    blend = (~inner) & (s < c2 * (1 - 1e-12))
    if np.any(blend):
        sb = s[blend][:, None]
        w = (sb - r) / (c2 - r)
        mapped[blend] = (1.0 - w) * sb * _disc_map(p[blend] / sb) + w * p[blend]

    # nodes: index (i, j, k) -> i*nx*nz + j*nz + k, label index + 1
    local = np.empty((nx, nx, nz, 3))
    local[..., 0] = mapped[:, 0].reshape(nx, nx)[:, :, None]
    local[..., 1] = mapped[:, 1].reshape(nx, nx)[:, :, None]
    local[..., 2] = zs[None, None, :]
    E = local_frame(axis)
    coords = np.asarray(contact_point_mm, float) + local.reshape(-1, 3) @ E
    labels = np.arange(1, nx * nx * nz + 1)

    def nid(i, j, k):
        return (i * nx + j) * nz + k + 1

    I, J, K = np.meshgrid(np.arange(nx - 1), np.arange(nx - 1), np.arange(nz - 1), indexing="ij")
    I, J, K = I.ravel(), J.ravel(), K.ravel()
    conn = np.stack([nid(I, J, K), nid(I + 1, J, K), nid(I + 1, J + 1, K), nid(I, J + 1, K),
                     nid(I, J, K + 1), nid(I + 1, J, K + 1), nid(I + 1, J + 1, K + 1), nid(I, J + 1, K + 1)],
                    axis=1)
    block = ElementBlock("C3D8", "C3D8", np.arange(1, len(conn) + 1), conn)

    top = nz - 1
    ti, tj = np.meshgrid(np.arange(nx), np.arange(nx), indexing="ij")
    s_grid = np.maximum(np.abs(xs[ti]), np.abs(xs[tj]))
    indentor = np.sort(nid(ti, tj, top)[s_grid <= r * (1 + 1e-12)])
    opening = np.sort(nid(ti, tj, top)[s_grid < c2 * (1 - 1e-12)])

    mesh = SolidMesh(labels, coords, [block], {"NALL": labels}, source="generated")
    faces, _ = boundary_faces(mesh)
    # a top face lies in the opening when its grid centre does
    on_top = np.all(np.isclose(local.reshape(-1, 3)[faces - 1][:, :, 2], 0.0), axis=1)
    grid_centre = np.array([_grid_s(xs, nx, nz, f) for f in faces])
    in_opening = on_top & (grid_centre < c2)
    iface_nodes = np.unique(faces[~in_opening])
    mesh.nsets.update({"INDENTOR": indentor, "INTERFACE": iface_nodes, "OPENING": opening})
    mesh.info = {
        "kind": "demonstration brick (bsipipe.fe.mesh.demo_block_mesh)",
        "element_type": "C3D8", "n_nodes": int(len(labels)), "n_elements": int(len(conn)),
        "half_width_mm": W, "depth_mm": H, "craniotomy_mm": 2 * c2, "indentor_radius_mm": r,
        "footprint_cell_mm": h, "n_footprint": n_footprint, "n_ring": n_ring, "n_outer": n_outer,
        "n_depth": n_depth, "local_frame_rows_e1_e2_e3": E.tolist(),
        "contact_point_mm": np.asarray(contact_point_mm, float).tolist(),
        "n_indentor_nodes": int(len(indentor)), "n_interface_nodes": int(len(iface_nodes)),
        "n_opening_faces": int(in_opening.sum()),
    }
    return mesh


def _grid_s(xs: np.ndarray, nx: int, nz: int, face_labels: np.ndarray) -> float:
    """Square "radius" max(|x|, |y|) of a face's centre in grid (unmapped) coordinates."""
    idx = face_labels - 1
    i, j = idx // (nx * nz), (idx // nz) % nx
    return float(max(abs(xs[i].mean()), abs(xs[j].mean())))


def boundary_faces(mesh: SolidMesh) -> tuple[np.ndarray, np.ndarray]:
    """The faces that belong to one element only, as corner-node labels, each ordered so its
    normal (right-hand rule) points out of the element.

    Returns ``(faces (m, 4) or (m, 3), element_ids (m,))``; a mesh mixing hexahedra and
    tetrahedra is not supported here.
    """
    bases = {b.base for b in mesh.blocks}
    if len(bases) != 1:
        raise ValueError(f"interface faces need one element family, the mesh has {sorted(bases)}")
    base = bases.pop()
    if base not in _FACES:
        raise ValueError(f"interface faces are implemented for C3D8 and C3D4 meshes, not {base}")
    nodes_per = 8 if base == "C3D8" else 4
    faces, owners, cents = [], [], []
    xyz = {int(n): c for n, c in zip(mesh.node_ids, mesh.coords_mm)}
    for b in mesh.blocks:
        conn = np.asarray(b.connectivity)[:, :nodes_per]
        for e, row in zip(b.element_ids, conn):
            for f in _FACES[base]:
                faces.append(row[list(f)])
                owners.append(int(e))
                cents.append(row)
    faces_arr = np.array(faces, dtype=np.int64)
    keys = np.sort(faces_arr, axis=1)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    once = counts[inv.ravel()] == 1
    out = faces_arr[once]
    owners_arr = np.array(owners)[once]
    # orient outward: normal . (face centre - element centre) > 0
    elem_rows = [cents[i] for i in np.flatnonzero(once)]
    for k, (f, row) in enumerate(zip(out, elem_rows)):
        P = np.array([xyz[int(n)] for n in f])
        n = _polygon_normal(P)
        ce = np.mean([xyz[int(v)] for v in row], axis=0)
        if n @ (P.mean(axis=0) - ce) < 0:
            out[k] = f[::-1]
    return out, owners_arr


def _polygon_normal(P: np.ndarray) -> np.ndarray:
    """Area vector (|n| = area) of a planar or slightly warped polygon (m, 3), Newell's method
    (for a quadrilateral: half the cross product of its diagonals)."""
    return 0.5 * np.sum(np.cross(P, np.roll(P, -1, axis=0)), axis=0)


@dataclass
class InterfaceSprings:
    """Axial springs from brain nodes to fixed skull nodes (a node on an edge or corner of the
    interface has one per side).

    ``brain_nodes`` (n,) labels (repeated at edges and corners), ``normals`` (n, 3) unit outward normals,
    ``skull_xyz_mm`` (n, 3) = brain node + ``length_mm`` x normal, ``tributary_area_mm2``
    (n,), ``area_mm2`` the interface area (sum of the faces), ``n_faces``.
    """

    brain_nodes: np.ndarray
    normals: np.ndarray
    skull_xyz_mm: np.ndarray
    tributary_area_mm2: np.ndarray
    area_mm2: float
    length_mm: float
    n_faces: int

    @property
    def n_springs(self) -> int:
        return int(len(self.brain_nodes))


#: Faces of an interface node whose normals differ by more than this (degrees) are on two
#: sides of an edge of the surface: the node gets a spring along each side's normal.
CREASE_DEG = 30.0


def interface_springs(mesh: SolidMesh, nset: str, length_mm: float) -> InterfaceSprings:
    """One spring per node of ``mesh.nsets[nset]``, or one per side at a node on an edge or a
    corner of the surface (faces whose normals differ by over :data:`CREASE_DEG`), each along
    its side's mean normal with its side's share of the tributary area (see the module
    docstring).

    Raises
    ------
    KeyError
        ``nset`` is not a node set of the mesh.
    ValueError
        No boundary face has all its nodes in the set, or a node of the set is on none.
    """
    labels = np.asarray(mesh.nsets[nset], dtype=np.int64)
    faces, _ = boundary_faces(mesh)
    inside = np.isin(faces, labels).all(axis=1)
    faces = faces[inside]
    if not len(faces):
        raise ValueError(f"no boundary face has all its nodes in node set {nset}")
    xyz = {int(n): c for n, c in zip(mesh.node_ids, mesh.coords_mm)}
    # each node's faces, grouped where their normals agree within CREASE_DEG: one spring per
    # group.  One spring along the mean normal at an edge or corner of the surface left the
    # node free in the plane across it, which cuts through the walls either side (an axial
    # spring resists only its own direction): on the demonstration brick 60 of 337 nodes went
    # up to 2.3 mm through the skull and the brain moved as a plug, markers 2.8 x the measured
    groups: dict[int, list[list]] = {int(n): [] for n in np.unique(faces)}   # node -> [[sum of a n, area]]
    cos_lim = float(np.cos(np.radians(CREASE_DEG)))
    total = 0.0
    for f in faces:
        a_vec = _polygon_normal(np.array([xyz[int(n)] for n in f]))
        a = float(np.linalg.norm(a_vec))
        total += a
        unit = a_vec / a if a > 0 else a_vec
        for n in f:
            g = groups[int(n)]
            for grp in g:
                if float(unit @ (grp[0] / np.linalg.norm(grp[0]))) >= cos_lim:
                    grp[0] = grp[0] + a_vec / len(f)
                    grp[1] += a / len(f)
                    break
            else:
                g.append([a_vec / len(f), a / len(f)])
    missing = np.setdiff1d(labels, list(groups))
    if len(missing):
        raise ValueError(f"{len(missing)} node(s) of {nset} (e.g. {int(missing[0])}) are on no interface face")
    nodes = np.array([n for n in sorted(groups) for _ in groups[n]], dtype=np.int64)
    normals = np.array([g[0] / np.linalg.norm(g[0]) for n in sorted(groups) for g in groups[n]])
    areas = np.array([g[1] for n in sorted(groups) for g in groups[n]])
    brain = np.array([xyz[int(n)] for n in nodes])
    return InterfaceSprings(nodes, normals, brain + float(length_mm) * normals,
                            areas, float(total), float(length_mm), int(len(faces)))
