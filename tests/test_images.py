"""Image and frame readers: every format written here into tmp_path, read back exactly."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from bsipipe.errors import InputError
from bsipipe.io.images import count_frames, iter_frames, lossy_compression, read_image


def _ramp(h=24, w=32, dtype=np.uint8, seed=0):
    rng = np.random.default_rng(seed)
    top = np.iinfo(dtype).max
    return rng.integers(0, top, size=(h, w), dtype=dtype, endpoint=True)


def _new_dicom(sop_class):
    """An empty dataset with its file meta (explicit VR little endian) for ``sop_class``."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    return ds


def _write_dicom(path, frames: np.ndarray, photometric="MONOCHROME2", frame_time_ms=None, frame_time_vector=None):
    """A minimal valid DICOM (Secondary Capture) holding ``frames`` (n, h, w) or (h, w)."""
    from pydicom.uid import SecondaryCaptureImageStorage

    ds = _new_dicom(SecondaryCaptureImageStorage)
    ds.SOPClassUID = SecondaryCaptureImageStorage
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID
    ds.Modality = "RF"
    ds.set_pixel_data(frames, photometric_interpretation=photometric,
                      bits_stored=8 * frames.dtype.itemsize)
    if frame_time_ms is not None:
        ds.FrameTime = frame_time_ms
    if frame_time_vector is not None:
        ds.FrameTimeVector = list(frame_time_vector)
    ds.save_as(str(path), enforce_file_format=True)


def test_png_8_and_16_bit_roundtrip(tmp_path):
    for dtype in (np.uint8, np.uint16):
        a = _ramp(dtype=dtype)
        p = tmp_path / f"x_{np.dtype(dtype).name}.png"
        cv2.imwrite(str(p), a)
        b = read_image(p)
        assert b.dtype == dtype and np.array_equal(a, b)
        assert read_image(p, dtype=np.float32).dtype == np.float32


def test_gray_png_decoder_gives_opencvs_pixels(tmp_path):
    """8- and 16-bit grayscale PNGs (X-ray frames) are decoded by imagecodecs' libpng, about
    a fifth faster than cv2.imdecode: the same pixels as OpenCV's, whatever the compression
    level or filter, on a real frame too; colour, palette, gray+alpha, 1-bit and interlaced
    PNGs are left to OpenCV; a gray PNG imagecodecs cannot decode (a damaged chunk) still ends
    in OpenCV's error naming the file."""
    from bsipipe.io.images import _gray_png
    rng = np.random.default_rng(5)
    real = cv2.imread(str(Path(__file__).parent / "data" / "real" / "xray_frame_deepxromm" / "sample_frame.jpg"),
                      cv2.IMREAD_GRAYSCALE)
    imgs = [real, rng.integers(0, 256, (37, 53)).astype(np.uint8), rng.integers(0, 65536, (40, 31)).astype(np.uint16),
            (real.astype(np.uint16) * 257)]
    for k, a in enumerate(imgs):
        for lvl in (0, 1, 9):
            for strategy in (cv2.IMWRITE_PNG_STRATEGY_DEFAULT, cv2.IMWRITE_PNG_STRATEGY_FILTERED):
                ok, buf = cv2.imencode(".png", a, [cv2.IMWRITE_PNG_COMPRESSION, lvl, cv2.IMWRITE_PNG_STRATEGY, strategy])
                data = np.frombuffer(buf.tobytes(), np.uint8)
                b = _gray_png(data)
                assert b is not None and b.dtype == a.dtype and np.array_equal(b, a), (k, lvl)
                assert np.array_equal(b, cv2.imdecode(data, cv2.IMREAD_UNCHANGED))
    import imagecodecs      # imagecodecs' own encoder too
    data = np.frombuffer(imagecodecs.png_encode(imgs[1]), np.uint8)
    assert np.array_equal(_gray_png(data), imgs[1])
    inter = data.copy()
    inter[28] = 1                                 # an interlaced header: left to OpenCV
    assert _gray_png(inter) is None
    ok, buf = cv2.imencode(".png", np.dstack([imgs[1]] * 3))
    assert _gray_png(np.frombuffer(buf.tobytes(), np.uint8)) is None
    assert _gray_png(np.frombuffer(imagecodecs.png_encode(np.dstack([imgs[1], imgs[1]])), np.uint8)) is None
    ok, buf = cv2.imencode(".png", (imgs[1] > 128).astype(np.uint8), [cv2.IMWRITE_PNG_BILEVEL, 1])
    assert _gray_png(np.frombuffer(buf.tobytes(), np.uint8)) is None
    ok, buf = cv2.imencode(".png", imgs[1])
    bad = bytearray(buf.tobytes())
    i = bad.index(b"IDAT") + 8
    bad[i:i + 20] = bytes(20)                     # the compressed data overwritten: no zlib stream
    assert _gray_png(np.frombuffer(bytes(bad), np.uint8)) is None
    (tmp_path / "bad.png").write_bytes(bytes(bad))
    with pytest.raises(InputError, match="bad.png"):
        read_image(tmp_path / "bad.png")


def test_tiff_8_16_float_and_multipage(tmp_path):
    for dtype in (np.uint8, np.uint16):
        a = _ramp(dtype=dtype)
        tifffile.imwrite(tmp_path / f"a_{np.dtype(dtype).name}.tif", a)
        assert np.array_equal(read_image(tmp_path / f"a_{np.dtype(dtype).name}.tif"), a)
    f = np.random.default_rng(1).normal(size=(10, 12)).astype(np.float32)
    tifffile.imwrite(tmp_path / "f.tiff", f)
    assert np.array_equal(read_image(tmp_path / "f.tiff"), f)
    stack = np.stack([_ramp(dtype=np.uint16, seed=s) for s in range(4)])
    tifffile.imwrite(tmp_path / "stack.tif", stack, photometric="minisblack")  # one page per frame
    frames = list(iter_frames(tmp_path / "stack.tif"))
    assert [fr.index for fr in frames] == [0, 1, 2, 3]
    assert all(np.array_equal(fr.image, stack[k]) for k, fr in enumerate(frames))
    assert frames[2].name == "stack.tif#2" and frames[2].time_s is None
    assert count_frames(tmp_path / "stack.tif") == 4
    rgb = np.stack([np.full((5, 6), v, np.uint8) for v in (200, 100, 50)])
    tifffile.imwrite(tmp_path / "planar.tif", rgb, photometric="rgb", planarconfig="separate")
    assert read_image(tmp_path / "planar.tif")[0, 0] == round(0.299 * 200 + 0.587 * 100 + 0.114 * 50)


def test_compressed_multipage_tiff(tmp_path):
    """Stacks saved compressed, as OpenCV (LZW, its default), ImageJ or an X-ray station
    writes them (LZW, Deflate, PackBits, 8 and 16 bit): every page read back exactly.  LZW
    needs tifffile's codecs package (``imagecodecs``, a dependency): without it the stack
    had been refused ("requires the 'imagecodecs' package")."""
    stack8 = np.stack([_ramp(dtype=np.uint8, seed=s) for s in range(3)])
    assert cv2.imwritemulti(str(tmp_path / "cv.tif"), list(stack8))
    assert int(tifffile.TiffFile(tmp_path / "cv.tif").pages[0].compression) == 5        # LZW
    frames = list(iter_frames(tmp_path / "cv.tif"))
    assert len(frames) == 3 and all(np.array_equal(fr.image, stack8[k]) for k, fr in enumerate(frames))
    stack16 = np.stack([_ramp(dtype=np.uint16, seed=s) for s in range(4)])
    for comp in ("lzw", "zlib", "packbits"):
        tifffile.imwrite(tmp_path / f"{comp}.tif", stack16, photometric="minisblack", compression=comp)
        frames = list(iter_frames(tmp_path / f"{comp}.tif"))
        assert [fr.index for fr in frames] == [0, 1, 2, 3], comp
        assert all(np.array_equal(fr.image, stack16[k]) for k, fr in enumerate(frames)), comp


def test_tiff_stack_times_from_its_metadata(tmp_path):
    """A stack's own time stamps: ImageJ's frame interval (Fiji's "Properties", in its time
    unit) and OME-TIFF's per-plane DeltaT (here uneven, with a gap of two periods: the pages
    after it are numbered by time).  A plain stack has none (the command's --fps gives them)."""
    stack = np.stack([_ramp(dtype=np.uint16, seed=s) for s in range(4)])
    tifffile.imwrite(tmp_path / "ij.tif", stack, imagej=True, metadata={"finterval": 0.5, "axes": "TYX"})
    fr = list(iter_frames(tmp_path / "ij.tif"))
    assert [f.time_s for f in fr] == pytest.approx([0.0, 0.5, 1.0, 1.5]) and [f.index for f in fr] == [0, 1, 2, 3]
    tifffile.imwrite(tmp_path / "ijms.tif", stack, imagej=True,
                     metadata={"finterval": 40.0, "tunit": "ms", "axes": "TYX"})
    assert [f.time_s for f in iter_frames(tmp_path / "ijms.tif")] == pytest.approx([0.0, 0.04, 0.08, 0.12])
    tifffile.imwrite(tmp_path / "ome.tif", stack, ome=True,
                     metadata={"axes": "TYX", "Plane": {"DeltaT": [100.0, 600.0, 1100.0, 2600.0],
                                                        "DeltaTUnit": ["ms"] * 4}})
    fr = list(iter_frames(tmp_path / "ome.tif"))
    assert [f.time_s for f in fr] == pytest.approx([0.0, 0.5, 1.0, 2.5]) and [f.index for f in fr] == [0, 1, 2, 5]
    assert all(np.array_equal(f.image, stack[k]) for k, f in enumerate(fr))
    tifffile.imwrite(tmp_path / "plain.tif", stack, photometric="minisblack")
    assert [f.time_s for f in iter_frames(tmp_path / "plain.tif")] == [None] * 4


def _ffmpeg_video(tmp_path, frames, times_s, name, codec_args):
    """``frames`` (gray uint8) shown at ``times_s`` (the last one for a period), encoded by the
    ffmpeg imageio-ffmpeg ships (with libx264), time stamps kept as given (variable rate)."""
    import subprocess
    ffmpeg = pytest.importorskip("imageio_ffmpeg").get_ffmpeg_exe()
    lines = []
    for k, img in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"src{k:03d}.png"), img)
        dur = (times_s[k + 1] - times_s[k]) if k + 1 < len(times_s) else (times_s[1] - times_s[0])
        lines += [f"file '{tmp_path / f'src{k:03d}.png'}'", f"duration {dur}"]
    (tmp_path / "list.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / name
    subprocess.run([ffmpeg, "-y", "-loglevel", "error", "-f", "concat", "-safe", "0", "-i", str(tmp_path / "list.txt"),
                    "-fps_mode", "passthrough", *codec_args, str(out)], check=True)
    return out


def test_video_h264_and_dropped_frames(tmp_path):
    """An H.264 MP4 (the usual capture format) is decoded with its time stamps; a capture
    that dropped frames keeps their times: a lossless FFV1 video with two frames missing
    numbers the frames after the gap by time (0-3, 6-11), so they still pair with the other
    view's by index, and its container's frame estimate (Matroska: duration x a nominal
    rate) is not taken for truncation."""
    rng = np.random.default_rng(5)
    imgs = [np.clip(rng.normal(120, 20, (64, 96)), 0, 255).astype(np.uint8) for _ in range(12)]
    t = [0.25 * k for k in range(12)]
    mp4 = _ffmpeg_video(tmp_path, imgs, t, "h264.mp4", ["-c:v", "libx264", "-crf", "10", "-pix_fmt", "yuv420p"])
    fr = list(iter_frames(mp4))
    assert [f.index for f in fr] == list(range(12))
    assert [f.time_s for f in fr] == pytest.approx(t, abs=0.05)
    assert max(np.abs(f.image.astype(float) - imgs[k]).mean() for k, f in enumerate(fr)) < 6.0
    keep = [k for k in range(12) if k not in (4, 5)]
    mkv = _ffmpeg_video(tmp_path, [imgs[k] for k in keep], [t[k] for k in keep], "gap.mkv",
                        ["-c:v", "ffv1", "-pix_fmt", "gray"])
    fr = list(iter_frames(mkv))
    assert [f.index for f in fr] == keep
    assert all(np.array_equal(f.image, imgs[k]) for k, f in zip(keep, fr))


def test_video_16_bit_lossless(tmp_path):
    """A lossless 16-bit gray video (FFV1 ``gray16le``, an X-ray archive's format and what the
    lossy-frames warning recommends) is read with its 16-bit samples: OpenCV's default BGR
    conversion had cut them to 8 bits (12-bit data read as 0, 0, 1, 1 ... for 0, 112, 224,
    336).  An 8-bit gray FFV1 stays 8-bit."""
    stack = [(np.arange(48 * 64).reshape(48, 64) * 7 % 4096).astype(np.uint16) * 16 + k for k in range(4)]
    v16 = _ffmpeg_video(tmp_path, stack, [0.25 * k for k in range(4)], "g16.mkv",
                        ["-c:v", "ffv1", "-pix_fmt", "gray16le"])
    fr = list(iter_frames(v16))
    assert all(f.image.dtype == np.uint16 and np.array_equal(f.image, stack[k]) for k, f in enumerate(fr))
    assert len(fr) == 4 and [f.time_s for f in fr] == pytest.approx([0.0, 0.25, 0.5, 0.75], abs=0.05)
    v8 = _ffmpeg_video(tmp_path, [(a >> 8).astype(np.uint8) for a in stack], [0.25 * k for k in range(4)], "g8.mkv",
                       ["-c:v", "ffv1", "-pix_fmt", "gray"])
    fr = list(iter_frames(v8))
    assert fr[1].image.dtype == np.uint8 and np.array_equal(fr[1].image, (stack[1] >> 8).astype(np.uint8))


def test_jpeg_and_colour_to_gray(tmp_path):
    rgb = np.zeros((20, 30, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 100, 50  # R, G, B
    cv2.imwrite(str(tmp_path / "c.png"), rgb[..., ::-1])  # OpenCV writes BGR
    g = read_image(tmp_path / "c.png")
    assert g.shape == (20, 30) and g.dtype == np.uint8
    assert g[0, 0] == round(0.299 * 200 + 0.587 * 100 + 0.114 * 50)
    assert read_image(tmp_path / "c.png", channel=1)[0, 0] == 100
    tifffile.imwrite(tmp_path / "c.tif", rgb)  # tifffile keeps RGB order
    assert read_image(tmp_path / "c.tif")[0, 0] == g[0, 0]
    a = np.full((16, 16), 128, np.uint8)
    cv2.imwrite(str(tmp_path / "j.jpg"), a, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert abs(int(read_image(tmp_path / "j.jpg")[8, 8]) - 128) <= 1


def test_dicom_single_multiframe_and_monochrome1(tmp_path):
    a = _ramp(dtype=np.uint16)
    _write_dicom(tmp_path / "one.dcm", a)
    assert np.array_equal(read_image(tmp_path / "one.dcm"), a)
    stack = np.stack([_ramp(dtype=np.uint16, seed=s) for s in range(3)])
    _write_dicom(tmp_path / "multi.dcm", stack, frame_time_ms=40.0)
    frames = list(iter_frames(tmp_path / "multi.dcm"))
    assert len(frames) == 3 and np.array_equal(frames[1].image, stack[1])
    assert frames[2].time_s == pytest.approx(0.08)
    assert count_frames(tmp_path / "multi.dcm") == 3
    from pydicom import dcmread
    ds = dcmread(tmp_path / "multi.dcm")
    del ds.FrameTime
    ds.CineRate = 15                       # frames per second, the Cine module's other form
    ds.save_as(tmp_path / "cine.dcm")
    assert [f.time_s for f in iter_frames(tmp_path / "cine.dcm")] == pytest.approx([0.0, 1 / 15, 2 / 15])
    b = _ramp(dtype=np.uint8)
    _write_dicom(tmp_path / "inv.dcm", b, photometric="MONOCHROME1")
    assert np.array_equal(read_image(tmp_path / "inv.dcm"), 255 - b)


def test_dicom_without_a_suffix_is_read_and_under_an_image_suffix_is_named(tmp_path):
    """A DICOM file without a suffix (as scanners write them) is found by its preamble; one
    named .png is not opened twice per frame to look for it, and its decoding fails with a
    message that says what it is, naming the file (exit 2 in a command)."""
    a = _ramp(dtype=np.uint16)
    _write_dicom(tmp_path / "IM0001", a)
    assert np.array_equal(read_image(tmp_path / "IM0001"), a)
    (tmp_path / "IM0001").rename(tmp_path / "frame.png")
    with pytest.raises(InputError, match=r"DICOM data in a file named \.png.*\.dcm") as e:
        read_image(tmp_path / "frame.png")
    assert "frame.png" in str(e.value)


def test_dicom_compressed_multiframe(tmp_path):
    """Multi-frame DICOM with compressed pixel data, as C-arms and PACS export it: JPEG
    Lossless (process 14, selection value 1: the usual angiography syntax; its decoder is
    pylibjpeg-libjpeg, a dependency) and RLE Lossless, 12-bit data in 16 bits, MONOCHROME1
    too: every frame read back exactly, one at a time, with its time.  Without the JPEG
    Lossless decoder such a file had been refused ("cannot decode DICOM pixel data")."""
    import imagecodecs
    from pydicom import dcmread
    from pydicom.encaps import encapsulate
    from pydicom.uid import JPEGLosslessSV1, RLELossless
    stack = np.stack([(_ramp(dtype=np.uint16, seed=s) >> 4) for s in range(4)])      # 12-bit values
    _write_dicom(tmp_path / "plain.dcm", stack, frame_time_ms=500.0)
    ds = dcmread(tmp_path / "plain.dcm")
    ds.BitsStored, ds.HighBit = 12, 11
    ds.compress(RLELossless, stack)
    ds.save_as(tmp_path / "rle.dcm", enforce_file_format=True)
    ds = dcmread(tmp_path / "plain.dcm")
    ds.BitsStored, ds.HighBit = 12, 11
    ds.PixelData = encapsulate([imagecodecs.ljpeg_encode(f, bitspersample=12) for f in stack])
    ds.file_meta.TransferSyntaxUID = JPEGLosslessSV1
    ds["PixelData"].VR = "OB"
    ds.save_as(tmp_path / "ljpeg.dcm", enforce_file_format=True)
    for name in ("rle.dcm", "ljpeg.dcm"):
        frames = list(iter_frames(tmp_path / name))
        assert [f.index for f in frames] == [0, 1, 2, 3], name
        assert all(np.array_equal(f.image, stack[k]) for k, f in enumerate(frames)), name
        assert frames[3].time_s == pytest.approx(1.5)
        assert np.array_equal(read_image(tmp_path / name), stack[0])
    ds = dcmread(tmp_path / "ljpeg.dcm")
    ds.PhotometricInterpretation = "MONOCHROME1"
    ds.save_as(tmp_path / "ljpeg_inv.dcm", enforce_file_format=True)
    assert np.array_equal(list(iter_frames(tmp_path / "ljpeg_inv.dcm"))[2].image, 4095 - stack[2])


def test_enhanced_dicom_per_frame_times(tmp_path):
    """An enhanced multi-frame file (Enhanced XA) states each frame's time in its
    per-frame functional groups (FrameContentSequence), not in FrameTime: the frames take
    those times (frame 2 at 0.533 s here, the intervals uneven), and a gap of a whole period
    numbers the frames after it by time."""
    from pydicom import dcmread
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence
    stack = np.stack([_ramp(dtype=np.uint16, seed=s) for s in range(4)])
    _write_dicom(tmp_path / "m.dcm", stack)
    ds = dcmread(tmp_path / "m.dcm")
    stamps = ["20261122101500.000000", "20261122101500.266000", "20261122101500.533000", "20261122101501.333000"]

    def groups(kw):
        out = []
        for st in stamps:
            fc = Dataset()
            setattr(fc, kw, st)
            item = Dataset()
            item.FrameContentSequence = Sequence([fc])
            out.append(item)
        return Sequence(out)

    for kw in ("FrameAcquisitionDateTime", "FrameReferenceDateTime"):
        ds.PerFrameFunctionalGroupsSequence = groups(kw)
        ds.save_as(tmp_path / "enh.dcm", enforce_file_format=True)
        frames = list(iter_frames(tmp_path / "enh.dcm"))
        assert [f.time_s for f in frames] == pytest.approx([0.0, 0.266, 0.533, 1.333])
        # 0.27 s periods, then 0.8 s: the last frame is frame 5 (frames 3 and 4 not recorded)
        assert [f.index for f in frames] == [0, 1, 2, 5]
        assert np.array_equal(frames[3].image, stack[3])


def test_dicom_export_folder_with_its_dicomdir(tmp_path):
    """A series exported from a PACS or onto a CD: files without a suffix (IM0000 ...) and the
    export's index, DICOMDIR (a DICOM file without pixel data), in the same folder: the
    images are the frames, the index is not one (it had stopped the command: "no pixel
    data")."""
    from pydicom.uid import MediaStorageDirectoryStorage
    imgs = [_ramp(dtype=np.uint16, seed=s) for s in range(3)]
    for k, a in enumerate(imgs):
        _write_dicom(tmp_path / f"IM{k:04d}", a)
    ds = _new_dicom(MediaStorageDirectoryStorage)
    ds.FileSetID = "EXPORT"
    ds.save_as(tmp_path / "DICOMDIR", enforce_file_format=True)
    frames = list(iter_frames(tmp_path))
    assert [f.name for f in frames] == ["IM0000", "IM0001", "IM0002"]
    assert all(np.array_equal(f.image, imgs[k]) for k, f in enumerate(frames))
    assert count_frames(tmp_path) == 3


def test_dicom_short_pixel_data_names_the_frame(tmp_path):
    """A multi-frame DICOM cut short, or whose NumberOfFrames states more frames than its
    pixel data holds: the frames before are read, then exit 2 naming the file and the frame."""
    from pydicom import dcmread
    stack = np.stack([_ramp(dtype=np.uint16, seed=s) for s in range(4)])
    _write_dicom(tmp_path / "m.dcm", stack)
    ds = dcmread(tmp_path / "m.dcm")
    ds.NumberOfFrames = 6
    ds.save_as(tmp_path / "six.dcm")
    data = (tmp_path / "m.dcm").read_bytes()
    (tmp_path / "cut.dcm").write_bytes(data[:len(data) - stack[0].nbytes - 100])
    for name, k in (("six.dcm", 4), ("cut.dcm", 2)):
        got = []
        with pytest.raises(InputError, match=f"{name}, frame {k}: cannot decode DICOM pixel data") as e:
            got.extend(fr.image for fr in iter_frames(tmp_path / name))
        assert e.value.exit_code == 2 and len(got) == k and np.array_equal(got[-1], stack[k - 1])


def test_dicom_series_folder_sorted_by_name(tmp_path):
    d = tmp_path / "series"
    d.mkdir()
    imgs = [_ramp(dtype=np.uint16, seed=s) for s in range(3)]
    for k, name in enumerate(["im2.dcm", "im10.dcm", "im1.dcm"]):
        _write_dicom(d / name, imgs[k])
    frames = list(iter_frames(d))
    assert [f.name for f in frames] == ["im1.dcm", "im2.dcm", "im10.dcm"]
    assert np.array_equal(frames[0].image, imgs[2])


def test_folder_and_glob_sorted(tmp_path):
    for k in (3, 1, 2):
        cv2.imwrite(str(tmp_path / f"f{k:03d}.png"), np.full((8, 9), k, np.uint8))
    (tmp_path / "notes.txt").write_text("not an image")
    frames = list(iter_frames(tmp_path))
    assert [f.name for f in frames] == ["f001.png", "f002.png", "f003.png"]
    assert [int(f.image[0, 0]) for f in frames] == [1, 2, 3]
    assert [f.index for f in iter_frames(str(tmp_path / "f00[23].png"))] == [0, 1]


@pytest.mark.parametrize("suffix,fourcc", [(".avi", "MJPG"), (".mp4", "mp4v")])
def test_video_frames_and_times(tmp_path, suffix, fourcc):
    p = tmp_path / f"v{suffix}"
    w = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*fourcc), 25.0, (64, 48), False)
    assert w.isOpened()
    for k in range(6):
        w.write(np.full((48, 64), 30 * k, np.uint8))
    w.release()
    frames = list(iter_frames(p))
    assert len(frames) == 6 and frames[0].image.shape == (48, 64)
    assert [abs(int(f.image.mean()) - 30 * f.index) <= 3 for f in frames] == [True] * 6
    assert frames[5].time_s == pytest.approx(5 / 25.0, abs=1e-3)
    assert count_frames(p) == 6


def test_corrupt_and_mismatched_images_name_the_file(tmp_path):
    good = np.zeros((10, 10), np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), good)
    (tmp_path / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(InputError, match="b.png"):
        list(iter_frames(tmp_path))
    d = tmp_path / "mixed"
    d.mkdir()
    cv2.imwrite(str(d / "a.png"), good)
    cv2.imwrite(str(d / "b.png"), np.zeros((12, 10), np.uint8))
    with pytest.raises(InputError, match=r"b.png, frame 1: image is 10x12 px, expected 10x10"):
        list(iter_frames(d))
    # a truncated JPEG decodes with only a libjpeg warning; it must still be refused
    cv2.imwrite(str(tmp_path / "t.jpg"), np.full((64, 64), 99, np.uint8))
    data = (tmp_path / "t.jpg").read_bytes()
    (tmp_path / "t.jpg").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="t.jpg.*truncated"):
        read_image(tmp_path / "t.jpg")
    (tmp_path / "x.dcm").write_bytes(b"not a dicom")
    with pytest.raises(InputError, match="x.dcm"):
        read_image(tmp_path / "x.dcm")
    (tmp_path / "v.avi").write_bytes(b"RIFF0000AVI garbage")
    with pytest.raises(InputError, match="v.avi"):
        list(iter_frames(tmp_path / "v.avi"))
    with pytest.raises(InputError, match="no such"):
        read_image(tmp_path / "missing.png")


def test_frame_hashes_from_the_bytes_decoded_match_the_files(tmp_path):
    """iter_frames(hashes=...) records each file's sha256 (from the bytes it decoded, for
    PNG/JPEG; from the file for TIFF): the provenance block is the same as hashing the files
    afresh, and a file iter_frames did not read (a note in the folder) is still hashed."""
    from bsipipe.provenance import input_hashes, sha256_file
    d = tmp_path / "seq"
    d.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        cv2.imwrite(str(d / f"f{k}.png"), rng.integers(0, 255, (16, 20), dtype=np.uint8))
    tifffile.imwrite(d / "f3.tif", rng.integers(0, 255, (16, 20), dtype=np.uint8))
    (d / "notes.txt").write_text("not a frame")
    hashes: dict = {}
    n = sum(1 for _ in iter_frames(d, hashes=hashes))
    assert n == 4 and sorted(hashes) == sorted(str(p) for p in d.iterdir() if p.suffix != ".txt")
    assert all(h == sha256_file(p) for p, h in hashes.items())
    assert input_hashes([d], hashes) == input_hashes([d])
    assert str(d / "notes.txt") in input_hashes([d], hashes)


@pytest.mark.parametrize("workers", [2, 3])
def test_decoding_threads_give_the_same_frames_and_errors(tmp_path, workers):
    """iter_frames(workers=N) on a folder of PNGs: the frames, names, order and hashes of a
    sequential read; a corrupt file raises when its turn comes (the frames before it are
    yielded first), naming it; a consumer that stops early stops the pool."""
    rng = np.random.default_rng(1)
    imgs = [rng.integers(0, 255, (12, 14), dtype=np.uint8) for _ in range(9)]
    for k, a in enumerate(imgs):
        cv2.imwrite(str(tmp_path / f"f{k:02d}.png"), a)
    h1, h2 = {}, {}
    seq = list(iter_frames(tmp_path, hashes=h1))
    par = list(iter_frames(tmp_path, hashes=h2, workers=workers))
    assert [f.name for f in par] == [f.name for f in seq] == [f"f{k:02d}.png" for k in range(9)]
    assert all(np.array_equal(a.image, b.image) and a.index == b.index for a, b in zip(seq, par))
    assert h1 == h2 and len(h1) == 9
    it = iter_frames(tmp_path, workers=workers)
    assert next(it).name == "f00.png"
    it.close()
    (tmp_path / "f05.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"junk" * 10 + b"IEND\xaeB`\x82")
    got = []
    with pytest.raises(InputError, match="f05.png"):
        for f in iter_frames(tmp_path, workers=workers):
            got.append(f.name)
    assert got == [f"f{k:02d}.png" for k in range(5)]


def _series_file(path, img, **tags):
    """A single-frame DICOM with the given header attributes (InstanceNumber, times...)."""
    import pydicom
    _write_dicom(path, img)
    ds = pydicom.dcmread(str(path))
    for k, v in tags.items():
        setattr(ds, k, v)
    ds.save_as(str(path), enforce_file_format=True)


def test_dicom_series_in_instance_order_timed_by_acquisition(tmp_path):
    # scanners name a series' files by UID: the order is the files' InstanceNumber, and each
    # frame's time its file's acquisition time (relative to the first)
    imgs = [_ramp(dtype=np.uint16, seed=s) for s in range(4)]
    names = ["1.2.840.9.77.dcm", "1.2.840.9.12.dcm", "1.2.840.9.5.dcm", "1.2.840.9.40.dcm"]
    inst = [3, 1, 4, 2]
    d = tmp_path / "uid"
    d.mkdir()
    for name, k in zip(names, inst):
        _series_file(d / name, imgs[k - 1], InstanceNumber=k, ContentDate="20261121",
                     ContentTime=f"1200{10 + k // 2:02d}.{500000 * (k % 2):06d}", FrameTime=500)
    frames = list(iter_frames(d))
    assert [int(f.image[0, 0]) for f in frames] == [int(a[0, 0]) for a in imgs]
    assert [f.time_s for f in frames] == pytest.approx([0.0, 0.5, 1.0, 1.5])
    # no per-file time: FrameTime (an interval) counts the instances, a gap is a frame missing
    e = tmp_path / "ft"
    e.mkdir()
    for k in (1, 2, 4):
        _series_file(e / f"x{5 - k}.dcm", imgs[k - 1], InstanceNumber=k, FrameTime=250)
    assert [f.time_s for f in iter_frames(e)] == pytest.approx([0.0, 0.25, 0.75])
    # a single-frame file alone states no time of its own (the command's --fps applies)
    assert next(iter_frames(e / "x1.dcm")).time_s is None
    # neither: no time, order by name
    g = tmp_path / "plain"
    g.mkdir()
    for k in range(3):
        _series_file(g / f"p{k}.dcm", imgs[k])
    assert [f.time_s for f in iter_frames(g)] == [None, None, None]


def test_damaged_stacks_videos_and_jpegs_are_refused(tmp_path):
    # a multi-page TIFF cut short: tifffile logs the bad page offset and drops the pages after
    stack = np.stack([_ramp(64, 64, seed=s) for s in range(20)])
    tifffile.imwrite(tmp_path / "s.tif", stack)
    data = (tmp_path / "s.tif").read_bytes()
    (tmp_path / "cut.tif").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut.tif.*(damaged or truncated|cannot decode)"):
        list(iter_frames(tmp_path / "cut.tif"))
    with pytest.raises(InputError, match="cut.tif"):
        count_frames(tmp_path / "cut.tif")
    assert len(list(iter_frames(tmp_path / "s.tif"))) == 20
    # a video cut short: fewer frames than its header states
    p = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48), False)
    for k in range(30):
        w.write(_ramp(48, 64, seed=k))
    w.release()
    assert len(list(iter_frames(p))) == 30
    (tmp_path / "vcut.avi").write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.raises(InputError, match=r"vcut.avi.*ends after \d+ of the 30 frames"):
        list(iter_frames(tmp_path / "vcut.avi"))
    # a JPEG overwritten in the middle keeps its start and end markers; the marker pattern
    # of its image data is broken (libjpeg only warns and returns garbage)
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(_ramp(256, 256), (0, 0), 2)
    for name, params in (("plain", []), ("progressive", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),
                         ("restarts", [cv2.IMWRITE_JPEG_RST_INTERVAL, 2])):
        good = cv2.imencode(".jpg", img, params)[1].tobytes()
        (tmp_path / f"{name}.jpg").write_bytes(good)
        assert np.array_equal(read_image(tmp_path / f"{name}.jpg"), cv2.imdecode(np.frombuffer(good, np.uint8), 0))
        bad = bytearray(good)
        m = len(bad) // 2
        bad[m:m + 2000] = rng.integers(0, 256, 2000, dtype=np.uint8).tobytes()
        (tmp_path / f"{name}_bad.jpg").write_bytes(bytes(bad))
        with pytest.raises(InputError, match=f"{name}_bad.jpg.*corrupt JPEG data"):
            read_image(tmp_path / f"{name}_bad.jpg")


def test_lossy_compression_of_a_source(tmp_path):
    """JPEG files and videos in a lossy codec are named (the track command warns of them);
    PNG and TIFF frames and videos in a lossless codec (FFV1, HuffYUV) are not."""
    img = np.full((48, 64), 90, np.uint8)
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(tmp_path / name), img)
    tifffile.imwrite(tmp_path / "s.tif", np.stack([img, img]))
    (tmp_path / "jpg").mkdir()
    cv2.imwrite(str(tmp_path / "jpg" / "f1.jpg"), img)
    assert lossy_compression(tmp_path / "a.png") is None
    assert lossy_compression(str(tmp_path / "*.png")) is None
    assert lossy_compression(tmp_path / "s.tif") is None
    assert lossy_compression(tmp_path / "jpg") == "JPEG files"
    found = {}
    for fourcc, suffix in (("FFV1", ".avi"), ("HFYU", ".avi"), ("MJPG", ".avi"), ("mp4v", ".mp4")):
        p = tmp_path / f"v_{fourcc}{suffix}"
        w = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*fourcc), 25.0, (64, 48), False)
        if not w.isOpened():
            continue
        for k in range(3):
            w.write(img)
        w.release()
        found[fourcc] = lossy_compression(p)
    assert found.get("MJPG") == "video codec MJPG"
    assert found.get("mp4v", "").startswith("video codec ")          # OpenCV writes mp4v as FMP4
    assert found.get("FFV1", None) is None and found.get("HFYU", None) is None
    assert {"MJPG", "mp4v"} <= set(found)


def test_a_frame_missing_from_the_numbering_keeps_its_index(tmp_path):
    """A recorder that drops a frame leaves a gap in its files' counter: the later frames keep
    the counter's indices (so they still pair with the other view's frames), the gap's index
    is left out.  Counters that are not frame counts (a time stamp in the name), names that
    differ around the number, and a constant step (every other frame saved) are counted."""
    def folder(name, files):
        d = tmp_path / name
        d.mkdir()
        for k, f in enumerate(files):
            cv2.imwrite(str(d / f), np.full((6, 7), k, np.uint8))
        return d

    d = folder("gap", [f"frame_{k:04d}.png" for k in (1, 2, 3, 5, 6, 7)])
    assert [f.index for f in iter_frames(d)] == [0, 1, 2, 4, 5, 6]
    assert [f.index for f in iter_frames(d, workers=3)] == [0, 1, 2, 4, 5, 6]
    assert [int(f.image[0, 0]) for f in iter_frames(d)] == list(range(6))
    assert [f.index for f in iter_frames(str(d / "frame_000[2-6].png"))] == [0, 1, 3, 4]
    step = folder("step", [f"f{k}.png" for k in (0, 2, 4, 8, 10)])
    assert [f.index for f in iter_frames(step)] == [0, 1, 2, 4, 5]
    every_other = folder("even", [f"f{k}.png" for k in (0, 2, 4, 6)])
    assert [f.index for f in iter_frames(every_other)] == [0, 1, 2, 3]
    stamps = folder("stamps", [f"img_{ms}.png" for ms in (1000, 1501, 1999, 2502, 3000)])
    assert [f.index for f in iter_frames(stamps)] == [0, 1, 2, 3, 4]
    mixed = folder("mixed", ["a1.png", "a2.png", "b4.png"])
    assert [f.index for f in iter_frames(mixed)] == [0, 1, 2]
    # a DICOM series in InstanceNumber order: a missing instance is a missing frame
    imgs = [_ramp(dtype=np.uint16, seed=s) for s in range(3)]
    e = tmp_path / "series"
    e.mkdir()
    for name, k in (("u9.dcm", 1), ("u3.dcm", 2), ("u5.dcm", 4)):
        _series_file(e / name, imgs[[1, 2, 4].index(k)], InstanceNumber=k)
    assert [f.index for f in iter_frames(e)] == [0, 1, 3]


def test_frames_a_dicom_source_skipped_keep_their_times_numbers(tmp_path):
    """A multi-frame DICOM whose FrameTimeVector skips a period (a frame the recorder did not
    store), and a series numbered without a gap whose acquisition times skip one: the frames
    after the gap keep the numbers their times give (index 3 left empty), as a folder whose
    file names skip a number does; times that merely jitter, or run evenly, are counted."""
    stack = np.stack([_ramp(dtype=np.uint16, seed=s) for s in range(5)])
    _write_dicom(tmp_path / "gap.dcm", stack, frame_time_vector=[0, 500, 500, 1000, 500])
    fr = list(iter_frames(tmp_path / "gap.dcm"))
    assert [f.index for f in fr] == [0, 1, 2, 4, 5]
    assert [f.time_s for f in fr] == pytest.approx([0.0, 0.5, 1.0, 2.0, 2.5])
    assert np.array_equal(fr[3].image, stack[3]) and fr[3].name == "gap.dcm#3"
    _write_dicom(tmp_path / "jitter.dcm", stack, frame_time_vector=[0, 500, 560, 450, 500])
    assert [f.index for f in iter_frames(tmp_path / "jitter.dcm")] == [0, 1, 2, 3, 4]
    _write_dicom(tmp_path / "even.dcm", stack, frame_time_ms=500.0)
    assert [f.index for f in iter_frames(tmp_path / "even.dcm")] == [0, 1, 2, 3, 4]
    d = tmp_path / "series"
    d.mkdir()
    for k, sec in enumerate([10.0, 10.5, 11.0, 12.0, 12.5]):
        _series_file(d / f"s{k}.dcm", stack[k], InstanceNumber=k + 1, ContentDate="20261121",
                     ContentTime=f"1200{int(sec):02d}.{int(round((sec % 1) * 1e6)):06d}")
    fr = list(iter_frames(d))
    assert [f.index for f in fr] == [0, 1, 2, 4, 5]
    assert [f.time_s for f in fr] == pytest.approx([0.0, 0.5, 1.0, 2.0, 2.5])


def test_a_thumbnail_that_sorts_first_is_named(tmp_path):
    """A preview image of another size that sorts before the frames (``_preview.png``) had
    made every later frame the odd one ("frame_0000.png: image is 64x48 px, expected 16x12
    like _preview.png"), and ``track`` blamed the calibration or the seeds checked against
    its size.  The first file is named when the files after it agree with each other."""
    import cv2
    from bsipipe.errors import InputError
    from bsipipe.io.images import iter_frames
    d = tmp_path / "cam1"
    d.mkdir()
    cv2.imwrite(str(d / "_preview.png"), np.full((12, 16), 100, np.uint8))
    for k in range(3):
        cv2.imwrite(str(d / f"frame_{k:04d}.png"), np.full((48, 64), 120 + k, np.uint8))
    with pytest.raises(InputError) as e:
        list(iter_frames(d))
    assert "_preview.png" in str(e.value) and "the files after it 64x48 px" in str(e.value)
    # a stray file of another size after the frames is still named by itself
    (d / "_preview.png").unlink()
    cv2.imwrite(str(d / "zz_stray.png"), np.full((12, 16), 100, np.uint8))
    with pytest.raises(InputError) as e:
        list(iter_frames(d))
    assert "zz_stray.png" in str(e.value) and "expected 64x48 px" in str(e.value)


def test_two_runs_of_a_series_in_one_folder_are_refused(tmp_path):
    """A folder with a 6-file run and 2 files of an earlier one (both numbered from 1, or of
    two series UIDs): ordered together by time, the gap had been taken for thousands of dropped
    frames and frames of the other run tracked, exit 0.  It is exit 2 naming the files."""
    from pydicom.uid import generate_uid
    imgs = [_ramp(dtype=np.uint16, seed=s) for s in range(8)]
    d = tmp_path / "mixed"
    d.mkdir()
    uid_a, uid_b = generate_uid(), generate_uid()
    for k in range(6):
        _series_file(d / f"IM{k:05d}.dcm", imgs[k], InstanceNumber=k + 1, SeriesInstanceUID=uid_a,
                     ContentDate="20261121", ContentTime=f"1210{k:02d}")
    for k in range(2):
        _series_file(d / f"RUN0_{k}.dcm", imgs[6 + k], InstanceNumber=k + 1, SeriesInstanceUID=uid_b,
                     ContentDate="20261121", ContentTime=f"1200{k:02d}")
    with pytest.raises(InputError, match="DICOM series") as e:
        list(iter_frames(d))
    assert "RUN0_0.dcm" in str(e.value)
    # the same numbering clash without series UIDs that tell them apart
    for f in d.glob("RUN0_*.dcm"):
        _series_file(f, imgs[7], InstanceNumber=int(f.stem[-1]) + 1, SeriesInstanceUID=uid_a,
                     ContentDate="20261121", ContentTime=f"1200{f.stem[-1]:0>2}")
    with pytest.raises(InputError, match="repeat another's InstanceNumber"):
        list(iter_frames(d))


def test_frame_time_vector_holding_times_is_read_as_times(tmp_path):
    """A FrameTimeVector of each frame's time (0, 250, 500, ... ms) where DICOM asks for the
    increments (0, 250, 250, ...): summed, the clip had run 0, 0.25, 0.75, 1.5 ... s, unsaid.
    Increments that grow by one period per frame are read as times (with a log warning)."""
    frames = np.stack([_ramp(seed=s) for s in range(6)])
    _write_dicom(tmp_path / "cum.dcm", frames, frame_time_vector=[0, 250, 500, 750, 1000, 1250])
    _write_dicom(tmp_path / "inc.dcm", frames, frame_time_vector=[0, 250, 250, 250, 250, 250])
    for name in ("cum.dcm", "inc.dcm"):
        assert [f.time_s for f in iter_frames(tmp_path / name)] == pytest.approx([0, 0.25, 0.5, 0.75, 1.0, 1.25])


def test_frames_named_by_decimal_times_in_time_order(tmp_path):
    """Files named by their time with a decimal point (t_0s, t_0.25s, t_0.5s ...): the natural
    order had read t_0.5s before t_0.25s (frames out of order, 3-D points 0.68 mm off, exit 0)."""
    d = tmp_path / "t"
    d.mkdir()
    times = [0, 0.25, 0.5, 0.75, 1, 1.25, 1.5, 2, 10.5]
    for k, t in enumerate(times):
        cv2.imwrite(str(d / f"t_{t:g}s.png"), _ramp(seed=k))
    got = [int(f.image[0, 0]) for f in iter_frames(d)]
    assert got == [int(_ramp(seed=k)[0, 0]) for k in range(len(times))]


def test_tiff_stack_with_a_preview_page(tmp_path):
    """A TIFF stack whose first page is a reduced-resolution preview (NewSubfileType 1): it had
    been taken for frame 0 and the real frames refused ("image is 512x512 px, expected 128x128
    px like cam1.tif#0").  Previews are left out of the frames and the count."""
    frames = [_ramp(64, 64, seed=s) for s in range(4)]
    p = tmp_path / "stack.tif"
    with tifffile.TiffWriter(str(p)) as w:
        w.write(frames[0][::4, ::4], subfiletype=1)
        for f in frames:
            w.write(f, contiguous=False)
    got = list(iter_frames(p))
    assert len(got) == 4 and count_frames(p) == 4
    assert all(np.array_equal(g.image, f) for g, f in zip(got, frames))
    assert np.array_equal(read_image(p), frames[0])


def _tm(sec: float, digits: int = 6) -> str:
    """A DICOM TM for ``sec`` seconds after 12:00:00, written to ``digits`` decimals."""
    whole = int(sec)
    frac = f"{sec - whole:.{digits}f}"[1:] if digits else ""
    return f"12{whole // 60:02d}{whole % 60:02d}{frac}"


def test_dicom_series_ordered_and_timed_by_the_acquisition_clock(tmp_path):
    """InstanceNumbers that run against AcquisitionTime (a writer numbering files as it exports
    them) had ordered the frames backwards and dropped the times as not increasing; a
    ContentTime of the export (files 8 ms apart) had been taken before the acquisition's 0.5 s
    clock.  Now the acquisition clock orders and times the frames."""
    imgs = [_ramp(dtype=np.uint16, seed=s) for s in range(5)]
    d = tmp_path / "reversed"
    d.mkdir()
    for k in range(5):
        _series_file(d / f"u{k}.dcm", imgs[k], InstanceNumber=5 - k, AcquisitionDate="20261121",
                     AcquisitionTime=_tm(0.5 * k), ContentDate="20261121", ContentTime=_tm(30 + 0.008 * (4 - k)))
    frames = list(iter_frames(d))
    assert [int(f.image[0, 0]) for f in frames] == [int(a[0, 0]) for a in imgs]
    assert [f.time_s for f in frames] == pytest.approx([0.0, 0.5, 1.0, 1.5, 2.0])
    e = tmp_path / "export_time"
    e.mkdir()
    for k in range(5):
        _series_file(e / f"v{k}.dcm", imgs[k], InstanceNumber=k + 1, AcquisitionDate="20261121",
                     AcquisitionTime=_tm(0.5 * k), ContentDate="20261121", ContentTime=_tm(30 + 0.008 * k))
    assert [f.time_s for f in iter_frames(e)] == pytest.approx([0.0, 0.5, 1.0, 1.5, 2.0])


def test_coarse_time_stamps_are_not_dropped_frames(tmp_path):
    """7.5 frames/s stamped to 0.1 s: intervals of 0.1 and 0.2 s had read as a frame dropped
    every other frame (12 phantom missing frames per view, differently in each view).  The
    frames are counted, and the steady rate the stamps allow gives their times; stamps fine
    enough to see a real gap still number the frames after it."""
    from bsipipe.io.images import stamp_resolution, time_indices
    n = 30
    imgs = [_ramp(8, 8, dtype=np.uint16, seed=s) for s in range(n)]
    d = tmp_path / "coarse"
    d.mkdir()
    stamps = [round(k / 7.5 + 0.05, 1) for k in range(n)]
    for k in range(n):
        _series_file(d / f"c{k:02d}.dcm", imgs[k], InstanceNumber=k + 1, AcquisitionDate="20261121",
                     AcquisitionTime=_tm(stamps[k], 1))
    frames = list(iter_frames(d))
    assert [f.index for f in frames] == list(range(n))
    truth = np.arange(n) / 7.5
    got = np.array([f.time_s for f in frames])
    raw = np.array(stamps) - stamps[0]
    assert np.abs(got - truth).max() < 0.02 < np.abs(raw - truth).max()
    assert stamp_resolution([0.0, 0.1, 0.3]) == 0.1
    assert time_indices([0.0, 0.133, 0.267, 0.533, 0.667]) == [0, 1, 2, 4, 5]


def test_clips_of_one_run_play_one_after_another(tmp_path):
    """A folder of multi-frame files (DICOM clips, ImageJ stacks) each timing its frames from 0:
    the times had restarted at 0 in every file (8.0, 8.5, 0.0, 0.5 ... in markers2d.csv) and
    every loop effect failed on them, exit 0.  Each file now starts one frame period after the
    last frame of the file before."""
    stack = np.stack([_ramp(dtype=np.uint16, seed=s) for s in range(7)])
    d = tmp_path / "clips"
    d.mkdir()
    _write_dicom(d / "run_1.dcm", stack[:4], frame_time_ms=500.0)
    _write_dicom(d / "run_2.dcm", stack[4:], frame_time_ms=500.0)
    fr = list(iter_frames(d))
    assert [f.index for f in fr] == list(range(7))
    assert [f.time_s for f in fr] == pytest.approx([0.5 * k for k in range(7)])
    t = tmp_path / "stacks"
    t.mkdir()
    for j, part in enumerate((stack[:3], stack[3:])):
        tifffile.imwrite(t / f"part{j}.tif", part, imagej=True, metadata={"finterval": 0.25, "axes": "TYX"})
    assert [f.time_s for f in iter_frames(t)] == pytest.approx([0.25 * k for k in range(7)])
    # one file alone keeps its own times
    assert [f.time_s for f in iter_frames(d / "run_2.dcm")] == pytest.approx([0.0, 0.5, 1.0])


def test_an_image_among_a_dicom_series_is_named(tmp_path):
    """A preview PNG of the same size among a series' UID-named files had turned the series
    off: the files came in name order with the preview as a frame, times lost, exit 0."""
    import cv2
    from bsipipe.errors import InputError
    imgs = [_ramp(seed=s) for s in range(4)]
    d = tmp_path / "series"
    d.mkdir()
    for k in range(3):
        _series_file(d / f"1.2.{7 - k}.dcm", imgs[k], InstanceNumber=k + 1)
    assert len(list(iter_frames(d))) == 3
    cv2.imwrite(str(d / "preview.png"), imgs[3])
    with pytest.raises(InputError, match=r"3 DICOM files and 1 other image file\(s\) \(preview.png\)"):
        list(iter_frames(d))
    assert len(list(iter_frames(str(d / "*.dcm")))) == 3


def test_a_folder_of_videos_says_how_to_give_them(tmp_path):
    from bsipipe.errors import InputError
    (tmp_path / "part1.avi").write_bytes(b"RIFF")
    with pytest.raises(InputError, match=r"folder holds videos \(part1.avi\).*\*\.avi"):
        list(iter_frames(tmp_path))
