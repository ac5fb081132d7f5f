"""The strict config of ``bsipipe synth`` (the C-arm digital twin).

Every key has a default taken from the sheep study, so an empty file is a valid config;
an unknown key, a wrong type or an out-of-range value is an error (exit 2) naming the key.
See ``configs/synth_default.yaml`` for every key with its meaning.
"""

from __future__ import annotations

import re
from typing import Literal

from pydantic import Field, PositiveFloat, PositiveInt, field_validator, model_validator

from ..config import StrictModel

#: Default detected quanta per pixel at the automatic-brightness level: a steel bead 4 px
#: across then has the signal-to-noise ratio of the beads in a real C-arm frame (see
#: :class:`NoiseConfig`; measured in ``tests/test_synth_noise.py``).
DEFAULT_QUANTA_PER_PX = 370.0
#: Default read (video) noise, 8-bit grey levels.
DEFAULT_READ_NOISE_DN = 0.5


class ImageConfig(StrictModel):
    size_px: int = Field(1024, ge=128, le=4096, description="square frames, size_px x size_px")
    bit_depth: Literal[8, 16] = 8
    supersample: int = Field(4, ge=1, le=8, description="sub-pixel rays per pixel and axis for beads and rods")


class GeometryConfig(StrictModel):
    sid_mm: PositiveFloat = Field(1000.0, description="source-to-image distance")
    sod_mm: PositiveFloat = Field(640.0, description="source-to-object (isocentre) distance")
    intensifier_diameter_mm: PositiveFloat = Field(305.0, description="12-inch image intensifier, imaged on size_px")
    fov_fraction: float = Field(0.98, gt=0.3, le=1.5, description="radius of the circular field / (size_px / 2)")
    angle_between_deg: float = Field(90.0, ge=30.0, le=150.0, description="angle between the two beams")
    jitter: bool = Field(True, description="small seeded differences between the C-arms (SID, tilt, roll, "
                                           "principal point, pixel aspect) as in a real set-up")

    @model_validator(mode="after")
    def _sod_inside(self):
        if self.sod_mm >= self.sid_mm:
            raise ValueError("sod_mm must be smaller than sid_mm")
        return self


class DistortionConfig(StrictModel):
    pincushion_edge_px: float = Field(15.0, ge=0, le=200, description="radial displacement (k1) at the field edge")
    tangential_edge_px: float = Field(1.5, ge=0, le=50, description="tangential displacement (p1, p2) at the edge")
    s_distortion_deg: float = Field(0.0, ge=-10, le=10, description="S-distortion: rotation at the field edge")
    local_rms_px: float = Field(0.0, ge=0, le=10, description="RMS of the smooth local displacement field")
    local_modes: int = Field(8, ge=1, le=30, description="Fourier modes of the local field")
    local_max_cycles: int = Field(3, ge=1, le=8, description="shortest local wavelength = size_px / local_max_cycles")


class NoiseConfig(StrictModel):
    """Quantum and read noise of the detector, calibrated to real X-ray frames.

    The default ``quanta_per_px`` gives a steel bead 4 px across the signal-to-noise ratio
    (Gaussian-fit amplitude over the local background / pixel noise) of the ~4 px steel beads
    in the real C-arm frame ``tests/data/real/xray_frame_deepxromm/sample_frame.jpg``
    (8-bit, background ~128 grey levels), measured the same way on both
    (``tests/test_synth_noise.py``):

    - pixel noise: 1.4826 MAD of the image minus its Gaussian blur (sigma 3 px) over the
      field of view, clipped pixels left out: real frame 2.70 grey levels at a background
      of ~126 (about the same in 32 px tiles from 110 to 140 grey levels, as a gamma-1/2
      video chain gives); the twin 2.81 at 370 quanta (1.8 at the old default of 1000);
    - bead amplitude (:func:`bsipipe.imaging.detect.refine_at`, 4 px): real median 33.2 grey
      levels over its 24 seeded beads, twin 33.5 (0.77 mm beads at the isocentre, 4 px): the
      steel attenuation (1.5 /mm) needs no change;
    - SNR: real 12.3; twin 11.9 at 370 quanta (about 19 at 1000).

    A second real X-ray image, the dot grid ``xray_dot_grid_discorpy/dot_pattern_05.jpg``
    (another detector, not a C-arm), has 2.2-2.4 grey levels of noise between its dots: the
    same order.  What the twin does not copy: the real noise is spatially correlated (lag-1
    autocorrelation 0.2-0.3 after JPEG and the intensifier's blur) where the twin's is
    white, which makes the twin slightly harder for sub-pixel centres at the same pixel noise.
    """

    enabled: bool = True
    quanta_per_px: PositiveFloat = Field(DEFAULT_QUANTA_PER_PX, description="detected quanta per pixel at the median "
                                         "brightness (default: real C-arm bead SNR, see NoiseConfig)")
    read_noise_dn: float = Field(DEFAULT_READ_NOISE_DN, ge=0, description="read noise in 8-bit grey levels "
                                 "(x257 for 16-bit)")


class XrayConfig(StrictModel):
    mu_steel_per_mm: PositiveFloat = Field(1.5, description="steel beads and indentor at C-arm energies")
    mu_soft_tissue_per_mm: float = Field(0.02, ge=0)
    mu_bone_per_mm: float = Field(0.04, ge=0)
    mu_acrylic_per_mm: float = Field(0.025, ge=0, description="calibration plate")
    blur_sigma_px: float = Field(0.7, ge=0, le=10, description="focal-spot + intensifier blur, Gaussian sigma")
    heel_gradient: float = Field(0.08, ge=0, le=0.5, description="relative intensity change per field radius")
    vignetting: float = Field(0.25, ge=0, le=0.9, description="brightness loss at the field edge")
    veiling_glare: float = Field(0.1, ge=0, le=0.9)
    fov_circle: bool = Field(True, description="black outside the intensifier's circular field")
    tissue: bool = Field(True, description="skull and soft-tissue background in the sequence")
    level: float = Field(0.4, gt=0.05, lt=0.95, description="automatic brightness: central median at this fraction of full scale")
    gamma: float = Field(0.5, gt=0.1, le=1.0, description="video chain's gamma (1 = linear in intensity)")


Pattern = Literal["circles", "asymmetric-circles", "chessboard", "charuco"]

#: OpenCV's predefined ArUco dictionaries (``cv2.aruco.DICT_*``) and how many markers each
#: holds (checked against OpenCV in ``tests/test_synth_config.py``); listed here so the
#: config is checked without importing OpenCV.
ARUCO_DICTIONARIES = {
    **{f"DICT_{b}X{b}_{n}": n for b in (4, 5, 6, 7) for n in (50, 100, 250, 1000)},
    "DICT_ARUCO_ORIGINAL": 1024,
    "DICT_APRILTAG_16h5": 30, "DICT_APRILTAG_16H5": 30, "DICT_APRILTAG_25h9": 35, "DICT_APRILTAG_25H9": 35,
    "DICT_APRILTAG_36h10": 2320, "DICT_APRILTAG_36H10": 2320, "DICT_APRILTAG_36h11": 587,
    "DICT_APRILTAG_36H11": 587, "DICT_ARUCO_MIP_36h12": 250, "DICT_ARUCO_MIP_36H12": 250,
}


class CalibrationConfig(StrictModel):
    views: int = Field(12, ge=0, le=200, description="views of the plate per C-arm")
    stereo_views: int = Field(6, ge=0, le=200, description="views seen by both C-arms at once")
    pattern: Pattern = "asymmetric-circles"
    grid: tuple[PositiveInt, PositiveInt] = Field(
        (8, 17), description="OpenCV pattern size: circles per row x rows; chessboard inner corners; ChArUco squares")
    spacing_mm: PositiveFloat = Field(7.0, description="OpenCV spacing: circle grid spacing or square size")
    bead_diameter_mm: PositiveFloat = 1.0
    plate_thickness_mm: PositiveFloat = 3.0
    max_tilt_deg: float = Field(35.0, ge=0, le=70)
    charuco_marker_fraction: float = Field(0.7, gt=0.2, lt=1.0, description="ArUco side / square side")
    charuco_dictionary: str = "DICT_4X4_250"
    optical_noise_dn: float = Field(2.0, ge=0, description="chessboard/ChArUco: Gaussian noise, 8-bit levels")

    @model_validator(mode="after")
    def _grid_ok(self):
        cols, rows = self.grid
        if cols < 2 or rows < 2:
            raise ValueError("grid needs at least 2 x 2")
        if self.pattern == "charuco" and (cols < 3 or rows < 3):
            raise ValueError("a ChArUco grid needs at least 3 x 3 squares")
        if self.pattern == "charuco":
            # a ChArUco board carries a marker in every other square
            need, have = cols * rows // 2, ARUCO_DICTIONARIES[self.charuco_dictionary]
            if need > have:
                raise ValueError(f"calibration.grid {cols} x {rows} needs {need} ChArUco markers but "
                                 f"charuco_dictionary {self.charuco_dictionary} holds {have}; use a smaller grid "
                                 "or a larger dictionary")
        return self

    @field_validator("charuco_dictionary")
    @classmethod
    def _known_dictionary(cls, v: str) -> str:
        if v not in ARUCO_DICTIONARIES:
            raise ValueError("unknown ArUco dictionary; use one of OpenCV's: "
                             + ", ".join(k for k in ARUCO_DICTIONARIES if not re.search(r"\d[H]\d", k)))
        return v


#: Bounds on the designed experiment (ramp, hold, unloading, 1 s after): the markers are
#: placed checking every design frame, and the log has a row per sample, so an unbounded
#: timeline (``hold_s: 1e6``, ``speed_mm_per_min: 0.0001``) would exhaust memory.
MAX_EXPERIMENT_S = 3600.0
MAX_DESIGN_FRAMES = 20000
MAX_LOG_SAMPLES = 1_000_000


class SequenceConfig(StrictModel):
    enabled: bool = True
    fps: PositiveFloat = 2.0
    n_frames: PositiveInt | None = Field(None, description="default: the whole indentation (and unloading)")
    speed_mm_per_min: PositiveFloat = 12.0
    depth_mm: PositiveFloat = Field(4.8, description="indentation depth after contact")
    gap_mm: float = Field(0.5, ge=0, description="indentor tip above the brain surface at the start")
    start_s: float = Field(1.0, ge=0, description="the indentor starts moving at this time")
    hold_s: float = Field(0.0, ge=0, description="hold at full depth")
    unload: bool = Field(True, description="retract at the same speed after the hold")
    indentor_diameter_mm: PositiveFloat = 5.0
    n_markers: int = Field(5, ge=0, le=12, description="implanted markers")
    marker_diameter_mm: PositiveFloat = 0.5
    n_references: int = Field(4, ge=0, le=8, description="reference markers at the craniotomy corners")
    reference_diameter_mm: PositiveFloat = 1.0
    indentor_markers: Literal[0, 2] = Field(
        2, description="steel beads on a radiolucent collar of the indentor, either side of its axis, so the "
                       "indentor is tracked in the X-ray frames like the markers (I1, I2)")
    indentor_marker_diameter_mm: PositiveFloat = 1.0
    indentor_marker_height_mm: PositiveFloat = Field(8.0, description="beads' centre above the flat end, along the axis")
    indentor_marker_offset_mm: PositiveFloat = Field(6.0, description="beads' centre from the indentor's axis")
    craniotomy_mm: PositiveFloat = Field(20.0, description="side of the square craniotomy")
    tissue_mu_pa: PositiveFloat = Field(720.0, description="log: one-term Ogden mu of the brain (2 mu / alpha^2 convention)")
    tissue_alpha: float = Field(-4.7, description="log: one-term Ogden alpha")
    log_rate_hz: PositiveFloat = 10.0
    force_noise_n: float = Field(0.001, ge=0)
    seed_click_noise_px: float = Field(0.5, ge=0, description="seeds.csv: a user's click error")

    def experiment_s(self) -> float:
        """Length of the designed experiment (s): start, ramp to full depth, hold, unloading, 1 s."""
        ramp_s = (self.gap_mm + self.depth_mm) / (self.speed_mm_per_min / 60.0)
        return self.start_s + ramp_s * (2 if self.unload else 1) + self.hold_s + 1.0

    @model_validator(mode="after")
    def _timeline_bounded(self):
        if not self.enabled:
            return self
        ramp_s = (self.gap_mm + self.depth_mm) / (self.speed_mm_per_min / 60.0)
        total = self.experiment_s()
        # name the term that makes the timeline long
        parts = {"sequence.hold_s": self.hold_s, "sequence.start_s": self.start_s,
                 "sequence.speed_mm_per_min (with gap_mm + depth_mm)": ramp_s}
        culprit = max(parts, key=parts.get)
        if total > MAX_EXPERIMENT_S:
            raise ValueError(f"the designed experiment lasts {total:.4g} s, more than the limit of "
                             f"{MAX_EXPERIMENT_S:g} s; mostly from {culprit}")
        frames = max(total * self.fps, self.n_frames or 0)
        if frames > MAX_DESIGN_FRAMES:
            key = "sequence.n_frames" if (self.n_frames or 0) > total * self.fps else "sequence.fps"
            raise ValueError(f"the designed experiment has {frames:.4g} frames per view, more than the limit of "
                             f"{MAX_DESIGN_FRAMES}; lower {key}")
        if total * self.log_rate_hz > MAX_LOG_SAMPLES:
            raise ValueError(f"the indentation log would have {total * self.log_rate_hz:.4g} rows, more than the "
                             f"limit of {MAX_LOG_SAMPLES}; lower sequence.log_rate_hz")
        return self


class EffectsConfig(StrictModel):
    occlusion: bool = Field(True, description="two implanted markers pass behind the indentor, one in each view")
    view_time_offset_s: float = Field(0.0, ge=-5, le=5, description="cam2's clock minus cam1's")
    view_clock_drift: float = Field(0.0, ge=-0.05, le=0.05, description="cam2's frame interval over cam1's, minus "
                                    "one: cam2's frame i is taken at i / fps * (1 + drift) + view_time_offset_s")
    moving_reference: bool = Field(False, description="reference R2 sits on the brain and moves with it")
    frame_jolt_px: int = Field(0, ge=0, le=20, description="in every sequence frame after the first, the anatomy "
                               "(everything but the intensifier's field) is shifted by a random whole number of px "
                               "up to this per axis and view (C-arm vibration, head movement); the truth shifts too")
    static_specks: int = Field(0, ge=0, le=200, description="static dark spots on each intensifier (dust, defects "
                               "of the input screen), bead-like (8-25 % darker, sigma 1-1.8 px), scattered over the "
                               "markers' region of each view: they stay put while the anatomy moves")


class CtConfig(StrictModel):
    noise_mm: float = Field(0.0, ge=0, le=2, description="CT localisation noise of each marker (per axis)")


class SynthConfig(StrictModel):
    """``bsipipe synth CONFIG``: the seeded twin of the two-C-arm sheep indentation study."""

    seed: int = 0
    image: ImageConfig = ImageConfig()
    geometry: GeometryConfig = GeometryConfig()
    distortion: DistortionConfig = DistortionConfig()
    noise: NoiseConfig = NoiseConfig()
    xray: XrayConfig = XrayConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    sequence: SequenceConfig = SequenceConfig()
    effects: EffectsConfig = EffectsConfig()
    ct: CtConfig = CtConfig()
