"""The digital twin of the two-C-arm sheep indentation study (``bsipipe synth``).

World frame (mm): origin at the isocentre, z up. C-arm ``cam1`` looks along +x, ``cam2``
along the direction turned by ``angle_between_deg`` about z (+y at 90 degrees); both
beams are horizontal up to the seeded jitter. The brain surface under the indentor is the
point ``S`` about 6 mm above the isocentre; the indentor moves along -z.

Output layout written by :mod:`bsipipe.commands.synth` (``DIR`` = ``-o``)::

    DIR/calibration/<view>/cal_000.png ...          each C-arm's own views of the plate
    DIR/calibration/stereo/<view>/stereo_000.png .. seen by both C-arms at once (same name)
    DIR/sequence/<view>/frame_0000.png ...          the indentation, <view> = cam1, cam2
    DIR/indentation_log.csv                         Micro Tester log, Bluehill 3 layout
    DIR/ct_markers.fcsv, DIR/ct_markers.mrk.json    CT marker coordinates (3D Slicer, LPS)
    DIR/calibration.yaml                            bsipipe calibrate's config for the plate views
    DIR/seeds.csv                                   view,marker,x_px,y_px in frame 0
    DIR/truth_markers.csv                           view,frame,time_s,marker,x_px,y_px,
                                                    x_mm,y_mm,z_mm,occluded,visible
    DIR/truth.json                                  every true value (below)
    DIR/synth.json                                  what was written, timing, provenance

``truth.json``: ``cameras`` (per view: K, OpenCV distortion, R, t, S-distortion, local
distortion, source position, field of view, detector settings), ``stereo_extrinsics``
(cam1 -> cam2, ``x2 = R x1 + T``, OpenCV's convention), ``calibration`` (pattern, object
points in the plate frame, per image the plate pose and the true raw-pixel projections),
``sequence`` (times per view, per marker the 3-D trajectory and per view the 2-D
projections and occlusion flags, the indentor, the displacement field), ``ct`` (the rigid
world -> CT transform and the markers' CT coordinates), ``log`` and ``effects``/``noise``.

Physical models (all documented where they are defined): exact chord lengths through steel
spheres and rods (:mod:`bsipipe.synth.xray`), a regularised Boussinesq displacement field
under the indentor (:func:`indentation_displacement`), a flat-punch force for the log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterator

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..imaging.camera import Camera, LocalDistortion, SDistortion, look_at
from .config import SynthConfig
from .xray import (Detector, Patch, RayField, RodShadow, apply_patch, cylinder_chord_mm, ellipsoid_chord_mm,
                   plate_chord_mm, sphere_patch)

VIEWS = ("cam1", "cam2")
_STREAMS = {"cameras": 1, "local": 2, "calibration": 3, "stereo": 4, "scene": 5, "frames": 6,
            "log": 7, "ct": 8, "seeds": 9, "calib_noise": 10, "ct_noise": 11, "jolt": 12, "specks": 13}


class TwinError(ValueError):
    """The config asks for a scene that cannot be built; ``key`` names the config key."""

    def __init__(self, message: str, key: str):
        super().__init__(message)
        self.key = key


def _shifted(img: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """``img`` moved by whole pixels (+x right, +y down), the edge rows and columns repeated
    into the uncovered border."""
    h, w = img.shape
    ys = np.clip(np.arange(h) - dy, 0, h - 1)
    xs = np.clip(np.arange(w) - dx, 0, w - 1)
    return img[ys[:, None], xs[None, :]]


def _speck_mask(size: tuple[int, int], specks: np.ndarray) -> np.ndarray:
    """Transmission (h, w) of static dark spots ``(x, y, depth, sigma)``: 1 - depth x a
    Gaussian of sd sigma around each (products where they overlap)."""
    w, h = size
    m = np.ones((h, w), np.float32)
    for x, y, depth, sg in specks:
        r = int(np.ceil(4 * sg))
        x0, x1 = max(int(x) - r, 0), min(int(x) + r + 1, w)
        y0, y1 = max(int(y) - r, 0), min(int(y) + r + 1, h)
        if x0 >= x1 or y0 >= y1:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        m[y0:y1, x0:x1] *= (1 - depth * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sg * sg))).astype(np.float32)
    return m


def stream(seed: int, name: str) -> np.random.Generator:
    """An independent generator per purpose, so switching one effect leaves the rest unchanged."""
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, _STREAMS[name]]))


# --- C-arms ------------------------------------------------------------------------------------

@dataclass
class CArm:
    """One C-arm: its camera model (source = camera centre), detector and ray field."""

    name: str
    camera: Camera
    detector: Detector
    beam_dir: np.ndarray
    sid_mm: float
    sod_mm: float
    pixel_pitch_mm: float
    _field: RayField | None = field(default=None, repr=False)

    @property
    def field(self) -> RayField:
        if self._field is None:
            self._field = RayField(self.camera)
        return self._field

    @property
    def fov_centre_px(self):
        return self.detector.fov_centre_px

    @property
    def fov_radius_px(self) -> float:
        return self.detector.fov_radius_px

    def in_fov(self, u: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        c = np.asarray(self.fov_centre_px)
        if self.detector.fov_circle:
            return np.hypot(u[:, 0] - c[0], u[:, 1] - c[1]) <= self.fov_radius_px - margin_px
        w, h = self.camera.image_size
        return ((u[:, 0] >= margin_px) & (u[:, 1] >= margin_px)
                & (u[:, 0] <= w - 1 - margin_px) & (u[:, 1] <= h - 1 - margin_px))

    def truth(self) -> dict:
        d = self.camera.to_dict()
        d.update({
            "source_mm": self.camera.centre_mm.tolist(),
            "beam_direction": self.beam_dir.tolist(),
            "sid_mm": self.sid_mm, "sod_mm": self.sod_mm, "pixel_pitch_mm": self.pixel_pitch_mm,
            "mm_per_px_at_isocentre": self.pixel_pitch_mm * self.sod_mm / self.sid_mm,
            "fov": {"centre_px": list(self.fov_centre_px), "radius_px": self.fov_radius_px,
                    "circle": self.detector.fov_circle},
            "detector": {"blur_sigma_px": self.detector.blur_sigma_px, "heel_gradient": self.detector.heel_gradient,
                         "heel_direction": list(self.detector.heel_direction), "vignetting": self.detector.vignetting,
                         "veiling_glare": self.detector.veiling_glare, "noise": self.detector.noise,
                         "quanta_per_px": self.detector.quanta_per_px, "read_noise_dn": self.detector.read_noise_dn,
                         "bit_depth": self.detector.bit_depth, "level": self.detector.level,
                         "gamma": self.detector.gamma},
        })
        return d


def build_carms(cfg: SynthConfig) -> dict[str, CArm]:
    """The two C-arms: pinhole geometry from SID, SOD and the intensifier size, pincushion
    and tangential distortion sized by their displacement at the field edge, optional S and
    local distortion, with seeded differences between the two when ``geometry.jitter``."""
    g, dcfg, size = cfg.geometry, cfg.distortion, cfg.image.size_px
    rng = stream(cfg.seed, "cameras")
    rng_local = stream(cfg.seed, "local")
    out = {}
    for i, name in enumerate(VIEWS):
        # every draw is made whether or not it is used, so switches leave the rest unchanged
        j = dict(sid=rng.uniform(-0.015, 0.015), sod=rng.uniform(-10, 10), elev=rng.uniform(-3, 3),
                 azim=rng.uniform(-2, 2), roll=rng.uniform(-2, 2), cx=rng.uniform(-8, 8), cy=rng.uniform(-8, 8),
                 aspect=rng.uniform(-0.003, 0.003), fovx=rng.uniform(-4, 4), fovy=rng.uniform(-4, 4),
                 iso=rng.uniform(-3, 3, 3), k1=rng.uniform(-0.15, 0.15), tdir=rng.uniform(0, 2 * np.pi),
                 tmag=rng.uniform(-0.2, 0.2), s=rng.uniform(-0.2, 0.2), heel=rng.uniform(-30, 30))
        if not g.jitter:
            j = {k: (np.zeros(3) if k == "iso" else 0.0) for k in j}
            j["tdir"] = np.deg2rad(30.0 + 90.0 * i)
        scale = size / 1024.0
        sid = g.sid_mm * (1 + j["sid"])
        sod = g.sod_mm + j["sod"]
        pitch = g.intensifier_diameter_mm / size
        f = sid / pitch
        az = np.deg2rad(i * g.angle_between_deg + j["azim"])
        el = np.deg2rad(j["elev"])
        beam = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        iso = np.asarray(j["iso"], float)
        src = iso - sod * beam
        R, _ = look_at(src, iso)
        roll = np.deg2rad(j["roll"])
        Rz = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
        R = Rz @ R
        t = -R @ src
        cx = (size - 1) / 2 + j["cx"] * scale
        cy = (size - 1) / 2 + j["cy"] * scale
        K = np.array([[f, 0, cx], [0, f * (1 + j["aspect"]), cy], [0, 0, 1]])
        fov_c = (cx + j["fovx"] * scale, cy + j["fovy"] * scale)
        fov_r = g.fov_fraction * size / 2
        rn = fov_r / f
        k1 = dcfg.pincushion_edge_px * (1 + j["k1"]) / (f * rn ** 3)
        p = dcfg.tangential_edge_px * (1 + j["tmag"]) / (3 * rn ** 2 * f)
        dist = np.array([k1, 0.0, p * np.cos(j["tdir"]), p * np.sin(j["tdir"]), 0.0])
        sdist = None
        if dcfg.s_distortion_deg != 0:
            sdist = SDistortion(float(np.deg2rad(dcfg.s_distortion_deg) * (1 + j["s"])), float(fov_r), fov_c)
        local_rng = np.random.default_rng(rng_local.integers(0, 2 ** 63))
        local = None
        if dcfg.local_rms_px > 0:
            local = LocalDistortion.random(local_rng, (size, size), dcfg.local_rms_px, dcfg.local_modes,
                                           dcfg.local_max_cycles, fov_c, fov_r)
        cam = Camera(K, dist, R, t, (size, size), sdist, local, name=name)
        hd = np.deg2rad(j["heel"])
        det = Detector((size, size), fov_c, fov_r, fov_circle=cfg.xray.fov_circle,
                       heel_gradient=cfg.xray.heel_gradient, heel_direction=(float(np.sin(hd)), float(np.cos(hd))),
                       vignetting=cfg.xray.vignetting, veiling_glare=cfg.xray.veiling_glare,
                       blur_sigma_px=cfg.xray.blur_sigma_px,
                       noise=cfg.noise.enabled, quanta_per_px=cfg.noise.quanta_per_px,
                       read_noise_dn=cfg.noise.read_noise_dn, bit_depth=cfg.image.bit_depth, level=cfg.xray.level,
                       gamma=cfg.xray.gamma)
        out[name] = CArm(name, cam, det, beam, float(sid), float(sod), float(pitch))
    return out


def stereo_extrinsics(a: Camera, b: Camera) -> dict:
    """Relative pose of camera b to camera a, OpenCV's stereo convention ``x_b = R x_a + T``."""
    R = b.R @ a.R.T
    T = b.t - R @ a.t
    return {"views": [a.name, b.name], "R": R.tolist(), "T_mm": T.tolist(),
            "angle_deg": float(np.rad2deg(np.linalg.norm(Rotation.from_matrix(R).as_rotvec()))),
            "baseline_mm": float(np.linalg.norm(T))}


# --- calibration patterns -------------------------------------------------------------------

@dataclass
class PlatePattern:
    """A calibration target in its own frame (z = 0 plane, mm), OpenCV's point order."""

    kind: str
    grid: tuple[int, int]
    spacing_mm: float
    object_points: np.ndarray
    corner_ids: np.ndarray | None = None
    board: object | None = None

    @property
    def xray(self) -> bool:
        return self.kind in ("circles", "asymmetric-circles")

    @property
    def centre(self) -> np.ndarray:
        lo, hi = self.object_points.min(axis=0), self.object_points.max(axis=0)
        return (lo + hi) / 2

    def extent(self) -> tuple[np.ndarray, np.ndarray]:
        """Board outline (lo, hi) in the plate frame, including its white border."""
        s = self.spacing_mm
        if self.kind == "chessboard":
            cols, rows = self.grid
            return np.array([-2 * s, -2 * s]), np.array([(cols + 1) * s, (rows + 1) * s])
        if self.kind == "charuco":
            sx, sy = self.grid
            return np.array([-s / 2, -s / 2]), np.array([sx * s + s / 2, sy * s + s / 2])
        lo, hi = self.object_points.min(axis=0)[:2], self.object_points.max(axis=0)[:2]
        return lo - 1.5 * s, hi + 1.5 * s


def make_pattern(cfg: SynthConfig) -> PlatePattern:
    c = cfg.calibration
    cols, rows = c.grid
    s = c.spacing_mm
    if c.pattern == "circles":
        pts = [(j * s, i * s, 0.0) for i in range(rows) for j in range(cols)]
    elif c.pattern == "asymmetric-circles":
        pts = [((2 * j + i % 2) * s, i * s, 0.0) for i in range(rows) for j in range(cols)]
    elif c.pattern == "chessboard":
        pts = [(j * s, i * s, 0.0) for i in range(rows) for j in range(cols)]
    else:
        dic = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, c.charuco_dictionary))
        board = cv2.aruco.CharucoBoard((cols, rows), s, s * c.charuco_marker_fraction, dic)
        pts = board.getChessboardCorners().astype(np.float64)
        return PlatePattern(c.pattern, (cols, rows), s, pts, np.arange(len(pts)), board)
    return PlatePattern(c.pattern, (cols, rows), s, np.asarray(pts, np.float64))


@dataclass
class PlatePose:
    """Plate frame -> world: ``X = R @ P + t``."""

    R: np.ndarray
    t: np.ndarray

    def world(self, P: np.ndarray) -> np.ndarray:
        return P @ self.R.T + self.t


def _plate_frame(normal_in: np.ndarray, right_hint: np.ndarray, psi: float) -> np.ndarray:
    e3 = normal_in / np.linalg.norm(normal_in)
    e1 = right_hint - np.dot(right_hint, e3) * e3
    e1 /= np.linalg.norm(e1)
    e1 = Rotation.from_rotvec(psi * e3).apply(e1)
    e2 = np.cross(e3, e1)
    return np.stack([e1, e2, e3], axis=1)


def _random_tilt(rng, axis: np.ndarray, max_deg: float, min_frac: float = 0.25) -> np.ndarray:
    """``axis`` turned by an angle in [min_frac, 1] * max_deg about a random perpendicular."""
    a = axis / np.linalg.norm(axis)
    v = rng.standard_normal(3)
    v -= np.dot(v, a) * a
    v /= np.linalg.norm(v)
    ang = np.deg2rad(max_deg) * rng.uniform(min_frac, 1.0)
    return Rotation.from_rotvec(ang * v).apply(a)


def _pose_ok(pattern: PlatePattern, pose: PlatePose, arms: list[CArm], bead_r_mm: float) -> bool:
    X = pose.world(pattern.object_points)
    for arm in arms:
        cam = arm.camera
        Xc = cam.to_camera(X)
        if np.any(Xc[:, 2] < 50):
            return False
        u = cam.project(X)
        rpx = cam.fx * bead_r_mm / Xc[:, 2].min()
        if pattern.xray:
            if not np.all(arm.in_fov(u, margin_px=rpx * 1.3 + 6)):
                return False
            d = np.sqrt(((u[:, None, :] - u[None, :, :]) ** 2).sum(-1)) + np.eye(len(u)) * 1e9
            if d.min() < 5 * rpx + 4:
                return False
        else:
            lo, hi = pattern.extent()
            corners = pose.world(np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0], [lo[0], hi[1], 0]]))
            w, h = cam.image_size
            uc = cam.project(corners)
            if np.any(uc < 2) or np.any(uc[:, 0] > w - 3) or np.any(uc[:, 1] > h - 3):
                return False
    return True


def sample_plate_pose(rng, pattern: PlatePattern, arms: list[CArm], max_tilt_deg: float, bead_r_mm: float,
                      shift_mm: float = 30.0, depth_mm: float = 40.0, tries: int = 3000) -> PlatePose:
    """A plate pose seen whole by every C-arm in ``arms`` (all beads inside each field of
    view, none overlapping; an optical board inside each image): the plate faces the mean
    beam direction, tilted by up to ``max_tilt_deg``, turned in its plane by up to 20 deg."""
    beam = np.mean([a.beam_dir for a in arms], axis=0)
    beam /= np.linalg.norm(beam)
    right = arms[0].camera.R[0]
    if pattern.xray:
        lo, hi = pattern.object_points.min(0)[:2], pattern.object_points.max(0)[:2]
    else:
        lo, hi = pattern.extent()
    for a in arms:  # even face-on at the farthest depth the pattern must fit
        half_diag_px = 0.5 * np.hypot(*(hi - lo)) * a.camera.fx / (a.sod_mm + depth_mm)
        room = a.fov_radius_px if (pattern.xray and a.detector.fov_circle) else 0.5 * np.hypot(*a.camera.image_size)
        if half_diag_px > room:
            raise TwinError(f"the pattern ({hi[0] - lo[0]:.0f} x {hi[1] - lo[1]:.0f} mm) cannot fit in the field "
                            f"of view of {a.name}; use a smaller grid or spacing_mm", key="calibration.grid")
    for k in range(tries):
        shrink = 1.0 - 0.7 * k / tries  # poses that fail draw ever closer to the isocentre
        nrm = _random_tilt(rng, beam, max_tilt_deg)
        psi = np.deg2rad(rng.uniform(-20, 20))
        R = _plate_frame(nrm, right, psi)
        perp1 = np.cross(beam, [0, 0, 1.0])
        perp1 /= np.linalg.norm(perp1)
        perp2 = np.cross(beam, perp1)
        centre = (rng.uniform(-1, 1) * shift_mm * shrink * perp1 + rng.uniform(-1, 1) * shift_mm * shrink * perp2
                  + rng.uniform(-1, 1) * depth_mm * shrink * beam)
        pose = PlatePose(R, centre - R @ pattern.centre)
        if _pose_ok(pattern, pose, arms, bead_r_mm):
            return pose
    raise TwinError("no plate pose keeps the whole pattern inside the field of view; "
                    "use a smaller grid or spacing_mm", key="calibration.grid")


def render_plate_xray(arm: CArm, pattern: PlatePattern, pose: PlatePose, cfg: SynthConfig) -> np.ndarray:
    """Transmission image of the acrylic plate with its steel beads (1 = no attenuation)."""
    cam = arm.camera
    c = cfg.calibration
    xy = arm.field.dense()
    lo, hi = pattern.extent()
    ctr_p = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.0])
    ctr = cam.R @ pose.world(ctr_p[None])[0] + cam.t
    axes = (cam.R @ pose.R).T  # rows: plate axes in camera coordinates
    chord = plate_chord_mm(xy, ctr, axes[2], axes[:2], c.plate_thickness_mm,
                           ((hi[0] - lo[0]) / 2 + 10, (hi[1] - lo[1]) / 2 + 10))
    T = np.exp(-cfg.xray.mu_acrylic_per_mm * chord).astype(np.float32)
    for X in pose.world(pattern.object_points):
        apply_patch(T, sphere_patch(arm.field, X, c.bead_diameter_mm / 2, cfg.xray.mu_steel_per_mm,
                                    cfg.image.supersample))
    return T


_TEXTURE_PX_PER_MM = 16.0


def board_texture(pattern: PlatePattern) -> tuple[np.ndarray, np.ndarray]:
    """Albedo texture (float32, 0.08 black .. 0.9 white) and the plate coordinate (mm) of
    its top-left corner; texture pixel (col, row) covers plate (x0 + col/ppmm, ...)."""
    s = pattern.spacing_mm
    ppmm = _TEXTURE_PX_PER_MM
    if pattern.kind == "chessboard":
        cols, rows = pattern.grid
        lo, hi = pattern.extent()
        W, H = int(round((hi[0] - lo[0]) * ppmm)), int(round((hi[1] - lo[1]) * ppmm))
        X = lo[0] + (np.arange(W) + 0.5) / ppmm
        Y = lo[1] + (np.arange(H) + 0.5) / ppmm
        ix = np.floor(X / s).astype(int)
        iy = np.floor(Y / s).astype(int)
        black = ((ix[None, :] + iy[:, None]) % 2 == 0)
        inside = ((X >= -s) & (X < cols * s))[None, :] & ((Y >= -s) & (Y < rows * s))[:, None]
        tex = np.where(black & inside, 0.08, 0.9).astype(np.float32)
        return tex, lo
    sx, sy = pattern.grid
    margin = int(round(s / 2 * ppmm))
    W, H = int(round(sx * s * ppmm)) + 2 * margin, int(round(sy * s * ppmm)) + 2 * margin
    img = pattern.board.generateImage((W, H), marginSize=margin, borderBits=1)
    tex = (0.08 + (0.9 - 0.08) * img.astype(np.float32) / 255.0).astype(np.float32)
    return tex, np.array([-margin / ppmm, -margin / ppmm])


def render_plate_optical(arm: CArm, pattern: PlatePattern, pose: PlatePose, texture, rng, cfg: SynthConfig,
                         ss: int = 3) -> np.ndarray:
    """An optical camera's image of a chessboard or ChArUco board: the board's albedo seen
    through the camera model (distortion included), ``ss x ss`` samples per pixel, uneven
    lighting, lens blur and Gaussian noise; no X-ray physics."""
    cam = arm.camera
    tex, origin = texture
    w, h = cam.image_size
    xy = arm.field.dense()
    Rb = cam.R @ pose.R
    O = cam.R @ pose.t + cam.t
    e1, e2, e3 = Rb[:, 0], Rb[:, 1], Rb[:, 2]
    xs, ys = xy[..., 0], xy[..., 1]
    dn = xs * e3[0] + ys * e3[1] + e3[2]
    s = (O @ e3) / dn
    qx, qy, qz = s * xs - O[0], s * ys - O[1], s - O[2]
    # board coordinates are smooth in the pixel position: exact at pixel centres, then
    # interpolated to the ss x ss sub-pixel samples
    X = ((qx * e1[0] + qy * e1[1] + qz * e1[2] - origin[0]) * _TEXTURE_PX_PER_MM - 0.5).astype(np.float32)
    Y = ((qx * e2[0] + qy * e2[1] + qz * e2[2] - origin[1]) * _TEXTURE_PX_PER_MM - 0.5).astype(np.float32)
    mapx = cv2.resize(X, (w * ss, h * ss), interpolation=cv2.INTER_LINEAR)
    mapy = cv2.resize(Y, (w * ss, h * ss), interpolation=cv2.INTER_LINEAR)
    alb = cv2.remap(tex, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.45)
    alb = cv2.resize(alb, (w, h), interpolation=cv2.INTER_AREA)
    gx, gy = np.meshgrid(np.linspace(-1, 1, w, dtype=np.float32), np.linspace(-1, 1, h, dtype=np.float32))
    a, b = rng.uniform(-0.15, 0.15, 2)
    img = alb * (1 + a * gx + b * gy)
    if cfg.xray.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), cfg.xray.blur_sigma_px)
    full = 2 ** cfg.image.bit_depth - 1
    img = img * np.float32(0.9 * full)
    if cfg.noise.enabled and cfg.calibration.optical_noise_dn > 0:
        img = img + rng.standard_normal(img.shape).astype(np.float32) * np.float32(
            cfg.calibration.optical_noise_dn * full / 255.0)
    return np.clip(np.rint(img), 0, full).astype(np.uint8 if cfg.image.bit_depth == 8 else np.uint16)


# --- the indentation scene ----------------------------------------------------------------

def indentation_displacement(X, surface_point, into, depth_mm: float, z0_mm: float) -> np.ndarray:
    """Displacement (N, 3) mm under a cylindrical indentor pressed ``depth_mm`` into tissue.

    The Boussinesq field of a normal point load on an incompressible (nu = 1/2) half-space,
    regularised by moving the load ``z0_mm`` (the indentor radius) above the surface and
    scaled so the surface point under the indentor moves exactly ``depth_mm``:

    .. math::

       \\mathbf u = \\frac{\\delta z_0}{2}\\Big[\\Big(\\frac{\\zeta^2}{R^3} + \\frac1R\\Big)\\mathbf n
                   + \\frac{\\zeta}{R^3}\\,\\boldsymbol\\rho\\Big],\\quad \\zeta = z + z_0,\\;
                   R = \\sqrt{\\rho^2 + \\zeta^2}

    ``z`` the depth below the surface along ``into`` (the unit indentation direction),
    ``rho`` the lateral offset from the indentor axis. Points above the surface (z < 0,
    e.g. a reference marker on the skull rim) use z = 0.
    """
    X = np.atleast_2d(np.asarray(X, float))
    n = np.asarray(into, float) / np.linalg.norm(into)
    d = X - np.asarray(surface_point, float)
    z = d @ n
    rho = d - z[:, None] * n
    zeta = np.maximum(z, 0.0) + z0_mm
    R = np.sqrt(np.einsum("ij,ij->i", rho, rho) + zeta ** 2)
    k = depth_mm * z0_mm / 2
    return k * ((zeta ** 2 / R ** 3 + 1 / R)[:, None] * n + (zeta / R ** 3)[:, None] * rho)


@dataclass
class Marker:
    name: str
    kind: str          # "implanted" | "reference" | "indentor"
    diameter_mm: float
    position0_mm: np.ndarray    # at the start (indentor travel 0)
    moves: bool        # follows the tissue (an indentor bead follows the indentor instead)


@dataclass
class IndentationScene:
    """Geometry and motion of the indentation: markers, indentor, tissue, timeline."""

    surface_mm: np.ndarray
    into: np.ndarray
    indentor_radius_mm: float
    indentor_length_mm: float
    gap_mm: float
    depth_mm: float
    speed_mm_s: float
    start_s: float
    hold_s: float
    unload: bool
    markers: list[Marker]
    tissue: list[dict]

    @property
    def z0_mm(self) -> float:
        return self.indentor_radius_mm

    @property
    def travel_max_mm(self) -> float:
        return self.gap_mm + self.depth_mm

    @property
    def end_s(self) -> float:
        t2 = self.start_s + self.travel_max_mm / self.speed_mm_s + self.hold_s
        return t2 + (self.travel_max_mm / self.speed_mm_s if self.unload else 0.0)

    def travel_mm(self, t) -> np.ndarray:
        """Indentor travel from its start position (mm, positive into the tissue) at ``t`` s."""
        t = np.asarray(t, float)
        v = self.speed_mm_s
        T = self.travel_max_mm
        t1 = self.start_s
        t2 = t1 + T / v
        t3 = t2 + self.hold_s
        down = np.clip((t - t1) * v, 0.0, T)
        if not self.unload:
            return down
        return np.where(t < t3, down, np.clip(T - (t - t3) * v, 0.0, T))

    def indentation_mm(self, t) -> np.ndarray:
        """Depth after contact (mm), 0 before contact."""
        return np.maximum(self.travel_mm(t) - self.gap_mm, 0.0)

    def tip_mm(self, t) -> np.ndarray:
        """Centre of the indentor's flat end (world mm), shape (len(t), 3)."""
        tr = np.atleast_1d(self.travel_mm(t))
        return self.surface_mm + (tr - self.gap_mm)[:, None] * self.into

    def positions_mm(self, t) -> np.ndarray:
        """Marker centres (len(t), n_markers, 3) at times ``t``."""
        t = np.atleast_1d(np.asarray(t, float))
        delta = self.indentation_mm(t)
        X0 = np.array([m.position0_mm for m in self.markers]).reshape(-1, 3)
        moves = np.array([m.moves and m.kind != "indentor" for m in self.markers], bool)
        on_rod = np.array([m.kind == "indentor" for m in self.markers], bool)
        out = np.repeat(X0[None], len(t), axis=0)
        if len(X0) == 0:
            return out
        unit = indentation_displacement(X0, self.surface_mm, self.into, 1.0, self.z0_mm)
        out[:, moves] += delta[:, None, None] * unit[None, moves]
        if on_rod.any():
            out[:, on_rod] += np.atleast_1d(self.travel_mm(t))[:, None, None] * self.into
        return out

    def tissue_line_integral(self, arm: CArm) -> np.ndarray:
        """Sum of mu * chord (dimensionless) of the skull and soft tissue, per pixel."""
        cam = arm.camera
        xy = arm.field.dense()
        acc = np.zeros(xy.shape[:2])
        for e in self.tissue:
            c = cam.R @ np.asarray(e["centre_mm"]) + cam.t
            axes = (cam.R @ np.asarray(e["axes"]).T).T
            acc += e["mu_per_mm"] * ellipsoid_chord_mm(xy, c, axes, e["semi_axes_mm"])
        return acc

    def rod_shadow(self, arm: CArm, xy: np.ndarray) -> RodShadow:
        """The rod's chords for rays ``xy``; ``chord(-travel)`` gives them at a travel."""
        cam = arm.camera
        tip0 = self.surface_mm - self.gap_mm * self.into
        return RodShadow(xy, cam.R @ tip0 + cam.t, cam.R @ (-self.into), self.indentor_radius_mm,
                         self.indentor_length_mm)

    def rod_box(self, arm: CArm, pad_px: int = 3) -> tuple[int, int, int, int]:
        """Pixel box (x0, y0, w, h) that holds the rod's shadow at every travel."""
        cam = arm.camera
        n = self.into / np.linalg.norm(self.into)
        a = np.cross(n, [1.0, 0, 0]) if abs(n[0]) < 0.9 else np.cross(n, [0, 1.0, 0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        ang = np.linspace(0, 2 * np.pi, 32, endpoint=False)
        ring = self.indentor_radius_mm * (np.cos(ang)[:, None] * a + np.sin(ang)[:, None] * b)
        pts = []
        for tr in (0.0, self.travel_max_mm):
            tip = self.surface_mm + (tr - self.gap_mm) * n
            for h in np.linspace(0, self.indentor_length_mm, 40):
                pts.append(tip - h * n + ring)
        pts = np.concatenate(pts)
        pts = pts[cam.to_camera(pts)[:, 2] > 1]
        u = cam.project(pts)
        w, h = cam.image_size
        x0 = int(np.clip(np.floor(u[:, 0].min()) - pad_px, 0, w))
        x1 = int(np.clip(np.ceil(u[:, 0].max()) + pad_px + 1, 0, w))
        y0 = int(np.clip(np.floor(u[:, 1].min()) - pad_px, 0, h))
        y1 = int(np.clip(np.ceil(u[:, 1].max()) + pad_px + 1, 0, h))
        return x0, y0, max(x1 - x0, 0), max(y1 - y0, 0)


def rod_cover(scene: IndentationScene, arm: CArm, P: np.ndarray, tips: np.ndarray, radius_mm: float,
              margin_mm: float = 0.4) -> tuple[np.ndarray, np.ndarray]:
    """Whether the rod hides a sphere of ``radius_mm`` at ``P`` (F, 3) with the rod's tip at
    ``tips`` (F, 3), frame by frame: ``clear`` (F,) no ray within ``radius + margin`` of the
    sphere's centre ray meets the rod; ``hidden`` (F,) every ray out to ``radius + 0.1 mm``
    passes through at least 1 mm of it."""
    cam = arm.camera
    Pc = cam.to_camera(P)
    tip_c = cam.to_camera(tips)[:, None, :]
    axis_c = cam.R @ (-scene.into)
    xy0 = Pc[:, :2] / Pc[:, 2:3]
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=-1)

    def chords(rad_mm):
        xy = np.concatenate([xy0[:, None, :], xy0[:, None, :] + (rad_mm / Pc[:, 2])[:, None, None] * ring[None]], axis=1)
        return cylinder_chord_mm(xy, tip_c, axis_c, scene.indentor_radius_mm, scene.indentor_length_mm)

    clear = np.all(chords(radius_mm + margin_mm) <= 0, axis=1)
    hidden = np.all(chords(radius_mm + 0.1) >= 1.0, axis=1)
    return clear, hidden


def build_scene(cfg: SynthConfig, arms: dict[str, CArm], times: dict[str, np.ndarray]) -> IndentationScene:
    """Seeded layout of the markers that meets the study's conditions in every frame: the
    implanted markers move 0.3-1.9 mm at full depth, none touches the indentor, all are
    inside both fields of view and apart on screen; with ``effects.occlusion`` marker M2
    passes behind the indentor in cam1 and M4 in cam2 for part of the sequence (and is
    visible at the first frame, and at the last when ``sequence.unload``), without it no
    marker is ever behind the rod. References: :func:`_reference_layout`.
    Markers are placed one at a time, each drawn again until it fits with those before."""
    sq, fx = cfg.sequence, cfg.effects
    rng = stream(cfg.seed, "scene")
    surface = np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), 6.0])
    into = np.array([0.0, 0.0, -1.0])
    a = sq.indentor_diameter_mm / 2
    yaw = np.deg2rad(rng.uniform(-15, 15))
    Rz = Rotation.from_euler("z", yaw).as_matrix()
    tissue = []
    if cfg.xray.tissue:
        mus, mub = cfg.xray.mu_soft_tissue_per_mm, cfg.xray.mu_bone_per_mm
        tissue = [
            {"name": "head soft tissue", "centre_mm": surface + Rz @ [0, 15, -30], "semi_axes_mm": [55, 95, 60],
             "mu_per_mm": mus},
            {"name": "skull (outer)", "centre_mm": surface + Rz @ [0, 8, -28], "semi_axes_mm": [36, 52, 31],
             "mu_per_mm": mub - mus},
            {"name": "brain (skull inner)", "centre_mm": surface + Rz @ [0, 8, -28], "semi_axes_mm": [33, 49, 28],
             "mu_per_mm": -(mub - mus)},
        ]
        for e in tissue:
            e["axes"] = Rz.T  # rows are the ellipsoid's axes in world coordinates

    def scene_with(markers):
        return IndentationScene(surface, into, a, 200.0, sq.gap_mm, sq.depth_mm, sq.speed_mm_per_min / 60.0,
                                sq.start_s, sq.hold_s, sq.unload, markers, tissue)

    base = scene_with([])
    occ_view = {"M2": "cam1", "M4": "cam2"} if fx.occlusion else {}
    tips = {v: base.tip_mm(times[v]) for v in VIEWS}

    def horiz(v):
        b = arms[v].beam_dir.copy()
        b -= np.dot(b, into) * into
        return b / np.linalg.norm(b)

    def draw(kind: str, k: int) -> Marker:
        if kind == "indentor":
            # a radiolucent collar on the shaft carries two beads either side of the axis, along
            # the bisector of the two beams, so each C-arm sees both clear of the steel rod
            b = horiz(VIEWS[0]) + horiz(VIEWS[1])
            b = b / np.linalg.norm(b) if np.linalg.norm(b) > 1e-6 else horiz(VIEWS[0])
            tip0 = surface - sq.gap_mm * into
            X = tip0 - sq.indentor_marker_height_mm * into + (1 if k == 0 else -1) * sq.indentor_marker_offset_mm * b
            return Marker(f"I{k + 1}", "indentor", sq.indentor_marker_diameter_mm, X, True)
        if kind == "reference":
            ang, rad = ref_layout[k]
            off = rad * np.array([np.cos(ang), np.sin(ang), 0.0])
            X = surface + off + rng.uniform(0.0, 1.5) * into  # in the skull rim
            return Marker(f"R{k + 1}", "reference", sq.reference_diameter_mm, X, bool(fx.moving_reference and k == 1))
        name = f"M{k + 1}"
        if name in occ_view:
            hb = horiz(occ_view[name])
            side = np.cross(into, hb)
            off = (rng.choice([-1, 1]) * rng.uniform(a + 0.8, a + 3.5) * hb
                   + rng.uniform(-1, 1) * max(a - sq.marker_diameter_mm / 2 - 0.6, 0.0) * side)
            depth = rng.uniform(1.0, 2.5)
        else:
            r, th = rng.uniform(0, 9), rng.uniform(0, 2 * np.pi)
            off = r * np.array([np.cos(th), np.sin(th), 0.0])
            depth = rng.uniform(2.0, 10.0)
        return Marker(name, "implanted", sq.marker_diameter_mm, surface + off + depth * into, True)

    kinds = ([("indentor", k) for k in range(sq.indentor_markers)] + [("reference", k) for k in range(sq.n_references)]
             + [("implanted", k) for k in range(sq.n_markers)])
    failed: dict[str, int] = {}
    for attempt in range(40):
        psi = np.deg2rad(rng.uniform(15, 30)) + np.pi / 4
        ref_layout = _reference_layout(cfg, arms, psi, [horiz(v) for v in VIEWS], rng)
        placed: list[Marker] = []
        tracks: dict[str, list[np.ndarray]] = {v: [] for v in VIEWS}
        for kind, k in kinds:
            for _ in range(200):
                m = draw(kind, k)
                tr = _marker_fits(scene_with([m]), m, arms, times, tips, occ_view, placed, tracks)
                if tr is not None:
                    placed.append(m)
                    for v in VIEWS:
                        tracks[v].append(tr[v])
                    break
            else:
                who = "occluded" if kind == "implanted" and f"M{k + 1}" in occ_view else kind
                failed[who] = failed.get(who, 0) + 1
                break
        if len(placed) == len(kinds):
            return scene_with(placed)
    who = max(failed, key=failed.get) if failed else "implanted"
    keys = {"indentor": ("sequence.indentor_markers", "sequence.indentor_marker_offset_mm"),
            "reference": ("sequence.n_references", "sequence.craniotomy_mm", "sequence.reference_diameter_mm"),
            "occluded": ("effects.occlusion", "sequence.indentor_diameter_mm"),
            "implanted": ("sequence.n_markers", "sequence.marker_diameter_mm", "sequence.indentor_diameter_mm")}[who]
    what = {"indentor": "the indentor's beads", "reference": "the reference markers",
            "occluded": "the markers that pass behind the indentor (M2, M4)",
            "implanted": "the implanted markers"}[who]
    hint = ""
    if who == "indentor":
        # the beads sit on the bisector of the two beams: each view sees them offset x sin(angle / 2)
        # from the rod's axis (at 60 degrees, 3 mm for the default offset against a 2.5 mm rod
        # radius: the message had named the beads' keys and not the angle)
        half = np.deg2rad(cfg.geometry.angle_between_deg) / 2.0
        seen = cfg.sequence.indentor_marker_offset_mm * np.sin(half)
        keys = keys + ("geometry.angle_between_deg",)
        hint = (f" (the beads sit on the bisector of the two C-arms' beams, so at geometry.angle_between_deg "
                f"{cfg.geometry.angle_between_deg:g} each view sees them {seen:.2g} mm from the rod's axis, against "
                f"its radius of {cfg.sequence.indentor_diameter_mm / 2:.2g} mm)")
    raise TwinError(f"could not place {what} so that they stay apart, inside the field of view and clear of "
                    f"the indentor (as the design needs){hint}; change {', '.join(keys)}", key=keys[0])


def _reference_layout(cfg: SynthConfig, arms: dict[str, CArm], psi: float, beams: list[np.ndarray],
                      rng: np.random.Generator) -> list[tuple[float, float]]:
    """(angle about the indentor axis, distance from it in mm) of each reference marker.

    Four references sit at the craniotomy's corners, turned by ``psi``; other counts on a
    circle of half the craniotomy's side, equally spaced from ``psi`` when that keeps every
    one out of the indentor rod's shadow in both views. Otherwise (three, five, six or eight
    references: equal spacing always puts one near a beam axis) they are drawn on the bone
    around the square craniotomy (corners at ``psi + 90 k``, up to 1.5 mm out), where each
    one's offset across each beam clears the rod (radius + bead radius + 0.6 mm) and differs
    from every other reference's by enough to keep them apart on screen (bead diameter +
    max(8 px at 1024 px, 3 px) + 0.3 mm)."""
    sq = cfg.sequence
    n, c = sq.n_references, sq.craniotomy_mm / 2
    if n == 0:
        return []
    rad = c * math.sqrt(2) if n == 4 else c
    layout = [(psi + 2 * np.pi * k / n, rad) for k in range(n)]
    clear_mm = sq.indentor_diameter_mm / 2 + sq.reference_diameter_mm / 2 + 0.6
    phi = np.array([math.atan2(b[1], b[0]) for b in beams])

    def across(ang, r):                 # (..., views) offset across each beam, mm
        return np.asarray(r)[..., None] * np.sin(np.asarray(ang)[..., None] - phi)

    if n == 4 or np.all(np.abs(across([a for a, _ in layout], rad)) >= clear_mm):
        return layout
    arm = arms[VIEWS[0]]
    mm_per_px = arm.pixel_pitch_mm * arm.sod_mm / arm.sid_mm
    sep_mm = sq.reference_diameter_mm + max(8 * arm.camera.image_size[0] / 1024.0, 3.0) * mm_per_px + 0.3
    # candidates on the bone around the square craniotomy (corners at psi + 90 k), up to 1.5 mm out
    g = np.arange(-c - 1.5, c + 1.5 + 1e-9, 0.25)
    gx, gy = np.meshgrid(g, g)
    on_rim = (np.maximum(np.abs(gx), np.abs(gy)) >= c).ravel()
    turn = psi - np.pi / 4
    xr = gx.ravel() * np.cos(turn) - gy.ravel() * np.sin(turn)
    yr = gx.ravel() * np.sin(turn) + gy.ravel() * np.cos(turn)
    cand_ang, cand_rad = np.arctan2(yr, xr)[on_rim], np.hypot(xr, yr)[on_rim]
    off = across(cand_ang, cand_rad)                  # (candidates, views)
    ok = np.all(np.abs(off) >= clear_mm, axis=1)
    cand_ang, cand_rad, off = cand_ang[ok], cand_rad[ok], off[ok]
    for _ in range(200):
        chosen: list[int] = []
        free = np.ones(len(off), bool)
        for _k in range(n):
            idx = np.flatnonzero(free)
            if len(idx) == 0:
                break
            j = int(rng.choice(idx))
            chosen.append(j)
            free &= np.all(np.abs(off - off[j]) >= sep_mm, axis=1)
        if len(chosen) == n:
            return [(float(cand_ang[j]), float(cand_rad[j])) for j in chosen]
    return layout                       # cannot be met: placement then fails and says so


def _marker_fits(scene: IndentationScene, m: Marker, arms, times, tips, occ_view, placed, tracks):
    """The marker's projected track per view (F, 3: x_px, y_px, r_px) if it meets every
    condition alone and against the markers already placed, else None."""
    r = m.diameter_mm / 2
    px = arms[VIEWS[0]].camera.image_size[0] / 1024.0   # pixel margins are set for 1024 px frames
    unit = indentation_displacement(m.position0_mm, scene.surface_mm, scene.into, 1.0, scene.z0_mm)[0]
    if m.kind == "implanted" and not (0.3 <= np.linalg.norm(unit) * scene.depth_mm <= 1.9):
        return None
    for p in placed:
        if np.linalg.norm(p.position0_mm - m.position0_mm) < 2.0:
            return None
    out = {}
    for v in VIEWS:
        arm = arms[v]
        P = scene.positions_mm(times[v])[:, 0]                        # (F, 3)
        rel = P - tips[v]
        ax = rel @ scene.into                                         # > 0: below the tip
        lat = np.linalg.norm(rel - ax[:, None] * scene.into, axis=-1)
        if m.kind == "implanted" and np.any((lat < scene.indentor_radius_mm + r + 0.2) & (ax < r + 0.3)):
            return None
        u = arm.camera.project(P)
        rpx = arm.camera.fx * r / arm.camera.to_camera(P)[:, 2]
        if not np.all(arm.in_fov(u, margin_px=25 * px)):
            return None
        for q in tracks[v]:
            if np.any(np.hypot(*(u - q[:, :2]).T) < rpx + q[:, 2] + max(8 * px, 3.0)):
                return None
        clear, hidden = rod_cover(scene, arm, P, tips[v], r)
        if occ_view.get(m.name) == v:
            # clear at the start, hidden for a while, and clear again once the indentor is
            # withdrawn (without unloading it stays down, so the marker stays hidden)
            if not (clear[0] and (clear[-1] or not scene.unload) and hidden.sum() >= 3):
                return None
        elif not np.all(clear):
            return None
        out[v] = np.column_stack([u, rpx])
    return out


# --- the twin --------------------------------------------------------------------------------

class Twin:
    """Everything ``bsipipe synth`` writes, computed from a validated :class:`SynthConfig`.

    Frames are produced lazily (:meth:`calibration_images`, :meth:`sequence_frames`), each
    as ``(relative path, image array)``; :meth:`truth` afterwards holds every true value.
    """

    def __init__(self, cfg: SynthConfig):
        self.cfg = cfg
        self.arms = build_carms(cfg)
        self.pattern = make_pattern(cfg)
        sq = cfg.sequence
        self._base_scene_times()
        self.scene = build_scene(cfg, self.arms, self.design_times) if sq.enabled else None
        self._calib_truth: dict = {"views": {}, "stereo": []}
        self._seq_truth: dict | None = None
        self.timing: dict[str, float] = {}

    # --- timeline ----------------------------------------------------------------------------
    def _base_scene_times(self) -> None:
        """Frame times per view. The layout is checked over the whole designed experiment
        (``design_times``), so ``n_frames`` only shortens or extends the recording."""
        sq = self.cfg.sequence
        v = sq.speed_mm_per_min / 60.0
        T = sq.gap_mm + sq.depth_mm
        end = sq.start_s + T / v + sq.hold_s + (T / v if sq.unload else 0.0) + 1.0
        n_design = int(math.floor(end * sq.fps + 1e-9)) + 1
        self.n_frames = sq.n_frames or n_design
        off = self.cfg.effects.view_time_offset_s
        rate = 1.0 + self.cfg.effects.view_clock_drift
        t = np.arange(self.n_frames) / sq.fps
        td = np.arange(max(n_design, self.n_frames)) / sq.fps
        self.times = {"cam1": t, "cam2": t * rate + off}
        self.design_times = {"cam1": td, "cam2": td * rate + off}

    # --- calibration -------------------------------------------------------------------------
    def calibration_images(self) -> Iterator[tuple[str, np.ndarray]]:
        cfg, c, pat = self.cfg, self.cfg.calibration, self.pattern
        r_bead = c.bead_diameter_mm / 2
        noise = stream(cfg.seed, "calib_noise")
        texture = None if pat.xray else board_texture(pat)
        for v in VIEWS:
            rng = np.random.default_rng(stream(cfg.seed, "calibration").integers(0, 2 ** 63, size=2)[VIEWS.index(v)])
            out = self._calib_truth["views"].setdefault(v, [])
            for i in range(c.views):
                pose = sample_plate_pose(rng, pat, [self.arms[v]], c.max_tilt_deg, r_bead)
                name = f"cal_{i:03d}.png"
                img = self._render_plate(v, pose, noise, texture)
                out.append(self._plate_truth(v, pose, f"calibration/{v}/{name}", name))
                yield f"calibration/{v}/{name}", img
        rng = stream(cfg.seed, "stereo")
        for i in range(c.stereo_views):
            pose = sample_plate_pose(rng, pat, [self.arms[v] for v in VIEWS], min(c.max_tilt_deg, 12.0), r_bead,
                                     shift_mm=15.0, depth_mm=15.0)
            name = f"stereo_{i:03d}.png"
            rec = {"file": name, "R_plate": pose.R.tolist(), "t_plate_mm": pose.t.tolist(), "views": {}}
            self._calib_truth["stereo"].append(rec)
            for v in VIEWS:
                img = self._render_plate(v, pose, noise, texture)
                rec["views"][v] = self._plate_truth(v, pose, f"calibration/stereo/{v}/{name}", name)
                yield f"calibration/stereo/{v}/{name}", img

    def _render_plate(self, v, pose, rng, texture):
        arm = self.arms[v]
        if self.pattern.xray:
            T = render_plate_xray(arm, self.pattern, pose, self.cfg)
            img, _ = arm.detector.expose(T, rng)
            return img
        return render_plate_optical(arm, self.pattern, pose, texture, rng, self.cfg)

    def _plate_truth(self, v, pose, path, name) -> dict:
        cam = self.arms[v].camera
        X = pose.world(self.pattern.object_points)
        u = cam.project(X)
        Rb = cam.R @ pose.R
        tb = cam.R @ pose.t + cam.t
        return {"file": name, "path": path, "R_plate": pose.R.tolist(), "t_plate_mm": pose.t.tolist(),
                "rvec": cv2.Rodrigues(Rb)[0].ravel().tolist(), "tvec_mm": tb.tolist(),
                "image_points_px": u.tolist(),
                "inside_fov": self.arms[v].in_fov(u).tolist()}

    # --- sequence --------------------------------------------------------------------------------
    def sequence_frames(self) -> Iterator[tuple[str, np.ndarray]]:
        cfg, sc = self.cfg, self.scene
        if sc is None:
            return
        ss = cfg.image.supersample
        rng = stream(cfg.seed, "frames")
        mu = cfg.xray.mu_steel_per_mm
        truth = {"projections_px": {}, "occluded": {}, "visible": {}, "tip_px": {}, "jolt_px": {}, "specks": {}}
        jolt_rng = stream(cfg.seed, "jolt")
        speck_rng = stream(cfg.seed, "specks")
        a = cfg.effects.frame_jolt_px
        for v in VIEWS:
            arm = self.arms[v]
            cam = arm.camera
            t = self.times[v]
            P = sc.positions_mm(t)
            tips = sc.tip_mm(t)
            T0 = np.exp(-sc.tissue_line_integral(arm)).astype(np.float32) if sc.tissue else \
                np.ones(cam.image_size[::-1], np.float32)
            bx, by, bw, bh = sc.rod_box(arm)
            rod = sc.rod_shadow(arm, arm.field.block(bx, by, bw, bh, 2)) if bw and bh else None
            travel = sc.travel_mm(t)
            ref = None
            proj, occ = [], []
            # a jolt moves the anatomy on the detector (not the intensifier's field): the
            # transmission image is shifted, its edge repeated, before the exposure
            jolt = jolt_rng.integers(-a, a + 1, (len(t), 2)) if a > 0 else np.zeros((len(t), 2), int)
            jolt[0] = 0
            truth["jolt_px"][v] = jolt
            # dust on the intensifier: a fixed transmission loss on the detector, scattered over
            # the markers' region (their first positions, 40 px around)
            specks = None
            if cfg.effects.static_specks:
                u0 = cam.project(P[0])
                lo, hi = u0.min(axis=0) - 40, u0.max(axis=0) + 40
                n = cfg.effects.static_specks
                sp = np.column_stack([speck_rng.uniform(lo, hi, (n, 2)), speck_rng.uniform(0.08, 0.25, n),
                                      speck_rng.uniform(1.0, 1.8, n)])
                truth["specks"][v] = sp
                specks = _speck_mask(cam.image_size, sp)
            for i in range(len(t)):
                T = T0.copy()
                rod_T = None
                if rod is not None:
                    rod_T = np.exp(-mu * rod.chord(-travel[i])).reshape(bh, 2, bw, 2).mean(axis=(1, 3))
                    T[by:by + bh, bx:bx + bw] *= rod_T.astype(np.float32)
                u = cam.project(P[i])
                o = []
                for j, m in enumerate(sc.markers):
                    p = sphere_patch(arm.field, P[i, j], m.diameter_mm / 2, mu, ss)
                    apply_patch(T, p)
                    o.append(self._occluded(p, rod_T, (bx, by), u[j], cam, P[i, j], m))
                if jolt[i].any():
                    T = _shifted(T, int(jolt[i, 0]), int(jolt[i, 1]))
                    u = u + jolt[i]
                if specks is not None:
                    T = T * specks
                img, ref = arm.detector.expose(T, rng, ref)
                proj.append(u)
                occ.append(o)
                yield f"sequence/{v}/frame_{i:04d}.png", img
            proj = np.array(proj).reshape(len(t), len(sc.markers), 2)
            occ = np.array(occ, bool).reshape(len(t), len(sc.markers))
            inside = arm.in_fov(proj.reshape(-1, 2), margin_px=3).reshape(occ.shape)
            truth["projections_px"][v] = proj
            truth["occluded"][v] = occ
            truth["visible"][v] = inside & ~occ
            truth["tip_px"][v] = cam.project(tips) + jolt
        self._seq_truth = truth

    @staticmethod
    def _occluded(p: Patch | None, rod_T, box, u, cam, X, m) -> bool:
        """True if the rod's shadow reaches the marker's disc (+1 px) anywhere."""
        if rod_T is None or p is None:
            return False
        bx, by = box
        bh, bw = rod_T.shape
        zc = cam.to_camera(X)[0, 2]
        r = cam.fx * m.diameter_mm / 2 / zc * 1.15 + 1.0
        x0, x1 = int(np.floor(u[0] - r)), int(np.ceil(u[0] + r)) + 1
        y0, y1 = int(np.floor(u[1] - r)), int(np.ceil(u[1] + r)) + 1
        xa, xb = max(x0, bx), min(x1, bx + bw)
        ya, yb = max(y0, by), min(y1, by + bh)
        if xa >= xb or ya >= yb:
            return False
        sub = rod_T[ya - by:yb - by, xa - bx:xb - bx]
        gy, gx = np.mgrid[ya:yb, xa:xb]
        near = np.hypot(gx - u[0], gy - u[1]) <= r
        return bool(np.any(sub[near] < 0.999))

    # --- log, CT, seeds, truth -------------------------------------------------------------------
    def machine_log(self):
        """The Micro Tester's record of the indentation, from the machine-log twin
        (:func:`bsipipe.synth.machine_log.synth_indentation_log`): the same gap, depth,
        speed, hold and unloading as the indentor in the frames, the brain as a one-term
        Ogden solid. The log's clock starts when the crosshead starts moving, ``start_s``
        after cam1's frame 0. Returns ``(frame, truth)``; frame compression-positive."""
        from .machine_log import synth_indentation_log

        sq = self.cfg.sequence
        protocol = "ramp" + ("-hold" if sq.hold_s > 0 else "") + ("-unload" if sq.unload else "")
        seed = int(stream(self.cfg.seed, "log").integers(0, 2 ** 31 - 1))
        frame, truth = synth_indentation_log(indenter_diameter_mm=sq.indentor_diameter_mm,
                                             speed_mm_min=sq.speed_mm_per_min, depth_mm=sq.depth_mm,
                                             gap_mm=sq.gap_mm, mu_pa=sq.tissue_mu_pa, alpha=sq.tissue_alpha,
                                             protocol=protocol, hold_s=sq.hold_s, noise_n=sq.force_noise_n,
                                             rate_hz=sq.log_rate_hz, seed=seed)
        truth = {k: v for k, v in truth.items() if k != "force_true_n"}
        truth.update(clock_offset_s=float(sq.start_s),
                     clock="cam1 time = log time + clock_offset_s",
                     contact_time_s=float(sq.gap_mm / self.scene.speed_mm_s))
        return frame, truth

    def ct_transform(self) -> tuple[np.ndarray, np.ndarray]:
        rng = stream(self.cfg.seed, "ct")
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        R = Rotation.from_rotvec(np.deg2rad(rng.uniform(15, 40)) * axis).as_matrix()
        t = np.array([rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(-160, -60)])
        return R, t

    def ct_markers(self) -> dict:
        """CT (LPS, mm) coordinates of every marker before indentation: ``x_ct = R x + t``,
        with optional localisation noise."""
        R, t = self.ct_transform()
        rng = stream(self.cfg.seed, "ct_noise")
        in_ct = [m for m in self.scene.markers if m.kind != "indentor"]    # the CT was taken before
        names = [m.name for m in in_ct]                                     # the indentor was mounted
        X0 = np.array([m.position0_mm for m in in_ct]).reshape(-1, 3)
        exact = X0 @ R.T + t
        noisy = exact + rng.normal(0, self.cfg.ct.noise_mm, exact.shape) if self.cfg.ct.noise_mm > 0 else exact
        return {"names": names, "exact_mm": exact, "written_mm": noisy, "R": R, "t_mm": t}

    def seeds(self) -> list[dict]:
        rng = stream(self.cfg.seed, "seeds")
        sc, out = self.scene, []
        s = self.cfg.sequence.seed_click_noise_px
        for v in VIEWS:
            u = self.arms[v].camera.project(sc.positions_mm(self.times[v][:1])[0])
            for j, m in enumerate(sc.markers):
                e = rng.normal(0, s, 2) if s > 0 else np.zeros(2)
                out.append({"view": v, "marker": m.name, "x_px": round(float(u[j, 0] + e[0]), 3),
                            "y_px": round(float(u[j, 1] + e[1]), 3)})
        return out

    def truth_markers_rows(self) -> list[dict]:
        sc, st = self.scene, self._seq_truth
        rows = []
        for v in VIEWS:
            P = sc.positions_mm(self.times[v])
            for i, tt in enumerate(self.times[v]):
                for j, m in enumerate(sc.markers):
                    rows.append({"view": v, "frame": i, "time_s": round(float(tt), 6), "marker": m.name,
                                 "x_px": float(st["projections_px"][v][i, j, 0]),
                                 "y_px": float(st["projections_px"][v][i, j, 1]),
                                 "x_mm": float(P[i, j, 0]), "y_mm": float(P[i, j, 1]), "z_mm": float(P[i, j, 2]),
                                 "occluded": bool(st["occluded"][v][i, j]), "visible": bool(st["visible"][v][i, j])})
        return rows

    def truth(self) -> dict:
        cfg = self.cfg
        out: dict = {
            "schema": "bsipipe-synth-truth/1",
            "seed": cfg.seed,
            "units": {"length": "mm", "time": "s", "force": "N", "pixels": "raw (distorted) image, OpenCV convention"},
            "world_frame": "origin at the isocentre, z up; cam1 looks along +x",
            "image_size": [cfg.image.size_px, cfg.image.size_px],
            "bit_depth": cfg.image.bit_depth,
            "cameras": {v: a.truth() for v, a in self.arms.items()},
            "stereo_extrinsics": stereo_extrinsics(self.arms["cam1"].camera, self.arms["cam2"].camera),
            "effects": cfg.effects.model_dump(),
            "distortion": cfg.distortion.model_dump(),
            "noise": {**cfg.noise.model_dump(), "blur_sigma_px": cfg.xray.blur_sigma_px},
            "xray": cfg.xray.model_dump(),
        }
        pat = self.pattern
        out["calibration"] = {
            "pattern": pat.kind, "grid": list(pat.grid), "spacing_mm": pat.spacing_mm,
            "bead_diameter_mm": cfg.calibration.bead_diameter_mm if pat.xray else None,
            "object_points_mm": pat.object_points.tolist(),
            "charuco": ({"dictionary": cfg.calibration.charuco_dictionary,
                         "marker_length_mm": pat.spacing_mm * cfg.calibration.charuco_marker_fraction,
                         "corner_ids": pat.corner_ids.tolist()} if pat.kind == "charuco" else None),
            "views": self._calib_truth["views"], "stereo": self._calib_truth["stereo"],
        }
        if self.scene is not None:
            sc = self.scene
            st = self._seq_truth or {}
            traj = {v: sc.positions_mm(self.times[v]) for v in VIEWS}
            ct = self.ct_markers()
            R, t = ct["R"], ct["t_mm"]
            seq = {
                "fps": cfg.sequence.fps, "n_frames": self.n_frames,
                "times_s": {v: self.times[v].tolist() for v in VIEWS},
                "view_time_offset_s": cfg.effects.view_time_offset_s,
                "view_clock_drift": cfg.effects.view_clock_drift,
                "markers": {m.name: {"kind": m.kind, "diameter_mm": m.diameter_mm, "moves": m.moves,
                                     "position0_mm": m.position0_mm.tolist()} for m in sc.markers},
                "trajectories_mm": {m.name: traj["cam1"][:, j].tolist() for j, m in enumerate(sc.markers)},
                "positions_mm_per_view": {v: {m.name: traj[v][:, j].tolist() for j, m in enumerate(sc.markers)}
                                          for v in VIEWS},
                "max_displacement_mm": {
                    m.name: float(np.linalg.norm(traj["cam1"][:, j] - traj["cam1"][0, j], axis=1).max())
                    for j, m in enumerate(sc.markers)},
                "indentor": {
                    "diameter_mm": 2 * sc.indentor_radius_mm, "length_mm": sc.indentor_length_mm,
                    "direction": sc.into.tolist(), "surface_point_mm": sc.surface_mm.tolist(),
                    "gap_mm": sc.gap_mm, "depth_mm": sc.depth_mm, "speed_mm_s": sc.speed_mm_s,
                    "start_s": sc.start_s, "hold_s": sc.hold_s, "unload": sc.unload,
                    "tip_mm": sc.tip_mm(self.times["cam1"]).tolist(),
                    "tip_ct_mm": (sc.tip_mm(self.times["cam1"]) @ R.T + t).tolist(),
                    "indentation_mm": sc.indentation_mm(self.times["cam1"]).tolist(),
                },
                "displacement_field": {"model": "regularised Boussinesq, incompressible half-space",
                                       "z0_mm": sc.z0_mm, "surface_point_mm": sc.surface_mm.tolist(),
                                       "direction": sc.into.tolist()},
                "tissue": [{k: (np.asarray(v).tolist() if k != "name" else v) for k, v in e.items()}
                           for e in sc.tissue],
            }
            if st:
                for key in ("projections_px", "occluded", "visible"):
                    seq[key] = {v: {m.name: st[key][v][:, j].tolist() for j, m in enumerate(sc.markers)}
                                for v in VIEWS}
                seq["indentor"]["tip_px"] = {v: st["tip_px"][v].tolist() for v in VIEWS}
                if cfg.effects.frame_jolt_px:
                    seq["frame_jolt_px"] = {v: st["jolt_px"][v].tolist() for v in VIEWS}
                if cfg.effects.static_specks:
                    seq["static_specks"] = {v: [dict(zip(("x_px", "y_px", "depth", "sigma_px"), map(float, r)))
                                                for r in st["specks"][v]] for v in VIEWS}
            out["sequence"] = seq
            out["ct"] = {"coordinate_system": "LPS", "R": R.tolist(), "t_mm": t.tolist(),
                         "maps": "x_ct = R @ x_world + t_mm", "frame": 0, "noise_mm": cfg.ct.noise_mm,
                         "markers_mm": {n: ct["exact_mm"][j].tolist() for j, n in enumerate(ct["names"])},
                         "markers_written_mm": {n: ct["written_mm"][j].tolist() for j, n in enumerate(ct["names"])},
                         "markers_ct_mm_per_frame": {m.name: (traj["cam1"][:, j] @ R.T + t).tolist()
                                                     for j, m in enumerate(sc.markers)}}
            _, log_truth = self.machine_log()
            out["log"] = {"file": "indentation_log.csv", "layout": "bluehill3", **log_truth}
        return out
