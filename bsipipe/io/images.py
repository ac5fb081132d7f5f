"""Read images and frame sequences: PNG, TIFF (8/16-bit, multi-page), JPEG, DICOM
(single-frame, multi-frame, series), folders and globs of image files, and videos (AVI, MP4).

Every frame comes back as a 2-D grayscale array in the file's **native dtype** (``uint8``,
``uint16``, ``float32``...), pixel values unchanged, so a 16-bit X-ray keeps its dynamic
range; pass ``dtype=np.float32`` (or any float dtype) for a float copy with the same values
(no rescaling).  Colour images become grayscale with the ITU-R BT.601 luma weights
(0.299 R + 0.587 G + 0.114 B) unless ``channel`` picks one channel (0 = R, 1 = G, 2 = B);
an alpha channel is dropped.  DICOM ``MONOCHROME1`` images (low values shown bright) are
inverted to the ``MONOCHROME2`` convention so that dense objects look the same in every
source (beads dark, as in raw C-arm frames).

Frames are streamed: :func:`iter_frames` yields one :class:`Frame` at a time and never holds
a whole video or stack in memory.  All frames of one source must have the same size.

Errors are :class:`~bsipipe.errors.InputError` (exit status 2) naming the file and, in a
sequence, the frame index: a missing path, an undecodable or truncated file, a size or a
bit depth that differs from the first frame's.
"""

from __future__ import annotations

import glob as _glob
import logging
import os
import re
from pathlib import Path
from typing import Iterator, NamedTuple

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)

#: File suffixes read as single still images (lower case).
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".dcm", ".dicom", ".pgm", ".ppm")
#: File suffixes read as videos through OpenCV's VideoCapture.
VIDEO_SUFFIXES = (".avi", ".mp4", ".mov", ".mkv", ".m4v", ".wmv")


class Frame(NamedTuple):
    """One frame of a source.

    index : int
        0-based position in the source (after sorting for folders); where the files' frame
        counter skips numbers (a dropped frame), the counter's, so the skipped indices stay
        empty (:func:`frame_numbers`).
    name : str
        File name for folders/globs, ``"<file>#<index>"`` inside a multi-frame file.
    image : ndarray, shape (h, w)
        Grayscale pixels, native dtype unless a dtype was asked for.
    time_s : float or None
        Time stamp the source states (video position, DICOM frame time); None otherwise.
    """

    index: int
    name: str
    image: np.ndarray
    time_s: float | None


def natural_key(name: str) -> list:
    """Sort key that orders embedded numbers by value (``f2`` before ``f10``).

    For zero-padded names this is the same order as plain sorting by name.

    >>> sorted(["f10.png", "f2.png", "f1.png"], key=natural_key)
    ['f1.png', 'f2.png', 'f10.png']
    """
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


#: Suffixes whose files are raster images, never DICOM: a folder of PNG frames is not opened
#: twice per frame to look for a DICOM preamble (0.1-0.5 ms a frame on the decoding threads);
#: DICOM data under such a name is refused by the decoder with a message saying so.
_RASTER_SUFFIXES = tuple(s for s in IMAGE_SUFFIXES if s not in (".dcm", ".dicom"))


def _is_dicom(path: Path) -> bool:
    suf = path.suffix.lower()
    if suf in (".dcm", ".dicom"):
        return True
    if suf in _RASTER_SUFFIXES:
        return False
    try:
        with open(path, "rb") as f:
            head = f.read(132)
        return len(head) == 132 and head[128:132] == b"DICM"
    except OSError:
        return False


def list_image_files(source: str | os.PathLike) -> list[Path]:
    """The image files a folder or glob names, sorted by name (:func:`natural_key`); a DICOM
    series (every file single-frame DICOM) in InstanceNumber order instead (then acquisition
    time, then name: :func:`_dicom_series`), as scanners name files by UID.

    A folder contributes its files with an image or DICOM suffix (or a DICOM preamble);
    hidden files are skipped.  A glob with no match, or a folder without images, is an
    InputError.
    """
    return _source_files(source)[0]


def _by_name(source: str | os.PathLike) -> list[Path]:
    """The image files of a folder or glob (a single file: itself), sorted by name."""
    s = str(source)
    p = Path(s)
    if p.is_dir():
        # a DICOMDIR (the index of a CD or PACS export, always that name) holds no image
        files = [q for q in p.iterdir() if q.is_file() and not q.name.startswith(".")
                 and q.name.upper() != "DICOMDIR"
                 and (q.suffix.lower() in IMAGE_SUFFIXES or (q.suffix == "" and _is_dicom(q)))]
        if not files:
            videos = sorted((q.name for q in p.iterdir() if q.is_file() and q.suffix.lower() in VIDEO_SUFFIXES),
                            key=natural_key)
            if videos:
                raise InputError(f"folder holds videos ({', '.join(videos[:3])}{', ...' if len(videos) > 3 else ''}), "
                                 "not image files: give the video, or a glob of them "
                                 f"({p / ('*' + Path(videos[0]).suffix)}) to play them one after another", path=p)
            raise InputError("folder holds no image files (PNG, TIFF, JPEG, BMP, DICOM)", path=p)
    elif any(c in s for c in "*?["):
        files = [Path(q) for q in _glob.glob(s) if Path(q).is_file()]
        if not files:
            raise InputError("no file matches this pattern", path=s)
    elif p.is_file():
        files = [p]
    else:
        raise InputError("no such file or folder", path=s)
    return sorted(files, key=_name_order(files))


#: A file stem that is one decimal number between a fixed prefix and suffix (``t_0.25s``).
_DECIMAL_NAME = re.compile(r"^(.*?)(\d+\.\d+|\d+)(\D*)$")


def _name_order(files: list[Path]):
    """The sort key of a folder's frames: :func:`natural_key`, or, where every name is one
    number with a decimal point or none between one prefix and one suffix (frames named by
    their time: ``t_0s``, ``t_0.25s``, ``t_0.5s``), that number's value (the natural order
    put ``t_0.5s`` before ``t_0.25s``: frames out of order, exit 0).

    >>> names = [Path(f"t_{t:g}s.png") for t in (0, 0.25, 0.5, 0.75, 1, 1.25)]
    >>> [q.name for q in sorted(names[::-1], key=_name_order(names))][:4]
    ['t_0s.png', 't_0.25s.png', 't_0.5s.png', 't_0.75s.png']
    """
    parts = [_DECIMAL_NAME.match(q.stem) for q in files]
    if (len(files) > 1 and all(parts) and any("." in m.group(2) for m in parts)
            and len({(m.group(1), m.group(3), q.suffix.lower()) for m, q in zip(parts, files)}) == 1):
        value = {q: float(m.group(2)) for q, m in zip(files, parts)}
        if len(set(value.values())) == len(files):
            return lambda q: (value.get(q, float("inf")), natural_key(q.name))
    return lambda q: natural_key(q.name)


#: The last number in a file name, with the text before and after it (``frame_0057.png``).
_COUNTER = re.compile(r"^(.*?)(\d+)(\D*)$")


def frame_numbers(numbers) -> list[int] | None:
    """Frame indices from a source's frame counter (the numbers in its file names, or a
    DICOM series' InstanceNumbers), in order, where some numbers are missing: a frame the
    recorder dropped or a file deleted leaves its index empty instead of shifting every
    later frame by one (which pairs the views' frames wrongly from there on).

    Index = (number - first) / step, the step being the numbers' greatest common difference
    (every other frame saved is not a gap).  None where the indices would be the ranks
    anyway (no gap), where the numbers do not increase strictly, or where more numbers are
    missing than half the files present (a counter that does not count frames, e.g. a time
    stamp in the name).

    >>> frame_numbers([1, 2, 3, 5, 6])
    [0, 1, 2, 4, 5]
    >>> frame_numbers([10, 20, 30, 50]), frame_numbers([0, 1, 2]), frame_numbers([3, 900, 2000])
    ([0, 1, 2, 4], None, None)
    """
    import math
    nums = [int(v) for v in numbers]
    n = len(nums)
    if n < 2 or any(b <= a for a, b in zip(nums, nums[1:])):
        return None
    step = 0
    for a, b in zip(nums, nums[1:]):
        step = math.gcd(step, b - a)
    idx = [(v - nums[0]) // step for v in nums]
    missing = idx[-1] + 1 - n
    if missing == 0 or missing > max(1, n // 2):
        return None
    return idx


def _name_numbers(files: list[Path]) -> list[int] | None:
    """The frame counter of each file name, where every name is the same text around its
    last number (``frame_0001.png`` ... ``frame_0200.png``); else None."""
    parts = [_COUNTER.match(f.name) for f in files]
    if len(files) < 2 or any(m is None for m in parts):
        return None
    if len({(m.group(1), m.group(3)) for m in parts}) != 1:
        return None
    return [int(m.group(2)) for m in parts]


#: A frame interval counts as a whole number of frame periods (frames the recorder did not
#: store in between) within this fraction of a period (:func:`time_indices`, :func:`_frames_elapsed`).
_PERIOD_TOLERANCE = 0.25


def stamp_resolution(times) -> float:
    """The decimal step the time stamps are written to (s): the largest of 1, 0.1, ...,
    1e-6 s that every stamp (from the first) is a whole multiple of; 0 when none is.

    >>> stamp_resolution([0.0, 0.1, 0.3, 0.4]), stamp_resolution([0.0, 0.133333, 0.266667])
    (0.1, 1e-06)
    """
    t = np.asarray(times, float)
    t = t - t[0]
    for k in range(7):
        q = 10.0 ** -k
        # within 1 % of the step: times taken from stamps of the epoch (1.7e9 s) keep only
        # about 2e-7 s of their digits
        if np.all(np.abs(t / q - np.rint(t / q)) <= 0.01):
            return q
    return 0.0


def time_indices(times) -> list[int] | None:
    """Frame numbers from a source's own time stamps where they skip frames: each interval
    within a quarter of a whole number of the median interval, some of them two or more (a
    frame the recorder did not store); None where the stamps are missing, irregular or skip
    nothing (the frames are then counted), and where they are written too coarsely to tell
    (:func:`stamp_resolution` over a quarter of the interval: 7.5 frames/s stamped to 0.1 s
    has intervals of 0.1 and 0.2 s, which had read as a frame dropped every other frame).

    >>> time_indices([0.0, 0.5, 1.0, 2.0, 2.5])
    [0, 1, 2, 4, 5]
    >>> time_indices([0.0, 0.1, 0.3, 0.4, 0.5, 0.7, 0.8]) is None
    True
    """
    if times is None or len(times) < 3 or any(t is None for t in times):
        return None
    dt = np.diff(np.asarray(times, float))
    period = float(np.median(dt)) if len(dt) else 0.0
    if not np.isfinite(period) or period <= 0:
        return None
    if stamp_resolution(times) > _PERIOD_TOLERANCE * period:
        return None
    m = dt / period
    r = np.rint(m)
    if (r < 1).any() or (np.abs(m - r) > _PERIOD_TOLERANCE).any() or not (r >= 2).any():
        return None
    return [0, *np.cumsum(r).astype(int).tolist()]


def _frame_index_of(files: list[Path], series: "_Series | None") -> dict | None:
    """Each file's frame index where the source's counter has gaps (:func:`frame_numbers`),
    else None (frames are counted); a gap is logged."""
    if len(files) < 2 or any(f.suffix.lower() in VIDEO_SUFFIXES for f in files):
        return None
    nums = series.numbers if series is not None else _name_numbers(files)
    idx = frame_numbers(nums) if nums is not None else None
    if idx is None and series is not None:
        # numbered without a gap (or not at all), but the files' own times skip a frame
        idx = time_indices(series.times)
    if idx is None:
        return None
    have = set(idx)
    gone = [i for i in range(idx[-1] + 1) if i not in have]
    log.debug("%s: %d frame(s) missing from the numbering of its %d files (frame %s): their indices are left "
              "empty", files[0].parent, len(gone), len(files), ", ".join(str(i) for i in gone[:10])
                + (", ..." if len(gone) > 10 else ""))
    return dict(zip(files, idx))


def _source_files(source: str | os.PathLike) -> tuple[list[Path], _Series | None]:
    """The files of a source in order (:func:`list_image_files`) and, for a DICOM series, its
    :class:`_Series` (the files' own times); the series' headers are read once."""
    p = Path(str(source))
    if p.is_file():
        return [p], None
    files = _by_name(source)
    series = _dicom_series(files)
    return (list(series.files) if series is not None else files), series


# --- DICOM series --------------------------------------------------------------------------

class _Series(NamedTuple):
    """A folder (or glob) of single-frame DICOM files in acquisition order, with each
    file's time in s from the first (None where the files do not say)."""

    files: tuple
    times: tuple | None
    order: str          # what the order and the times were taken from, in words
    numbers: tuple | None = None   # the InstanceNumbers, in that order (None: ordered otherwise)


def _dicom_seconds(ds, date_kw: str, time_kw: str) -> float | None:
    """Seconds since an arbitrary epoch from a DICOM DA + TM pair, or from a DT attribute
    (``date_kw`` None: ``time_kw`` names a DT, ``YYYYMMDDHHMMSS.FFFFFF&ZZXX``)."""
    import datetime as dt
    raw_t = str(getattr(ds, time_kw, "") or "").strip()
    if not raw_t:
        return None
    if date_kw is None:                       # DT: date and time in one, an offset ignored
        m = re.fullmatch(r"(\d{8})(\d{2})?(\d{2})?(\d{2})?(\.\d{1,6})?([+-]\d{4})?", raw_t)
        if m is None:
            return None
        d, hh, mm, ss, frac = m.group(1), m.group(2) or "00", m.group(3) or "00", m.group(4) or "00", m.group(5)
    else:
        raw_d = str(getattr(ds, date_kw, "") or "").strip().replace(".", "")
        d = raw_d if re.fullmatch(r"\d{8}", raw_d) else "19700101"
        # TM: HHMMSS.FFFFFF (the old ACR-NEMA form HH:MM:SS.frac too)
        m = re.fullmatch(r"(\d{2}):?(\d{2})?:?(\d{2})?(\.\d{1,6})?", raw_t)
        if m is None:
            return None
        hh, mm, ss, frac = m.group(1), m.group(2) or "00", m.group(3) or "00", m.group(4)
    try:
        day = dt.datetime.strptime(d, "%Y%m%d")
    except ValueError:
        return None
    sec = int(hh) * 3600 + int(mm) * 60 + min(int(ss), 60) + (float(frac) if frac else 0.0)
    return (day - dt.datetime(1970, 1, 1)).total_seconds() + sec


def _dicom_series(files: list[Path]) -> _Series | None:
    """The acquisition order and times of a DICOM series: ``files`` when there are two or
    more and every one is DICOM (by suffix, or a DICOM preamble where there is no suffix),
    else None.  Headers only (no pixel data) are read.

    Order: by InstanceNumber when every file has a distinct one, else by acquisition time
    when every file has a distinct one, else by name (as given); InstanceNumbers that disagree
    with the acquisition times (AcquisitionDateTime or AcquisitionTime) give way to them, with
    a warning.  Times: the first of AcquisitionDateTime, AcquisitionDate + AcquisitionTime,
    ContentDate + ContentTime that every file has and that increases strictly in that order,
    relative to the first file; else each file's rank times a FrameTime (ms) that every file
    states alike; else None."""
    if len(files) < 2:
        return None
    dicom = [f.suffix.lower() in (".dcm", ".dicom") or (f.suffix == "" and _is_dicom(f)) for f in files]
    if not all(dicom):
        if sum(dicom) >= 2:
            # a preview or an export among a series' files: read by name, the UID-named files
            # had come in name order with the stray image as a frame, times lost, exit 0
            other = [f.name for f, d in zip(files, dicom) if not d]
            raise InputError(f"the folder holds {sum(dicom)} DICOM files and {len(other)} other image file(s) "
                             f"({', '.join(other[:3])}{', ...' if len(other) > 3 else ''}): one view's frames are "
                             "one kind of file; move the others out, or give a glob of the DICOM files",
                             path=files[0].parent)
        return None
    try:
        stats = [f.stat() for f in files]
        key = tuple((str(f), st.st_mtime_ns, st.st_size) for f, st in zip(files, stats))
    except OSError:
        key = None
    if key is not None and key in _SERIES_CACHE:
        return _SERIES_CACHE[key]
    series = _read_series(files)
    if key is not None:
        if len(_SERIES_CACHE) >= 4:
            _SERIES_CACHE.pop(next(iter(_SERIES_CACHE)))
        _SERIES_CACHE[key] = series
    return series


#: A DICOM series' time stamps, in the order they are taken (the acquisition's own first):
#: (name, date attribute or None for a DT, time attribute).
_SERIES_STAMPS = (("AcquisitionDateTime", None, "AcquisitionDateTime"),
                  ("AcquisitionDate/AcquisitionTime", "AcquisitionDate", "AcquisitionTime"),
                  ("ContentDate/ContentTime", "ContentDate", "ContentTime"))
_ACQUISITION_STAMPS = ("AcquisitionDateTime", "AcquisitionDate/AcquisitionTime")

#: The last few series read (:func:`_dicom_series`), keyed by each file's path, mtime and size:
#: a command lists a source more than once (count, first frame, frames).
_SERIES_CACHE: dict = {}


def _read_series(files: list[Path]) -> _Series | None:
    """:func:`_dicom_series` without the cache."""
    heads = []
    for f in files:
        ds = _dicom_dataset(f, pixels=False)
        if int(getattr(ds, "NumberOfFrames", 1) or 1) > 1:
            return None                     # multi-frame files: each holds its own clip
        heads.append(ds)
    n = len(files)
    # one series per source: files of two series in one folder (an earlier run, a localizer)
    # had been ordered together by time, the gap taken for 2,395 dropped frames, exit 0
    uids: dict[str, list[str]] = {}
    for f, ds in zip(files, heads):
        uid = getattr(ds, "SeriesInstanceUID", None)
        if uid:
            uids.setdefault(str(uid), []).append(f.name)
    # (a writer that gives every file its own series UID says nothing: only groups count)
    if sum(len(v) > 1 for v in uids.values()) > 1:
        parts = [f"{len(v)} file(s) of series ...{u[-12:]} ({', '.join(v[:3])}{', ...' if len(v) > 3 else ''})"
                 for u, v in sorted(uids.items(), key=lambda kv: -len(kv[1]))]
        raise InputError(f"the folder holds {len(uids)} DICOM series (SeriesInstanceUID): " + "; ".join(parts)
                         + ": give one series per view (a folder or a glob of its files)", path=files[0].parent)
    # the acquisition's clock first: ContentTime is when the image was made, which an export
    # or a reconstruction can set long after (files 8 ms apart for frames 0.5 s apart)
    stamps = {}
    for key, date_kw, time_kw in _SERIES_STAMPS:
        t = [_dicom_seconds(ds, date_kw, time_kw) for ds in heads]
        if all(v is not None for v in t) and len(set(t)) == n:
            stamps[key] = np.asarray(t, float)
    inst = []
    for ds in heads:
        try:
            inst.append(int(ds.InstanceNumber))
        except (AttributeError, TypeError, ValueError):
            inst = None
            break
    if inst is not None and 1 < len(set(inst)) < n:
        # numbers that repeat but are not all one: two runs numbered from 1 in one folder
        seen: dict[int, str] = {}
        twice = []
        for f, i in zip(files, inst):
            if i in seen:
                twice.append(f"{seen[i]} and {f.name} both {i}")
            seen.setdefault(i, f.name)
        raise InputError(f"{n - len(set(inst))} of the {n} DICOM files repeat another's InstanceNumber "
                         f"({'; '.join(twice[:3])}{'; ...' if len(twice) > 3 else ''}): two series or runs in one "
                         "folder?  Give one run per view", path=files[0].parent)
    if inst is not None and len(set(inst)) == n:
        order, how = np.argsort(inst, kind="stable"), "InstanceNumber"
        acq = next((k for k in _ACQUISITION_STAMPS if k in stamps), None)
        by_t = np.argsort(stamps[acq], kind="stable") if acq is not None else order
        if not np.array_equal(by_t, order):
            # numbers that disagree with the acquisition clock (a writer that numbers the files
            # as it exports them): the clock orders the frames; taken in the numbers' order the
            # frames had run backwards or shuffled and their times were dropped as not increasing
            moved = [files[i].name for i, j in zip(order, by_t) if i != j]
            log.warning("%s: the InstanceNumbers of %d of the %d DICOM files disagree with their %s (%s%s): "
                        "the files are taken in the order of their acquisition times", files[0].parent,
                        len(moved), n, acq, ", ".join(moved[:3]), ", ..." if len(moved) > 3 else "")
            order, how = by_t, f"{acq} (the InstanceNumbers disagree)"
    elif stamps:
        key = next(iter(stamps))
        order, how = np.argsort(stamps[key], kind="stable"), key
    else:
        order, how = np.arange(n), "file name"
    times = None
    for key, t in stamps.items():
        t = t[order]
        if np.all(np.diff(t) > 0):
            times, how = tuple(float(v) for v in t - t[0]), f"{how}; times from {key}"
            break
    if times is None:
        ft = set()
        for ds in heads:
            try:
                ft.add(float(ds.FrameTime))
            except (AttributeError, TypeError, ValueError):
                ft.add(None)
        if len(ft) == 1 and (v := ft.pop()) is not None and np.isfinite(v) and v > 0:
            # instance numbers count the frames (a gap is a frame missing); else the rank
            step = (np.asarray(inst)[order] - inst[order[0]]) if how == "InstanceNumber" else np.arange(n)
            times, how = tuple(float(i) * v / 1000.0 for i in step), f"{how}; times from FrameTime {v:g} ms"
    if times is not None:
        times, coarse = _regular_if_coarse(times)
        if coarse:
            how += f" (written to {coarse:g} s: a steady rate fitted)"
    numbers = tuple(int(inst[i]) for i in order) if how.startswith("InstanceNumber") else None
    return _Series(tuple(files[i] for i in order), times, how, numbers)


def _regular_if_coarse(times) -> tuple[tuple, float]:
    """Times written too coarsely for their frame interval (:func:`stamp_resolution` over a
    quarter of it: 7.5 frames/s stamped to 0.1 s) that a steady rate explains to within that
    resolution: the rate's times (the line on the frame ranks with the least maximum
    deviation, from its first frame), and the resolution; else the times as given, and 0."""
    t = np.asarray(times, float)
    if len(t) < 3:
        return tuple(times), 0.0
    q = stamp_resolution(t)
    dt = np.diff(t)
    if not (q > 0 and np.median(dt) > 0 and q > _PERIOD_TOLERANCE * float(np.median(dt))):
        return tuple(times), 0.0
    # the line nearest to every stamp at once (least maximum deviation, a small linear
    # program): a rounded stamp lies within half a step of its time, and the least-squares
    # line is pulled by the rounding's pattern (1.1 % off the rate on 30 frames at 7.5/s)
    from scipy.optimize import linprog
    k = np.arange(len(t), dtype=float)
    one = np.ones_like(k)
    A = np.vstack([np.column_stack([one, k, -one]), np.column_stack([-one, -k, -one])])
    res = linprog([0.0, 0.0, 1.0], A_ub=A, b_ub=np.concatenate([t, -t]),
                  bounds=[(None, None), (None, None), (0.0, None)], method="highs")
    if not res.success:
        return tuple(times), 0.0
    _, slope, worst = res.x
    if not (slope > 0 and worst <= q):
        return tuple(times), 0.0
    log.info("time stamps written to %g s for frames %.4g s apart: a steady rate of %.5g frames/s fitted",
             q, slope, 1.0 / slope)
    return tuple(float(v) for v in slope * k), q


# --- pixel conversion ---------------------------------------------------------------------

def _to_gray(a: np.ndarray, rgb_order: bool, channel: int | None, path, frame=None) -> np.ndarray:
    """Reduce (h, w), (h, w, 1), (h, w, 3) or (h, w, 4) to (h, w), keeping the dtype."""
    if a.ndim == 2:
        return a
    if a.ndim == 3 and a.shape[2] == 1:
        return a[:, :, 0]
    if a.ndim == 3 and a.shape[2] in (3, 4):
        rgb = a[:, :, :3] if rgb_order else a[:, :, 2::-1]
        if channel is not None:
            if channel not in (0, 1, 2):
                raise InputError(f"channel must be 0 (R), 1 (G) or 2 (B), got {channel}", path=path, frame=frame)
            return np.ascontiguousarray(rgb[:, :, channel])
        w = np.array([0.299, 0.587, 0.114])
        g = rgb.astype(np.float64) @ w
        if np.issubdtype(a.dtype, np.integer):
            info = np.iinfo(a.dtype)
            return np.clip(np.rint(g), info.min, info.max).astype(a.dtype)
        return g.astype(a.dtype)
    raise InputError(f"cannot read an image of shape {a.shape} as grayscale", path=path, frame=frame)


def _finish(a: np.ndarray, dtype, rgb_order: bool, channel, path, frame=None) -> np.ndarray:
    g = _to_gray(a, rgb_order, channel, path, frame)
    if g.size == 0:
        raise InputError("image is empty", path=path, frame=frame)
    if dtype is not None:
        g = g.astype(dtype, copy=False)
    return g


# --- single files --------------------------------------------------------------------------

#: Marker codes that may follow a scan's entropy-coded data (JPEG, ITU-T T.81 B.1.1.3, B.2.4):
#: tables, the next scan, DNL, restart interval, application data, comments, end of image.
_JPEG_AFTER_SCAN = frozenset([0xC4, 0xCC, 0xD9, 0xDA, 0xDB, 0xDC, 0xDD, 0xFE, *range(0xE0, 0xF0)])


def _check_jpeg(data: np.ndarray, path: Path) -> None:
    """The marker structure of a JPEG file (``data``: its bytes, uint8): libjpeg decodes a
    truncated or corrupted file with only a warning on stderr and returns an image that is
    grey or garbage past the damage.  Checked: start of image; every segment's length within
    the file; in each scan's entropy-coded data, every 0xFF byte stuffed (0xFF00), a fill
    byte, or a restart marker in sequence (RST0..7 cycling), up to a marker that may follow
    a scan; an end-of-image marker.  (Damage that keeps to valid byte patterns is not seen;
    overwritten or lost data almost always breaks them: what libjpeg warns of as "Corrupt
    JPEG data".)"""
    b = data
    n = int(b.size)
    if n < 4 or b[0] != 0xFF or b[1] != 0xD8:
        raise InputError("not a JPEG file (no start-of-image marker)", path=path)
    # every 0xFF and the byte after it, once for the whole file
    ff = np.flatnonzero(b[:-1] == 0xFF)
    nb = b[ff + 1]
    rst = (nb >= 0xD0) & (nb <= 0xD7)
    marker = ~((nb == 0x00) | (nb == 0xFF) | rst)
    mpos, mcode = ff[marker], nb[marker]
    rpos, rcode = ff[rst], nb[rst]
    pos = 2
    while True:
        if pos >= n or b[pos] != 0xFF:
            raise InputError(f"corrupt JPEG data (no marker at byte {pos})", path=path)
        while pos < n and b[pos] == 0xFF:
            pos += 1
        if pos >= n:
            break
        code = int(b[pos])
        pos += 1
        if code == 0xD9:
            return
        if 0xD0 <= code <= 0xD7 or code == 0x01:
            continue
        if pos + 2 > n:
            break
        seg_len = (int(b[pos]) << 8) | int(b[pos + 1])
        if seg_len < 2:
            raise InputError(f"corrupt JPEG data (marker 0xFF{code:02X} at byte {pos - 2} has length {seg_len})",
                             path=path)
        if pos + seg_len > n:
            break
        pos += seg_len
        if code != 0xDA:
            continue
        # a scan: its entropy-coded data run to the first 0xFF that is neither stuffed, fill
        # nor a restart marker
        i = int(np.searchsorted(mpos, pos))
        end = int(mpos[i]) if i < len(mpos) else n
        r0, r1 = np.searchsorted(rpos, [pos, end])
        if r1 > r0:
            got = rcode[r0:r1].astype(int) - 0xD0
            bad = np.flatnonzero(got != np.arange(r1 - r0) % 8)
            if len(bad):
                k = int(bad[0])
                raise InputError(f"corrupt JPEG data (restart marker RST{got[k]} at byte {int(rpos[r0 + k])} "
                                 f"where RST{k % 8} belongs)", path=path)
        if i >= len(mpos):
            break
        if int(mcode[i]) not in _JPEG_AFTER_SCAN:
            raise InputError(f"corrupt JPEG data (marker 0xFF{int(mcode[i]):02X} inside the image data at "
                             f"byte {end})", path=path)
        pos = end
    # the structure ran past the end: a file that still ends in EOI was damaged inside
    if b"\xff\xd9" in b[-64:].tobytes():
        raise InputError(f"corrupt JPEG data (a segment or the image data at byte {pos} runs past the end of "
                         f"the file)", path=path)
    raise InputError("JPEG file is truncated (no end-of-image marker)", path=path)


def _check_png_complete(data: np.ndarray, path: Path) -> None:
    """libpng prints its own error line for a truncated PNG; a complete one ends with IEND
    (``data``: the file's bytes).  (Content without the PNG signature is left to OpenCV,
    which decodes by content.)"""
    if data[:8].tobytes() == b"\x89PNG\r\n\x1a\n" and b"IEND" not in data[-12:].tobytes():
        raise InputError("PNG file is truncated (no IEND chunk at the end)", path=path)


def _gray_png(data: np.ndarray) -> np.ndarray | None:
    """An 8- or 16-bit grayscale PNG (an X-ray frame) decoded by imagecodecs' libpng, which
    takes about 5.0 ms for a 1024 x 1024 bench frame where ``cv2.imdecode`` takes 6.4 (the
    same pixels: PNG is lossless, ``tests/test_images.py``).  None for any other PNG (colour,
    palette, 1-4 bit, interlaced: OpenCV's conversions stay the reference) and where
    imagecodecs cannot decode it (OpenCV then says what is wrong)."""
    if data.size < 33 or data[:8].tobytes() != b"\x89PNG\r\n\x1a\n" or data[12:16].tobytes() != b"IHDR":
        return None
    if int(data[25]) != 0 or int(data[24]) not in (8, 16) or int(data[28]) != 0:
        return None                             # IHDR: colour type 0 (gray), 8/16 bit, not interlaced
    try:
        import imagecodecs
        a = imagecodecs.png_decode(data)
    except Exception:  # noqa: BLE001 - any failure falls back to OpenCV, which reports it
        return None
    return a if a.ndim == 2 else None


def _read_cv2(path: Path, hashes: dict | None = None) -> np.ndarray:
    """Decode an image file with OpenCV; with ``hashes``, the sha256 of the bytes decoded is
    stored under ``str(path)`` (the provenance hash without reading the file twice)."""
    import cv2
    data = np.fromfile(str(path), dtype=np.uint8)
    if data.size == 0:
        raise InputError("file is empty", path=path)
    if path.suffix.lower() == ".png":
        _check_png_complete(data, path)
    elif path.suffix.lower() in (".jpg", ".jpeg"):
        _check_jpeg(data, path)
    if hashes is not None:
        import hashlib
        hashes[str(path)] = hashlib.sha256(data).hexdigest()
    a = _gray_png(data)
    if a is not None:
        return a
    a = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if a is None:
        if data.size >= 132 and data[128:132].tobytes() == b"DICM":
            raise InputError(f"DICOM data in a file named {path.suffix}: give it the suffix .dcm (or none)",
                             path=path)
        raise InputError("cannot decode image (corrupt file or unsupported format)", path=path)
    return a


def _full_pages(tif) -> list[int]:
    """The indices of a TIFF's pages that are images of their own, not reduced-resolution
    previews (NewSubfileType bit 0: a thumbnail first page had been taken for frame 0, and the
    real frames refused as "image is 512x512 px, expected 128x128 like frame 0"); all of them
    where every page is so marked."""
    full = [k for k, pg in enumerate(tif.pages) if not (int(getattr(pg, "subfiletype", 0) or 0) & 1)]
    return full or list(range(len(tif.pages)))


def _tiff_pages(path: Path):
    import tifffile
    try:
        tif = tifffile.TiffFile(str(path))
    except Exception as e:  # tifffile raises several types for a broken header
        raise InputError(f"cannot read TIFF: {e}", path=path) from None
    return tif


#: Time units of OME-TIFF's DeltaTUnit and ImageJ's tunit, in seconds.
_TIME_UNITS = {"s": 1.0, "sec": 1.0, "second": 1.0, "seconds": 1.0, "ms": 1e-3, "msec": 1e-3, "us": 1e-6,
               "µs": 1e-6, "\u03bcs": 1e-6, "ns": 1e-9, "min": 60.0, "h": 3600.0, "hour": 3600.0}


def _tiff_times(tif, n: int) -> list[float | None]:
    """Each page's time in s from the stack's own metadata: OME-TIFF's Plane DeltaT (one per
    page, a single channel and focal plane, in DeltaTUnit), else ImageJ's frame interval
    (``finterval``, in ``tunit``, seconds by default) for a stack of frames only; relative to
    the first page and increasing, else None for every page."""
    none = [None] * n
    if n < 2:
        return none
    try:
        if tif.is_ome and tif.ome_metadata:
            import xml.etree.ElementTree as ET
            root = ET.fromstring(tif.ome_metadata)
            pix = next((e for e in root.iter() if e.tag.endswith("}Pixels") or e.tag == "Pixels"), None)
            if pix is not None and int(pix.get("SizeC", 1)) == 1 and int(pix.get("SizeZ", 1)) == 1:
                planes = [e for e in pix if e.tag.endswith("Plane") and e.get("DeltaT") is not None]
                if len(planes) == n:
                    t = np.array([float(e.get("DeltaT")) * _TIME_UNITS.get(e.get("DeltaTUnit", "s"), np.nan)
                                  for e in planes])
                    if np.all(np.isfinite(t)) and np.all(np.diff(t) > 0):
                        return [float(v - t[0]) for v in t]
        md = tif.imagej_metadata if tif.is_imagej else None
        if md and md.get("finterval"):
            dt = float(md["finterval"]) * _TIME_UNITS.get(str(md.get("tunit", "sec")).strip().lower(), np.nan)
            only_frames = int(md.get("channels", 1) or 1) == 1 and int(md.get("slices", 1) or 1) == 1
            if only_frames and np.isfinite(dt) and dt > 0:
                return [k * dt for k in range(n)]
    except (ValueError, TypeError, AttributeError, KeyError) as e:   # malformed metadata: no times
        log.info("TIFF time metadata not read (%s)", e)
    return none


class _TiffErrors(logging.Handler):
    """Collects what tifffile logs at ERROR while it reads a file: a damaged page list (an
    offset past the end of a truncated stack, a corrupt tag list) is logged, not raised,
    and the pages after it silently dropped.  While installed, tifffile's records go here
    only."""

    def __init__(self):
        super().__init__(logging.ERROR)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage())

    def __enter__(self):
        self._log = logging.getLogger("tifffile")
        self._propagate = self._log.propagate
        self._log.addHandler(self)
        self._log.propagate = False
        return self

    def __exit__(self, *exc):
        self._log.removeHandler(self)
        self._log.propagate = self._propagate
        return False

    def check(self, path: Path, frame=None) -> None:
        if self.messages:
            msg = re.sub(r"^<tifffile\.\w+[^>]*>\s*", "", self.messages[0])
            raise InputError(f"TIFF file is damaged or truncated ({msg})", path=path, frame=frame)


def _tiff_page_array(page, path: Path, k: int | None) -> np.ndarray:
    try:
        a = page.asarray()
    except Exception as e:  # a damaged strip or an unsupported compression
        raise InputError(f"cannot decode TIFF page: {e}", path=path, frame=k) from None
    if a.ndim == 3 and int(getattr(page, "planarconfig", 1)) == 2:
        a = np.moveaxis(a, 0, -1)  # separate colour planes -> (h, w, samples)
    return a


def _dicom_dataset(path: Path, *, pixels: bool = True):
    """The DICOM file's dataset (``pixels=False``: its header only); a file pydicom cannot
    read is an InputError naming it."""
    import pydicom
    try:
        return pydicom.dcmread(str(path), stop_before_pixels=not pixels)
    except Exception as e:  # pydicom raises InvalidDicomError, OSError, ValueError...
        raise InputError(f"cannot read DICOM: {e}", path=path) from None


def _dicom_frames(ds, path: Path) -> Iterator[np.ndarray]:
    """The file's frames one at a time, (h, w[, samples]), MONOCHROME1 inverted; ``ds`` its
    header.  Decoded frame by frame (:func:`pydicom.pixels.iter_pixels`: a multi-frame file's
    pixel data is never held whole), compressed transfer syntaxes included (RLE, JPEG
    baseline and lossless, JPEG-LS, JPEG 2000: pydicom's own decoders and pylibjpeg's)."""
    from pydicom.pixels import iter_pixels
    spp = int(getattr(ds, "SamplesPerPixel", 1) or 1)
    mono1 = str(getattr(ds, "PhotometricInterpretation", "")).upper() == "MONOCHROME1"
    n = int(getattr(ds, "NumberOfFrames", 1) or 1)
    k = 0
    try:
        for a in iter_pixels(str(path)):
            if k >= n:
                raise InputError(f"DICOM pixel data holds more frames than NumberOfFrames ({n})", path=path)
            if a.ndim != 2 + (spp > 1):
                raise InputError(f"unexpected DICOM frame shape {a.shape}", path=path, frame=k if n > 1 else None)
            yield _monochrome1(a, ds) if mono1 else a
            k += 1
    except InputError:
        raise
    except Exception as e:  # missing or short pixel data, or a transfer syntax without a decoder
        short = f" (the pixel data ends before frame {k} of the {n} NumberOfFrames states?)" if 0 < k < n else ""
        raise InputError(f"cannot decode DICOM pixel data{short}: {e}", path=path,
                         frame=k if n > 1 else None) from None
    if k < n:
        raise InputError(f"DICOM pixel data holds {k} frame(s), NumberOfFrames says {n}", path=path)


def _monochrome1(a: np.ndarray, ds) -> np.ndarray:
    """A MONOCHROME1 frame (low values shown bright) in the MONOCHROME2 convention."""
    if np.issubdtype(a.dtype, np.integer):
        bits = int(getattr(ds, "BitsStored", np.iinfo(a.dtype).bits))
        top = (1 << bits) - 1 if np.iinfo(a.dtype).min == 0 else int(a.max()) + int(a.min())
        return (top - a.astype(np.int64)).astype(a.dtype)
    return a.max() + a.min() - a


def _dicom_frame_times(ds, n: int) -> list[float | None]:
    """Frame times in s from FrameTimeVector (ms increments), FrameTime (ms) or CineRate
    (frames/s); else, in an
    enhanced multi-frame file (Enhanced XA, XRF), from each frame's FrameContentSequence
    (FrameAcquisitionDateTime, else FrameReferenceDateTime) where every frame has one and they
    increase, relative to the first; else None.  A single-frame file has no time of its own
    (a series' times come from :func:`_dicom_series`)."""
    if n < 2:
        return [None] * n
    vec = getattr(ds, "FrameTimeVector", None)
    if vec is not None and len(vec) == n:
        v = np.asarray(vec, dtype=float)
        if n >= 4 and v[0] == 0 and np.all(np.diff(v[1:]) > 0):
            d = np.diff(v)
            if np.ptp(d) <= 0.01 * np.median(d):
                # increments that grow by one period each frame: the vector holds each frame's
                # time, not the increments the standard asks for (such writers exist; read as
                # increments the clip ran 0, 0.25, 0.75, 1.5 ... 108.75 s for 7.25)
                log.warning("%s: FrameTimeVector holds times (0, %g, %g, ... ms), not the increments DICOM "
                            "asks for: read as each frame's time", getattr(ds, "filename", "DICOM file"), v[1], v[2])
                return list(v / 1000.0)
        return list(np.cumsum(v) / 1000.0)
    ft = getattr(ds, "FrameTime", None)
    if ft is not None and float(ft) > 0:
        return [i * float(ft) / 1000.0 for i in range(n)]
    rate = getattr(ds, "CineRate", None)          # the Cine module's frames per second, without FrameTime
    try:
        if rate is not None and float(rate) > 0:
            return [i / float(rate) for i in range(n)]
    except (TypeError, ValueError):
        pass
    per = getattr(ds, "PerFrameFunctionalGroupsSequence", None)
    if per is not None and len(per) == n:
        for kw in ("FrameAcquisitionDateTime", "FrameReferenceDateTime"):
            t = []
            for item in per:
                fc = getattr(item, "FrameContentSequence", None)
                t.append(_dicom_seconds(fc[0], None, kw) if fc else None)
            if all(v is not None for v in t) and np.all(np.diff(t) > 0):
                return [float(v - t[0]) for v in t]
    return [None] * n


def read_image(path: str | os.PathLike, *, dtype=None, channel: int | None = None) -> np.ndarray:
    """Read one still image as a 2-D grayscale array (native dtype unless ``dtype``).

    PNG, JPEG, BMP through OpenCV; TIFF through tifffile (first page); DICOM through pydicom
    (first frame).  Raises :class:`InputError` naming the file when it is missing, empty,
    truncated or undecodable.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError("no such file", path=p)
    suf = p.suffix.lower()
    if suf in (".tif", ".tiff"):
        tif = _tiff_pages(p)
        with tif, _TiffErrors() as errors:
            if not tif.pages:
                errors.check(p)
                raise InputError("TIFF file has no pages", path=p)
            a = _tiff_page_array(tif.pages[_full_pages(tif)[0]], p, None)
            errors.check(p)
        return _finish(a, dtype, True, channel, p)
    if _is_dicom(p):
        ds = _dicom_dataset(p, pixels=False)
        a = next(iter(_dicom_frames(ds, p)), None)
        if a is None:
            raise InputError("DICOM file has no frame", path=p)
        return _finish(a, dtype, True, channel, p)
    return _finish(_read_cv2(p), dtype, False, channel, p)


# --- sequences -----------------------------------------------------------------------------

def _hash_into(hashes: dict | None, path: Path) -> None:
    """Store the file's sha256 in ``hashes`` (if given) under ``str(path)``: for the formats
    whose readers open the file themselves (videos, TIFF, DICOM)."""
    if hashes is not None:
        from ..provenance import sha256_file
        hashes[str(path)] = sha256_file(path)


def _iter_file(path: Path, dtype, channel, hashes: dict | None = None
               ) -> Iterator[tuple[str, np.ndarray, float | None, int]]:
    """Frames inside one file: (name, gray image, time_s, frame index within the file: its
    position, or where a multi-frame DICOM's frame times skip a period, its number by time,
    :func:`time_indices`); with ``hashes``, the file's sha256 is stored in it under
    ``str(path)``."""
    suf = path.suffix.lower()
    if suf in VIDEO_SUFFIXES:
        _hash_into(hashes, path)
        yield from _iter_video(path, dtype, channel)
    elif suf in (".tif", ".tiff"):
        _hash_into(hashes, path)
        tif = _tiff_pages(path)
        with tif, _TiffErrors() as errors:
            n = len(tif.pages)                  # indexes every page: a damaged page list is logged
            errors.check(path)
            if n == 0:
                raise InputError("TIFF file has no pages (damaged or truncated)", path=path)
            # a stack's own times (OME DeltaT, ImageJ frame interval); a gap of whole periods
            # numbers the pages after it by time, as a DICOM clip's
            all_times = _tiff_times(tif, n)
            pages = _full_pages(tif)
            if len(pages) < n:
                log.info("%s: %d reduced-resolution page(s) (previews) left out", path, n - len(pages))
            times = [all_times[k] for k in pages]
            ks = time_indices(times) or range(len(pages))
            for j, k in enumerate(pages):
                # the page's index within the file names it in a stack; a file of one page
                # is named by the file alone (in a folder its frame is not page 0)
                a = _tiff_page_array(tif.pages[k], path, k if n > 1 else None)
                errors.check(path, k if n > 1 else None)
                name = path.name if n == 1 else f"{path.name}#{k}"
                yield name, _finish(a, dtype, True, channel, path, k if n > 1 else None), times[j], ks[j]
    elif _is_dicom(path):
        _hash_into(hashes, path)
        ds = _dicom_dataset(path, pixels=False)
        n = int(getattr(ds, "NumberOfFrames", 1) or 1)
        times = _dicom_frame_times(ds, n)
        # a FrameTimeVector that skips a frame period: the frames after keep their times' numbers
        ks = time_indices(times) or range(n)
        for k, a in enumerate(_dicom_frames(ds, path)):
            name = path.name if n == 1 else f"{path.name}#{k}"
            yield name, _finish(a, dtype, True, channel, path, k if n > 1 else None), times[k], ks[k]
    else:
        yield path.name, _finish(_read_cv2(path, hashes), dtype, False, channel, path), None, 0


def _frames_elapsed(t: float | None, prev_t: float | None, ivals: list[float]) -> int:
    """Frame periods between a video frame at ``t`` and the one before at ``prev_t`` (s): 1,
    unless the interval is a whole number (2 or more) of the frame period, within a quarter
    of one, as where a capture dropped frames and the container kept their time; the period
    is the median of the intervals seen so far (``ivals``, appended to; at least 3), so a
    stream is numbered as it is read.  Without times: 1."""
    if t is None or prev_t is None or not t > prev_t:
        return 1
    dt = t - prev_t
    step = 1
    if len(ivals) >= 3:
        per = float(np.median(ivals[-64:]))
        r = dt / per if per > 0 else 1.0
        m = int(round(r))
        if m >= 2 and abs(r - m) <= _PERIOD_TOLERANCE:
            step = m
    ivals.append(dt / step)
    return step


def _open_video(path: Path):
    """``cv2.VideoCapture`` on ``path``; a stream of 16-bit gray samples (FFV1 or raw
    ``gray16le``, as a lossless X-ray archive holds them) is opened without OpenCV's BGR
    conversion, which would cut it to 8 bits."""
    import cv2
    cap = cv2.VideoCapture(str(path))
    if cap.isOpened():
        v = int(cap.get(cv2.CAP_PROP_CODEC_PIXEL_FORMAT) or 0)
        if bytes((v >> (8 * i)) & 255 for i in range(4)) == b"Y1\x00\x10":      # FFmpeg's gray16le tag
            cap.release()
            level = cv2.utils.logging.getLogLevel()
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)   # "BGR conversion turned OFF"
            try:
                cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG, [cv2.CAP_PROP_CONVERT_RGB, 0])
            finally:
                cv2.utils.logging.setLogLevel(level)
    return cap


def _iter_video(path: Path, dtype, channel):
    import cv2
    cap = _open_video(path)
    try:
        if not cap.isOpened():
            raise InputError("cannot open video (corrupt file or unsupported codec)", path=path)
        stated = cap.get(cv2.CAP_PROP_FRAME_COUNT)
        stated = int(stated) if stated is not None and np.isfinite(stated) and stated > 0 else None
        k = 0
        idx = 0                 # the frame's number: its position, or past a gap in its times, by time
        prev_t = None
        ivals: list[float] = []
        while True:
            ok, a = cap.read()
            if not ok or a is None:
                # a container's frame count can be an estimate (duration x rate): a frame
                # short is tolerated with a warning; more is a truncated or damaged file
                if stated is not None and k < stated:
                    short = stated - k
                    # a count that is the container's estimate (duration x a nominal rate, as
                    # Matroska's) overstates a stream whose frames are further apart: its
                    # frames' times reaching the stated duration say it is complete
                    fps = cap.get(cv2.CAP_PROP_FPS)
                    per = float(np.median(ivals)) if ivals else None
                    whole = (per is not None and prev_t is not None and fps and np.isfinite(fps) and fps > 0
                             and prev_t + 2.0 * per >= stated / fps)
                    if short > max(1, stated // 100) and not whole:
                        raise InputError(f"video ends after {k} of the {stated} frames its header states "
                                         f"(truncated or damaged)", path=path, frame=k)
                    (log.info if whole else log.warning)(
                        "%s: %d frame(s) decoded, the header states %d%s", path, k, stated,
                        " (an estimate: the frames' times reach its duration)" if whole else "")
                break
            t_ms = cap.get(cv2.CAP_PROP_POS_MSEC)
            t = float(t_ms) / 1000.0 if t_ms is not None and np.isfinite(t_ms) and (k == 0 or t_ms > 0) else None
            if k > 0:
                idx += _frames_elapsed(t, prev_t, ivals)
            yield f"{path.name}#{k}", _finish(a, dtype, False, channel, path, k), t, idx
            prev_t = t
            k += 1
        if k == 0:
            raise InputError("video holds no decodable frame", path=path)
    finally:
        cap.release()


#: Suffixes of files that hold exactly one frame, decoded by OpenCV: a folder of them can be
#: decoded by several threads at once (:func:`iter_frames` ``workers``).
_ONE_FRAME_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm")


def _files_in_order(files: list[Path], dtype, channel, hashes: dict | None, workers: int):
    """``(file, (name, image, time_s, k))`` for every frame of ``files`` in order; single-frame
    image files are decoded ``workers`` at a time on a thread pool (OpenCV's decoders and file
    reads release the GIL), at most ``2 workers`` files ahead of the one being yielded, so
    memory stays flat.  An error is raised when its file's turn comes, as in a sequential read."""
    if workers <= 1 or len(files) < 2 or any(f.suffix.lower() not in _ONE_FRAME_SUFFIXES for f in files):
        for f in files:
            for item in _iter_file(f, dtype, channel, hashes):
                yield f, item
        return
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    def one(f: Path):
        return list(_iter_file(f, dtype, channel, hashes))

    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="bsipipe-decode") as pool:
        pending: deque = deque()
        it = iter(files)
        try:
            for f in it:
                pending.append((f, pool.submit(one, f)))
                if len(pending) >= 2 * workers:
                    break
            while pending:
                f, fut = pending.popleft()
                nxt = next(it, None)
                if nxt is not None:
                    pending.append((nxt, pool.submit(one, nxt)))
                for item in fut.result():
                    yield f, item
        finally:
            for _, fut in pending:
                fut.cancel()


def iter_frames(source: str | os.PathLike, *, dtype=None, channel: int | None = None,
                check_size: bool = True, hashes: dict | None = None, workers: int = 1) -> Iterator[Frame]:
    """Stream the frames of a source, one :class:`Frame` at a time.

    ``source`` is a folder of image files or a glob (sorted by name, see
    :func:`natural_key`; a DICOM series is such a folder), a multi-page TIFF, a
    multi-frame DICOM, a video (AVI, MP4, ...), or a single image (one frame).  Frame
    indices run over the whole source; where the files' names (or a DICOM series'
    InstanceNumbers) count the frames and skip some numbers, a skipped number's index is
    left out (:func:`frame_numbers`).  With ``check_size`` every frame must have the
    size and the pixel type (bit depth) of the first; a difference is an InputError naming the
    file and frame.  ``hashes`` (a dict) receives the sha256 of every file read, keyed by
    ``str(path)`` as :func:`bsipipe.provenance.input_hashes` keys them: an image file's from
    the bytes it was decoded from, so a command's provenance need not read its frames again.
    ``workers`` > 1 decodes a folder (or glob) of single-frame image files that many at a
    time, a few files ahead (same frames, same order, same errors).  A DICOM series comes in
    InstanceNumber order, each frame timed by its file's acquisition time (or FrameTime),
    see :func:`_dicom_series`.
    """
    files, series = _source_files(source)
    times = dict(zip(series.files, series.times)) if series is not None and series.times is not None else None
    if series is not None:
        log.debug("%s: DICOM series of %d files, in the order of %s", source, len(files), series.order)
    numbered = _frame_index_of(files, series)
    shape0 = None
    first = first_path = None
    index = base = 0
    n_files = 0
    prev_f = None
    # several files each with its own clock from 0 (clips of a run, video chunks): played one
    # after another, each file's times start one frame period after the last frame before it
    # (they had restarted at 0 in each file, and every loop effect failed on times that did
    # not increase)
    joined = 0.0                # added to the current file's own times
    last_t = own_prev = None    # the last frame's time (joined), the current file's last own time
    ivals: list[float] = []     # frame intervals within files
    n_joined = 0
    for f, (name, img, t, k) in _files_in_order(files, dtype, channel, hashes, int(workers)):
        new_file = f != prev_f
        if new_file:
            n_files, prev_f = n_files + 1, f
        if times is None and t is not None:
            if new_file:
                if last_t is not None:
                    if not ivals:
                        raise InputError("the files of this source each hold their own frame times from 0, and the "
                                         f"one before {Path(f).name} has a single frame: the files cannot be put one "
                                         "after another in time; give --fps, or one file per view", path=f)
                    joined = last_t + float(np.median(ivals[-64:])) - t
                    n_joined += 1
                    if n_joined == 1:
                        log.warning("%s: its files each hold their own frame times from 0 (%s, %s, ...): they are "
                                    "taken one after another, each starting one frame period after the last frame "
                                    "of the file before (a pause between the files is not known)",
                                    source, Path(files[0]).name, Path(f).name)
            elif own_prev is not None and t > own_prev:
                ivals.append((t - own_prev) / max(1, k - own_k))
            own_prev, own_k = t, k
            t = t + joined
            last_t = t
        if k == 0:
            # a frame missing from the numbering (or skipped by a file's own times) keeps its index
            base = max(index, numbered[f]) if numbered is not None else index
        index = base + k
        if check_size:
            if shape0 is None:
                shape0, dtype0, first, first_path = img.shape, img.dtype, name, f
            elif img.shape != shape0:
                h, w = img.shape
                if n_files == 2 and len(files) >= 3 and _header_size(files[2]) == (w, h):
                    # the first file is the odd one (a thumbnail or preview that sorts first)
                    raise InputError(f"image is {shape0[1]}x{shape0[0]} px, the files after it {w}x{h} px "
                                     f"({Path(f).name}, {Path(files[2]).name}): a thumbnail or another image among "
                                     "the frames? Move it out of the folder", path=first_path, frame=0)
                raise InputError(
                    f"image is {w}x{h} px, expected {shape0[1]}x{shape0[0]} px like {first}",
                    path=f, frame=index)
            elif img.dtype != dtype0:  # e.g. one 16-bit export among 8-bit frames: grey levels differ
                raise InputError(f"image has {_depth(img.dtype)} pixels, expected {_depth(dtype0)} like {first}",
                                 path=f, frame=index)
        yield Frame(index, name, img, times[f] if times is not None else t)
        index += 1


def _header_size(path) -> tuple[int, int] | None:
    """An image file's (width, height) from its header (Pillow reads no pixels), None where
    Pillow cannot tell."""
    try:
        from PIL import Image
        with Image.open(path) as im:
            return tuple(int(v) for v in im.size)
    except Exception:  # noqa: BLE001 - only a hint for a message
        return None


def _depth(dtype) -> str:
    """``8-bit``, ``16-bit``, ``32-bit float``: a pixel type in words."""
    dt = np.dtype(dtype)
    return f"{8 * dt.itemsize}-bit" + (" float" if dt.kind == "f" else "")


#: Video codecs (FourCC, upper case) that keep every pixel: raw frames, FFV1, HuffYUV, Lagarith,
#: PNG-in-AVI and the like; any other codec of a video is taken as lossy.
LOSSLESS_FOURCC = frozenset({"FFV1", "HFYU", "FFVH", "LAGS", "PNG ", "MPNG", "Y800", "GREY", "Y8  ", "Y16 ", "RGBA",
                             "RAW ", "DIB ", "\x00\x00\x00\x00", "UYVY", "YUY2", "I420", "IYUV", "YV12"})
#: DICOM transfer syntaxes whose pixel data are lossily compressed (JPEG baseline/extended,
#: JPEG-LS near-lossless, JPEG 2000 lossy, MPEG-2/4, HEVC).
_DICOM_LOSSY_SYNTAXES = ("1.2.840.10008.1.2.4.50", "1.2.840.10008.1.2.4.51", "1.2.840.10008.1.2.4.81",
                         "1.2.840.10008.1.2.4.91", "1.2.840.10008.1.2.4.100", "1.2.840.10008.1.2.4.101",
                         "1.2.840.10008.1.2.4.102", "1.2.840.10008.1.2.4.103", "1.2.840.10008.1.2.4.104",
                         "1.2.840.10008.1.2.4.105", "1.2.840.10008.1.2.4.106", "1.2.840.10008.1.2.4.107",
                         "1.2.840.10008.1.2.4.108")


def lossy_compression(source: str | os.PathLike) -> str | None:
    """How the frames of a source were lossily compressed, in words (``"JPEG files"``,
    ``"video codec FMP4"`` (OpenCV's mp4v), ``"DICOM transfer syntax 1.2.840.10008.1.2.4.50"``), or None for
    lossless sources (PNG, TIFF, BMP, a lossless or raw video codec, uncompressed DICOM).
    A lossy codec removes the fine-grained pixel noise the detector measures its threshold
    and each marker's SNR from, and smears small beads.  Only the first file is examined (a
    source's files share their format)."""
    files, _ = _source_files(source)
    if not files:
        return None
    f = files[0]
    suf = f.suffix.lower()
    if suf in (".jpg", ".jpeg"):
        return "JPEG files"
    if suf in VIDEO_SUFFIXES:
        import cv2
        cap = cv2.VideoCapture(str(f))
        try:
            code = int(cap.get(cv2.CAP_PROP_FOURCC)) if cap.isOpened() else 0
        finally:
            cap.release()
        fourcc = "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))
        if fourcc.upper() in LOSSLESS_FOURCC:
            return None
        shown = fourcc.strip("\x00 ") or f"0x{code:08x}"
        return f"video codec {shown}"
    if _is_dicom(f):
        ds = _dicom_dataset(f, pixels=False)
        ts = str(getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", "") or "")
        if ts in _DICOM_LOSSY_SYNTAXES or str(getattr(ds, "LossyImageCompression", "")).strip() == "01":
            return f"DICOM transfer syntax {ts}" if ts else "DICOM marked lossy (LossyImageCompression 01)"
    return None


def count_frames(source: str | os.PathLike) -> int:
    """Number of frames in a source without decoding pixels where the format allows."""
    files, _ = _source_files(source)
    n = 0
    for f in files:
        suf = f.suffix.lower()
        if suf in VIDEO_SUFFIXES:
            import cv2
            cap = cv2.VideoCapture(str(f))
            try:
                if not cap.isOpened():
                    raise InputError("cannot open video (corrupt file or unsupported codec)", path=f)
                c = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            finally:
                cap.release()
            n += c if c > 0 else sum(1 for _ in _iter_video(f, None, None))
        elif suf in (".tif", ".tiff"):
            tif = _tiff_pages(f)
            with tif, _TiffErrors() as errors:
                n += len(_full_pages(tif))
                errors.check(f)
        elif _is_dicom(f):
            ds = _dicom_dataset(f, pixels=False)
            n += int(getattr(ds, "NumberOfFrames", 1) or 1)
        else:
            n += 1
    return n


def decode_workers() -> int:
    """Threads that decode a folder of frames for ``track``: one per usable core, at most 4.
    Decoding a 1024 x 1024 PNG takes longer than tracking it; with the tracker on one core,
    the others decode.  On 2 cores, 2 x 2,000 frames of the bench twin, two readers beat
    three (one more than the cores, as before) in 6 of 7 interleaved pairs of runs, by about
    1 s of 25 s wall and 1.5 s of 38 s CPU: a third reader only contends with the tracker;
    one reader is 4-5 s slower in wall time."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    return max(1, min(4, cores))


def prefetched(frames, depth: int = 2):
    """The frames of an iterator, decoded ``depth`` ahead on a background thread.

    Decoding (``cv2.imdecode``, file reads) releases the GIL, so the next frames decode while
    this one is tracked: on two or more cores the command takes about the longer of decoding
    and tracking instead of their sum.  At most ``depth`` frames wait in the queue (memory
    stays flat); an error in the source is raised here, in order, when its frame is due; a
    consumer that stops early stops the thread."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def work():
        try:
            for fr in frames:
                if not put(("frame", fr)):
                    return
            put(("end", None))
        except BaseException as e:  # noqa: BLE001 - handed to the consumer, raised there
            put(("error", e))

    t = threading.Thread(target=work, name="bsipipe-decode", daemon=True)
    t.start()
    try:
        while True:
            kind, item = q.get()
            if kind == "frame":
                yield item
            elif kind == "error":
                raise item
            else:
                return
    finally:
        stop.set()
        t.join(timeout=5.0)
