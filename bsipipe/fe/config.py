"""The strict config of ``bsipipe export-fe`` (the FE hand-off package).

Paths are relative to the config file's folder.  Every key except the four inputs has a
default taken from the sheep-brain study (``data/real/README.md``: indentation at 12 mm/min
to 4.8 mm after contact, interface stiffness 11.45 N/mm per mm^2, 5240 springs 0.3 mm
long); ``configs/export_fe_example.yaml`` lists every key with its meaning.  An unknown
key, a wrong type or a missing required key is an error (exit 2) naming the key.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, PositiveFloat, PositiveInt, field_validator, model_validator

from ..config import StrictModel

Vector3 = tuple[float, float, float]

UnitName = Literal["mm-kg-s-kPa", "mm-N-s-MPa", "mm-kg-ms-GPa", "mm-g-ms-MPa", "m-kg-s-Pa"]


def _nonzero(v: Vector3 | None, what: str) -> Vector3 | None:
    if v is not None and not float(np.linalg.norm(v)) > 0.0:
        raise ValueError(f"{what} must be a non-zero vector")
    return v


class InputsConfig(StrictModel):
    """The files the hand-off is built from."""

    fit: str = Field(description="fit.json of `bsipipe fit-ogden` (model, params, prony)")
    registration: str = Field(description="registration.json of `bsipipe register` (R, t_mm, scale)")
    markers_ct: str = Field(description="markers_ct.csv of `bsipipe register` (markers in the CT frame)")
    log: str = Field(description="the indentation machine log (Micro Tester / Instron export)")
    markers3d: str | None = Field(None, description="markers3d.csv (X-ray frame); when given, the indentor's "
                                                     "markers are taken from it and mapped by the registration")


class PoseConfig(StrictModel):
    """The indentor's pose in the X-ray frame, for when it carries no tracked marker."""

    tip_mm: Vector3 = Field(description="centre of the flat end before the motion (log extension 0), X-ray frame")
    axis: Vector3 = Field(description="direction of indentation (into the brain), X-ray frame")

    @field_validator("axis")
    @classmethod
    def _axis(cls, v):
        return _nonzero(v, "axis")


class IndentorConfig(StrictModel):
    diameter_mm: PositiveFloat = Field(5.0, description="diameter of the indentor's flat end")
    markers: list[str] = Field(default_factory=list, description="names of the X-ray points fixed to the indentor "
                                                                 "(markers3d.csv / markers_ct.csv)")
    tip_offset_mm: float = Field(0.0, description="from the markers' centroid to the flat end, along the direction "
                                                  "of indentation (0: the point is the tip)")
    axis_xray: Vector3 | None = Field(None, description="direction of indentation in the X-ray frame; "
                                                        "default: fitted to the X-ray motion")
    pose_xray: PoseConfig | None = Field(None, description="the pose, when no marker is tracked on the indentor")

    @field_validator("axis_xray")
    @classmethod
    def _axis(cls, v):
        return _nonzero(v, "axis_xray")

    @model_validator(mode="after")
    def _source(self):
        if not self.markers and self.pose_xray is None:
            raise ValueError("give the indentor's X-ray markers (markers) or its pose (pose_xray)")
        if len(set(self.markers)) != len(self.markers):
            raise ValueError("a marker is named twice in markers")
        return self


class LogConfig(StrictModel):
    clock_offset_s: float | None = Field(None, description="X-ray time = log time + clock_offset_s; "
                                                           "default: fitted to the X-ray motion")
    contact_mm: float | None = Field(None, description="contact displacement (log frame, from its first sample); "
                                                       "default: detected (hinge fit)")


class InterfaceConfig(StrictModel):
    """Brain-skull interface springs: stiffness per spring = k x area / n (``lumping: uniform``,
    the published model's rule) or k x the node's tributary area (``tributary``)."""

    stiffness_n_per_mm_per_mm2: PositiveFloat = Field(11.45, description="interface stiffness per unit area")
    area_mm2: PositiveFloat | None = Field(None, description="the study's interface area; default the deck "
                                                             "mesh's interface area")
    n_springs: PositiveInt = Field(5240, description="the study's number of springs")
    spring_length_mm: PositiveFloat = Field(0.3, description="skull node this far outside the brain node")
    lumping: Literal["uniform", "tributary"] = Field(
        "uniform", description="uniform: every spring k x area / n (the published model's rule, exact on a mesh "
                               "of equal interface cells); tributary: each spring k x its node's tributary area "
                               "(a distributed stiffness lumped consistently on any mesh; the decks then carry one "
                               "stiffness per spring)")
    anchors: Literal["sliding", "fixed"] = Field(
        "sliding", description="sliding: a spring's skull end follows its brain node along the skull "
                               "(frictionless interface, the spring stays normal); fixed: skull nodes fixed")


class DemoMeshConfig(StrictModel):
    """The demonstration brick written when no mesh is given (bsipipe.fe.mesh.demo_block_mesh)."""

    half_width_mm: PositiveFloat = 20.0
    depth_mm: PositiveFloat = 20.0
    craniotomy_mm: PositiveFloat = Field(20.0, description="side of the square opening in the skull")
    n_footprint: PositiveInt = Field(2, description="cells across the indentor (even)")
    n_ring: PositiveInt = Field(2, description="cells from the indentor to the craniotomy edge")
    n_outer: PositiveInt = Field(2, description="cells from the craniotomy edge to the block's side")
    n_depth: PositiveInt = Field(4, description="cells through the depth")

    @field_validator("n_footprint")
    @classmethod
    def _even(cls, v):
        if v % 2:
            raise ValueError("n_footprint must be even (a node on the indentor's axis)")
        return v


class MeshSetsConfig(StrictModel):
    """Node sets of a mesh given in ``mesh`` (the demonstration brick has its own)."""

    interface: str = Field("INTERFACE", description="node set of the brain surface against the skull")
    indentor: str = Field("INDENTOR", description="node set under the indentor's flat end")


class DeckConfig(StrictModel):
    units: UnitName = Field("mm-kg-s-kPa", description="unit system of the decks (mN forces keep brain "
                                                       "residuals above CalculiX's floor)")
    amplitude_source: Literal["log", "xray"] = Field("log", description="which trajectory drives the decks")
    amplitude_tolerance_mm: PositiveFloat = Field(0.001, description="the amplitude keeps every knot needed to "
                                                                      "stay within this of the trajectory")
    max_increment_mm: PositiveFloat = Field(0.5, description="indentor travel per solver increment at most")
    bulk_modulus_pa: PositiveFloat | None = Field(None, description="default 1000 x G0 (nearly incompressible)")
    density_kg_m3: PositiveFloat = 1040.0
    element_type: str | None = Field(None, description="solid element type written (default: as in the mesh; "
                                                        "C3D8 for the demonstration mesh)")


class ChecksConfig(StrictModel):
    speed_mm_per_min: PositiveFloat | None = Field(12.0, description="expected indentor speed (null: no check)")
    speed_rel_tol: PositiveFloat = 0.05
    depth_mm: PositiveFloat | None = Field(4.8, description="expected depth after contact (null: no check)")
    depth_tol_mm: PositiveFloat = Field(0.1, description="allowed depth difference, plus 2 sd of the contact "
                                                         "travel the log's force shows (0 when log.contact_mm is given)")
    max_trajectory_difference_mm: PositiveFloat | None = Field(
        0.5, description="largest log-vs-X-ray difference of the indentor's position during contact")
    on_fail: Literal["error", "warn"] = Field("error", description="error: exit 1; warn: log and record")


class ExportConfig(StrictModel):
    """``bsipipe export-fe CONFIG -o DIR``."""

    inputs: InputsConfig
    indentor: IndentorConfig
    log: LogConfig = LogConfig()
    interface: InterfaceConfig = InterfaceConfig()
    mesh: str | None = Field(None, description="ABAQUS .inp mesh in the CT frame (mm) with the node sets of "
                                               "mesh_sets; null: the demonstration brick")
    mesh_sets: MeshSetsConfig = MeshSetsConfig()
    demo_mesh: DemoMeshConfig = DemoMeshConfig()
    deck: DeckConfig = DeckConfig()
    checks: ChecksConfig = ChecksConfig()
