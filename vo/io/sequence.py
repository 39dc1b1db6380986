"""Open an input sequence and stream its frames one at a time.

:func:`open_sequence` recognises four kinds of input:

* ``"kitti"``: a KITTI odometry sequence folder with ``image_2/`` or
  ``image_0/`` (``image_2`` preferred when both hold images; PNG or JPEG) and
  ``calib.txt`` (the ``P<n>:`` line matching the image folder's name);
  ``times.txt`` (one timestamp per line) when present. Passing the
  ``image_<n>`` folder itself works too when its parent holds ``calib.txt``.
* ``"kitti_raw"``: a KITTI raw drive folder (``<date>_drive_<NNNN>_sync``) with
  ``image_02/data/`` (else ``image_00/data/``) and the date folder's
  ``calib_cam_to_cam.txt`` (``P_rect_02``, resp. ``P_rect_00``), see
  :mod:`trianflow_vo.io.kitti_raw`; ``image_02/timestamps.txt`` when present.
* ``"tum"``: a TUM RGB-D folder with ``rgb.txt`` (``timestamp filename``
  lines) and ``rgb/``. Intrinsics: the published values of the Freiburg
  camera named in the folder name, else ``--intrinsics``/``--calib``.
* ``"images"``: any folder of png/jpg/jpeg/bmp/tif/tiff images, in natural
  order (``2.png`` before ``10.png``); intrinsics from ``--intrinsics``,
  ``--calib`` or a ``calib.txt``/``K.txt`` inside the folder. A folder with no
  images of its own but exactly one image sub-folder named ``color``,
  ``images``, ``image``, ``rgb`` or ``frames`` (the 7-Scenes clip's layout) reads
  that sub-folder, with the calibration and ``poses.txt`` beside it.
* ``"video"``: a file with a video container suffix (mp4, mov, avi, mkv, webm,
  m4v, mpg, mpeg, wmv, flv, ts, ... see :data:`VIDEO_EXTENSIONS`) whose first
  frame decodes as an image; timestamps from the container. Any other file is
  refused (FFmpeg would otherwise read e.g. a ``.txt`` as a video of rendered
  text). When the video ends before the frame count its container states (a
  truncated file), :attr:`Sequence.shortfall` says so after iteration.

Frames are decoded lazily while iterating (or one at a time for random access
with :meth:`Sequence.read_frame` / :class:`FrameReader`); a :class:`Sequence`
holds only the list of file names (or the video path), never the images. Frames that cannot be
used (unreadable, truncated, empty, or of a size different from the first
frame) come out as :class:`vo.frames.FrameSkip` instead of raising: its
``source`` is the file (or ``video#index``), its ``reason`` says what is wrong.
"""

from __future__ import annotations

import os
import queue
import re
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from trianflow_vo.errors import InputError
from trianflow_vo.frames import Frame, FrameSkip, Shortfall
from trianflow_vo.io import calib as _calib
from trianflow_vo.io import kitti_raw as _kitti_raw

IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"})
# video container suffixes accepted as a video input (anything else is refused, not probed)
VIDEO_EXTENSIONS = frozenset({".mp4", ".m4v", ".mov", ".avi", ".mkv", ".webm", ".mpg", ".mpeg", ".m2v", ".wmv",
                              ".asf", ".flv", ".ts", ".mts", ".m2ts", ".3gp", ".ogv", ".mxf", ".vob"})
EXPECTED_INPUT = ("expected a sequence folder (KITTI or TUM), an image folder or a video file "
                  "(.mp4, .mov, .avi, .mkv, .webm, ...)")
KINDS = ("kitti", "kitti_raw", "tum", "images", "video")
# sub-folders searched when an "images" folder holds no images itself
IMAGE_SUBFOLDERS = ("color", "images", "image", "rgb", "frames")


def natural_key(name: str) -> tuple:
    """Sort key ordering digit runs by value: ``"2.png" < "10.png"``; ties broken by the name."""
    parts = re.split(r"(\d+)", name)
    key = tuple(int(p) if i % 2 else p.lower() for i, p in enumerate(parts))
    return key, name


def list_images(folder: Path) -> list[Path]:
    """Image files directly inside ``folder`` (hidden files ignored), natural order."""
    files = [
        p
        for p in folder.iterdir()
        if p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".") and p.is_file()
    ]
    return sorted(files, key=lambda p: natural_key(p.name))


def _jpeg_complete(data: np.ndarray) -> bool:
    """True when the bytes end with the JPEG end-of-image marker (trailing padding allowed)."""
    tail = data[-64:].tobytes().rstrip(b"\x00\r\n ")
    return tail.endswith(b"\xff\xd9")


def decode_image(path: Path) -> tuple[np.ndarray | None, str]:
    """Decode one image file to ``(H, W, 3)`` uint8 BGR.

    Returns ``(image, "")`` or ``(None, reason)`` (the reason does not repeat
    the path); never raises for bad files.
    Truncated JPEGs (which OpenCV would decode partially, grey at the bottom)
    are detected by their missing end-of-image marker.
    """
    import cv2

    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as e:
        return None, f"cannot read file ({e.strerror or e})"
    if data.size == 0:
        return None, "empty file"
    if path.suffix.lower() in (".jpg", ".jpeg") and not _jpeg_complete(data):
        return None, "truncated JPEG (no end-of-image marker)"
    try:
        img = cv2.imdecode(data, cv2.IMREAD_COLOR)
    except cv2.error:
        img = None
    if img is None:
        return None, "cannot decode image (truncated, corrupt or not an image)"
    if img.ndim == 2:  # defensive: IMREAD_COLOR already expands grey to 3 channels
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    return np.ascontiguousarray(img), ""


class Sequence:
    """A selected range of frames from one source, streamed on iteration.

    Attributes:
        kind: ``"kitti"``, ``"kitti_raw"``, ``"tum"``, ``"images"`` or ``"video"``.
        path: the sequence folder (KITTI/KITTI raw drive/TUM/images) or the video file.
        K: ``(3, 3)`` float64 intrinsics at the source resolution.
        K_source: where ``K`` came from, e.g. ``"calib.txt:P0"``, ``"--intrinsics"``.
        image_size: ``(H, W)`` of the first readable selected frame; frames of
            another size are skipped.
        start, end, stride: the selection, ``range(start, end, stride)`` of
            source indices (``end`` already clipped to the source length).
        n_source_frames: frames in the whole source (for video: the
            container's frame count, possibly approximate).
        image_dir: the folder the frames are read from (None for video).
        shortfall: after an iteration, a :class:`~vo.frames.Shortfall` when the
            video ended before the frame count its container states (truncated
            file), else None.
    """

    def __init__(
        self,
        kind: str,
        path: Path,
        K: np.ndarray,
        K_source: str,
        *,
        files: list[Path] | None,
        timestamps: list[float] | None,
        n_source_frames: int,
        start: int,
        end: int,
        stride: int,
        image_size: tuple[int, int],
        image_dir: Path | None = None,
    ):
        self.kind = kind
        self.path = path
        self.K = K
        self.K_source = K_source
        self.image_size = image_size
        self.start = start
        self.end = end
        self.stride = stride
        self.n_source_frames = n_source_frames
        self.image_dir = image_dir
        self.shortfall: Shortfall | None = None
        self._files = files
        self._timestamps = timestamps

    def __repr__(self) -> str:
        return (
            f"Sequence(kind={self.kind!r}, path={str(self.path)!r}, frames={len(self)}, "
            f"image_size={self.image_size}, range({self.start}, {self.end}, {self.stride}))"
        )

    @property
    def indices(self) -> range:
        """Source indices of the selected frames."""
        return range(self.start, self.end, self.stride)

    def __len__(self) -> int:
        return len(self.indices)

    @property
    def files(self) -> tuple[Path, ...] | None:
        """The image files of the whole source in order (source index -> file); None for a video."""
        return None if self._files is None else tuple(self._files)

    def read_frame(self, index: int) -> Frame | FrameSkip:
        """Decode source frame ``index`` (any index in ``range(n_source_frames)``) on its own.

        A one-shot :class:`FrameReader`: for many reads from a video keep a reader instead
        (it keeps the capture open). Raises ``IndexError`` outside the source.
        """
        with FrameReader(self) as reader:
            return reader.read(index)

    def timestamp(self, index: int) -> float | None:
        """Timestamp (s) of source frame ``index`` for file-based kinds, None if unknown."""
        if self._timestamps is None:
            return None
        return self._timestamps[index]

    def ground_truth_path(self) -> Path | None:
        """``poses.txt`` (KITTI format) in the sequence folder when it exists, else None."""
        if self.kind == "video":
            return None
        p = self.path / "poses.txt"
        return p if p.is_file() else None

    def __iter__(self) -> Iterator[Frame | FrameSkip]:
        """Yield a :class:`Frame` or :class:`FrameSkip` per selected index, decoding one at a time."""
        if self.kind == "video":
            yield from self._iter_video()
            return
        H, W = self.image_size
        for i in self.indices:
            path = self._files[i]
            img, reason = decode_image(path)
            if img is None:
                yield FrameSkip(index=i, source=str(path), reason=reason)
                continue
            if img.shape[:2] != (H, W):
                h, w = img.shape[:2]
                yield FrameSkip(
                    index=i,
                    source=str(path),
                    reason=f"size {w}x{h} differs from the first frame's {W}x{H}",
                )
                continue
            yield Frame(index=i, timestamp=self.timestamp(i), image=img, source=str(path))

    def _iter_video(self) -> Iterator[Frame | FrameSkip]:
        import cv2

        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise InputError("video cannot be opened", self.path)
        fps = cap.get(cv2.CAP_PROP_FPS)
        H, W = self.image_size
        self.shortfall = None
        try:
            i = 0
            while i < self.end:
                wanted = i >= self.start and (i - self.start) % self.stride == 0
                if not wanted:
                    if not cap.grab():
                        self._ended_early(i)
                        return
                    i += 1
                    continue
                ok, img = cap.read()
                if not ok or img is None:
                    self._ended_early(i)
                    return
                src = f"{self.path}#{i}"
                if img.ndim == 2:
                    img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
                if img.shape[:2] != (H, W):
                    h, w = img.shape[:2]
                    yield FrameSkip(i, src, f"size {w}x{h} differs from the first frame's {W}x{H}")
                else:
                    yield Frame(index=i, timestamp=_video_time(cap, i, fps), image=img, source=src)
                i += 1
        finally:
            cap.release()

    def _ended_early(self, decoded: int) -> None:
        """The video ended at source frame ``decoded`` before ``self.end``: record the shortfall."""
        missing = sum(1 for k in self.indices if k >= decoded)
        self.shortfall = Shortfall(str(self.path), decoded, self.n_source_frames, missing)


class FrameReader:
    """Random access to the source frames of a :class:`Sequence`: :meth:`read` one index.

    Image files are decoded per call (no state). For a video, one ``cv2.VideoCapture``
    is kept, opened lazily by the process that reads: a reader pickled into (or forked
    into) a data-loader worker opens its own capture there, never shares one. Reading
    forwards a few frames grabs them; any other jump seeks (``CAP_PROP_POS_FRAMES``).
    Frames of a size other than ``seq.image_size`` come out as :class:`FrameSkip`, as
    in iteration (``seq.K`` would not fit them).
    """

    # forward jumps up to this many frames are decoded through instead of seeking
    MAX_GRAB = 16

    def __init__(self, seq: Sequence):
        self.seq = seq
        self._cap = None
        self._pid: int | None = None
        self._next: int | None = None  # source index the capture returns next, None: unknown
        self._fps = 0.0

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state.update(_cap=None, _pid=None, _next=None)
        return state

    def __enter__(self) -> FrameReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release the video capture of this process (the reader stays usable: it reopens)."""
        self._drop_capture()

    def _drop_capture(self) -> None:
        if self._cap is not None:
            if self._pid == os.getpid():
                self._cap.release()
            else:
                _keep_forever(self._cap)
        self._cap, self._pid, self._next = None, None, None

    def read(self, index: int) -> Frame | FrameSkip:
        """Source frame ``index`` as a :class:`Frame` (``(H, W, 3)`` uint8 BGR), or a
        :class:`FrameSkip` with the reason; never raises for a bad file. Raises
        ``IndexError`` for an index outside ``range(seq.n_source_frames)``."""
        n = self.seq.n_source_frames
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < n:
            raise IndexError(f"frame index {index!r} outside the source's {n} frames")
        index = int(index)
        H, W = self.seq.image_size
        if self.seq.kind == "video":
            img, reason, t = self._read_video(index)
            src = f"{self.seq.path}#{index}"
        else:
            path = self.seq._files[index]
            img, reason = decode_image(path)
            t, src = self.seq.timestamp(index), str(path)
        if img is None:
            return FrameSkip(index=index, source=src, reason=reason)
        if img.shape[:2] != (H, W):
            h, w = img.shape[:2]
            return FrameSkip(index=index, source=src, reason=f"size {w}x{h} differs from the first frame's {W}x{H}")
        return Frame(index=index, timestamp=t, image=img, source=src)

    def _capture(self):
        import cv2

        if self._cap is None or self._pid != os.getpid():
            self._drop_capture()  # one inherited through fork is never freed here (see _keep_forever)
            self._cap = cv2.VideoCapture(str(self.seq.path))
            self._pid, self._next = os.getpid(), 0
            self._fps = self._cap.get(cv2.CAP_PROP_FPS) if self._cap.isOpened() else 0.0
        return self._cap

    def _read_video(self, index: int) -> tuple[np.ndarray | None, str, float | None]:
        import cv2

        cap = self._capture()
        if not cap.isOpened():
            self.close()
            return None, "video cannot be opened", None
        try:
            if self._next is None or not self._next <= index <= self._next + self.MAX_GRAB:
                cap.set(cv2.CAP_PROP_POS_FRAMES, index)
                self._next = index
            while self._next < index:
                if not cap.grab():
                    self._next = None
                    return None, f"video ended before frame {index} (container states {self.seq.n_source_frames})", None
                self._next += 1
            ok, img = cap.read()
        except cv2.error as e:
            self._next = None
            return None, f"cannot decode video frame ({' '.join(str(e).split())[:120]})", None
        if not ok or img is None:
            self._next = None
            return None, f"video ended before frame {index} (container states {self.seq.n_source_frames})", None
        self._next = index + 1
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        return img, "", _video_time(cap, index, self._fps)


def _keep_forever(obj) -> None:
    """Never free ``obj``: a ``cv2.VideoCapture`` inherited through ``fork``.

    Its FFmpeg decoder and scaler own worker threads that exist only in the parent;
    freeing them in the child waits for those threads and never returns (seen with
    ``libswscale``'s slice threads). One extra reference makes the child leave it alone
    (the parent's own copy is unaffected).
    """
    import ctypes

    ctypes.pythonapi.Py_IncRef(ctypes.py_object(obj))


def _video_time(cap, index: int, fps: float) -> float | None:
    """Seconds of the frame just read: the container's timestamp, else ``index / fps``."""
    import cv2

    ms = cap.get(cv2.CAP_PROP_POS_MSEC)
    if ms > 0 or (index == 0 and ms == 0):
        return ms / 1000.0
    if fps > 0:
        return index / fps
    return None


# ---------------------------------------------------------------------------
# opening


def _read_times(path: Path) -> list[float]:
    """KITTI ``times.txt``: one number (seconds) per line."""
    out = []
    for i, line in enumerate(path.read_text().splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        try:
            out.append(float(s))
        except ValueError:
            raise InputError(f"malformed timestamp line (expected one number): {s[:60]!r}", path, i) from None
    return out


def _read_tum_list(path: Path) -> tuple[list[Path], list[float]]:
    """TUM ``rgb.txt``: ``timestamp filename`` lines, ``#`` comments."""
    files, times = [], []
    for i, line in enumerate(path.read_text().splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        try:
            t = float(parts[0])
        except ValueError:
            t = None
        if len(parts) != 2 or t is None:
            raise InputError(f"malformed line (expected 'timestamp filename'): {s[:60]!r}", path, i)
        files.append(path.parent / parts[1])
        times.append(t)
    return files, times


def _override_K(
    intrinsics: tuple[float, float, float, float] | None, calib: Path | None, camera: str | None
) -> tuple[np.ndarray, str] | None:
    if intrinsics is not None and calib is not None:
        raise InputError("give either --intrinsics or --calib, not both")
    if intrinsics is not None:
        vals = tuple(intrinsics)
        if len(vals) != 4:
            raise InputError(f"--intrinsics expects four numbers fx,fy,cx,cy, got {vals}")
        try:
            return _calib.intrinsics_matrix(*vals), "--intrinsics"
        except ValueError as e:
            raise InputError(f"--intrinsics: {e}") from None
    if calib is not None:
        calib = Path(calib)
        if not calib.is_file():
            raise InputError("calibration file not found", calib)
        return _calib.read_calib_file(calib, camera), f"--calib {calib}"
    return None


def _no_intrinsics(path: Path, looked: str) -> InputError:
    return InputError(f"no camera intrinsics found ({looked}): {_calib.how_to_give_intrinsics()}", path)


def _select(n: int, start: int, end: int | None, stride: int, path: Path) -> int:
    """Validate the selection against ``n`` source frames; returns the clipped end."""
    if stride < 1:
        raise InputError(f"stride must be >= 1, got {stride}", path)
    if start < 0:
        raise InputError(f"start must be >= 0, got {start}", path)
    if end is not None and start >= end:
        raise InputError(f"start ({start}) must be before end ({end})", path)
    stop = n if end is None else min(end, n)
    count = len(range(start, stop, stride))
    if count < 2:
        raise InputError(
            f"fewer than two frames selected ({count} of {n}: start={start}, end={end}, stride={stride})", path
        )
    return stop


def _first_readable_size(files: list[Path], indices: range, path: Path) -> tuple[int, int]:
    reasons = []
    for i in indices:
        img, reason = decode_image(files[i])
        if img is not None:
            return img.shape[0], img.shape[1]
        reasons.append(f"{files[i]}: {reason}")
    raise InputError(f"none of the {len(indices)} selected images can be decoded (first: {reasons[0]})", path)


def _open_files(
    kind: str,
    path: Path,
    files: list[Path],
    timestamps: list[float] | None,
    K_and_source: tuple[np.ndarray, str],
    start: int,
    end: int | None,
    stride: int,
    image_dir: Path | None,
) -> Sequence:
    stop = _select(len(files), start, end, stride, path)
    size = _first_readable_size(files, range(start, stop, stride), path)
    K, K_source = K_and_source
    return Sequence(
        kind,
        path,
        K,
        K_source,
        files=files,
        timestamps=timestamps,
        n_source_frames=len(files),
        start=start,
        end=stop,
        stride=stride,
        image_size=size,
        image_dir=image_dir,
    )


def _kitti_image_dir(folder: Path) -> Path | None:
    """``image_2`` if it holds images, else ``image_0`` if it does, else the first that exists."""
    existing = [folder / n for n in ("image_2", "image_0") if (folder / n).is_dir()]
    for d in existing:
        if list_images(d):
            return d
    return existing[0] if existing else None


def _open_kitti(folder, image_dir, intrinsics, calib, start, end, stride) -> Sequence:
    files = list_images(image_dir)
    if not files:
        raise InputError("no images (png/jpg/jpeg/bmp/tif) in the KITTI image folder", image_dir)
    camera = _calib.kitti_camera_for_folder(image_dir)
    K_src = _override_K(intrinsics, calib, camera)
    if K_src is None:
        calib_file = folder / "calib.txt"
        if not calib_file.is_file():
            raise _no_intrinsics(folder, f"no calib.txt beside {image_dir.name}/")
        K_src = _calib.read_kitti_calib(calib_file, camera), f"calib.txt:{camera}"
    times = None
    times_file = folder / "times.txt"
    if times_file.is_file():
        times = _read_times(times_file)
        if len(times) != len(files):
            raise InputError(
                f"{len(times)} timestamps for {len(files)} images in {image_dir.name}/", times_file
            )
    return _open_files("kitti", folder, files, times, K_src, start, end, stride, image_dir)


def _open_kitti_raw(drive, intrinsics, calib, start, end, stride) -> Sequence:
    if _kitti_raw.is_extract_drive(drive):
        raise InputError("an unrectified KITTI raw drive (_extract): its images do not fit P_rect; "
                         "give the _sync drive", drive)
    image_dir = _kitti_raw.drive_image_dir(drive)
    files = list_images(image_dir)
    if not files:
        raise InputError("no images (png/jpg/jpeg/bmp/tif) in the KITTI raw camera folder", image_dir)
    cam = _kitti_raw.camera_of(image_dir)
    K_src = _override_K(intrinsics, calib, f"P{int(cam)}")
    if K_src is None:
        calib_file = _kitti_raw.calib_file_for(drive)
        if calib_file is None:
            raise _no_intrinsics(drive, f"no {_kitti_raw.CALIB_NAME} in the date folder {drive.parent.name}/ "
                                        "nor in the drive folder")
        K_src = _kitti_raw.rect_intrinsics(calib_file, cam)[0], f"{_kitti_raw.CALIB_NAME}:P_rect_{cam}"
    times = None
    times_file = image_dir.parent / "timestamps.txt"
    if times_file.is_file():
        times = _kitti_raw.read_timestamps(times_file)
        if len(times) != len(files):
            raise InputError(f"{len(times)} timestamps for {len(files)} images in {image_dir.parent.name}/data/",
                             times_file)
    return _open_files("kitti_raw", drive, files, times, K_src, start, end, stride, image_dir)


def _open_tum(folder, intrinsics, calib, start, end, stride) -> Sequence:
    list_file = folder / "rgb.txt"
    files, times = _read_tum_list(list_file)
    if not files:
        raise InputError("no frames listed", list_file)
    K_src = _override_K(intrinsics, calib, None)
    if K_src is None:
        found = _calib.tum_default_intrinsics(folder)
        if found is None:
            raise _no_intrinsics(folder, "TUM folder name names no freiburg1/2/3 camera")
        vals, cam = found
        K_src = _calib.intrinsics_matrix(*vals), f"TUM {cam} default"
    return _open_files("tum", folder, files, times, K_src, start, end, stride, folder / "rgb")


def _open_images(folder, intrinsics, calib, start, end, stride) -> Sequence:
    image_dir = folder
    files = list_images(folder)
    if not files:
        # a dataset-style folder: images in one sub-folder (e.g. 7-Scenes ``color/``), calibration beside it
        subs = [folder / n for n in IMAGE_SUBFOLDERS if (folder / n).is_dir() and list_images(folder / n)]
        if len(subs) == 1:
            image_dir = subs[0]
            files = list_images(image_dir)
    if not files:
        raise InputError(
            "no images (png/jpg/jpeg/bmp/tif) in this folder (nor in a sub-folder "
            + "/".join(IMAGE_SUBFOLDERS)
            + "/), and it is not a KITTI or TUM folder",
            folder,
        )
    K_src = _override_K(intrinsics, calib, None)
    if K_src is None:
        for d in dict.fromkeys((folder, image_dir)):
            for name in ("calib.txt", "K.txt"):
                if (d / name).is_file():
                    K_src = _calib.read_calib_file(d / name), str((d / name).relative_to(folder))
                    break
            if K_src is not None:
                break
    if K_src is None:
        raise _no_intrinsics(folder, "no calib.txt or K.txt in the folder")
    return _open_files("images", folder, files, None, K_src, start, end, stride, image_dir)


def _open_video(path, intrinsics, calib, start, end, stride) -> Sequence:
    import cv2

    K_src = _override_K(intrinsics, calib, None)
    if K_src is None:
        raise _no_intrinsics(path, "a video carries no calibration")
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise InputError(f"video cannot be opened (unknown format or corrupt file); {EXPECTED_INPUT}", path)
        n = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        ok, img = cap.read()
        if not ok or not isinstance(img, np.ndarray) or img.ndim not in (2, 3) or img.size == 0:
            raise InputError(f"video has no decodable frame; {EXPECTED_INPUT}", path)
    finally:
        cap.release()
    if n <= 0:
        raise InputError("video reports no frame count; convert it to images or a standard container", path)
    stop = _select(n, start, end, stride, path)
    K, K_source = K_src
    return Sequence(
        "video",
        path,
        K,
        K_source,
        files=None,
        timestamps=None,
        n_source_frames=n,
        start=start,
        end=stop,
        stride=stride,
        image_size=(img.shape[0], img.shape[1]),
    )


def open_sequence(
    path: str | Path,
    *,
    intrinsics: tuple[float, float, float, float] | None = None,
    calib: str | Path | None = None,
    start: int = 0,
    end: int | None = None,
    stride: int = 1,
) -> Sequence:
    """Open ``path`` as a KITTI (odometry or raw drive), TUM, image-folder or video sequence.

    Args:
        path: sequence folder or video file.
        intrinsics: ``(fx, fy, cx, cy)`` at source resolution; overrides the
            sequence's own calibration.
        calib: a calibration file (KITTI ``calib.txt``, 3x3 K, or
            ``fx fy cx cy``); overrides the sequence's own calibration. For a
            KITTI folder its ``P<n>`` line is chosen by the image folder name.
        start, end: source index range, ``end`` exclusive (None: to the end).
        stride: use every ``stride``-th frame (>= 1).

    Returns:
        a :class:`Sequence`; nothing is decoded except the first selected
        frame (to learn the image size).

    Raises:
        InputError: missing path, no images, no intrinsics, malformed
            calibration / ``times.txt`` / ``rgb.txt`` line, a file without a video
            container suffix, video that cannot be opened or whose first frame does
            not decode, bad selection, fewer than two frames selected.
    """
    p = Path(path)
    if not p.exists():
        raise InputError("no such file or folder", p)
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise InputError(f"stride must be an integer >= 1, got {stride!r}", p)
    calib_p = None if calib is None else Path(calib)
    if p.is_file():
        if p.suffix.lower() in IMAGE_EXTENSIONS:
            raise InputError("a single image is not a sequence: give its folder or a video", p)
        if p.suffix.lower() not in VIDEO_EXTENSIONS:
            what = f"a {p.suffix} file" if p.suffix else "a file without a suffix"
            raise InputError(f"not a video file ({what}, not a video container); {EXPECTED_INPUT}", p)
        return _open_video(p, intrinsics, calib_p, start, end, stride)
    if not p.is_dir():
        raise InputError("neither a folder nor a file", p)
    if (p / "rgb.txt").is_file():
        return _open_tum(p, intrinsics, calib_p, start, end, stride)
    image_dir = _kitti_image_dir(p)
    if image_dir is not None:
        return _open_kitti(p, image_dir, intrinsics, calib_p, start, end, stride)
    if re.fullmatch(r"image_\d+", p.name) and (p.parent / "calib.txt").is_file():
        return _open_kitti(p.parent, p, intrinsics, calib_p, start, end, stride)
    if not list_images(p) and _kitti_raw.is_drive(p):
        return _open_kitti_raw(p, intrinsics, calib_p, start, end, stride)
    return _open_images(p, intrinsics, calib_p, start, end, stride)


# ---------------------------------------------------------------------------
# prefetching


_DONE = object()


class Prefetcher:
    """Iterate ``items`` in a background thread, ``depth`` items ahead.

    Decoding (``cv2.imdecode``) releases the GIL, so wrapping a
    :class:`Sequence` overlaps decoding frame t+1 with processing frame t.
    Exceptions raised by the source are re-raised in the consumer. Use as a
    context manager (or call :meth:`close`) to stop the thread early::

        with Prefetcher(seq) as frames:
            for f in frames: ...
    """

    def __init__(self, items: Iterable, depth: int = 2):
        if depth < 1:
            raise ValueError(f"depth must be >= 1, got {depth}")
        self._q: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(items,), daemon=True)
        self._thread.start()

    def _put(self, item) -> bool:
        while not self._stop.is_set():
            try:
                self._q.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def _run(self, items: Iterable) -> None:
        it = iter(items)
        try:
            for item in it:
                if not self._put((item, None)):
                    return
        except BaseException as e:  # handed to the consumer
            self._put((_DONE, e))
            return
        finally:
            close = getattr(it, "close", None)
            if close is not None:
                close()  # e.g. release a video capture when stopped early
        self._put((_DONE, None))

    def __iter__(self):
        while True:
            try:
                item, err = self._q.get(timeout=0.05)
            except queue.Empty:
                if self._stop.is_set() or not self._thread.is_alive() and self._q.empty():
                    return
                continue
            if item is _DONE:
                self._thread.join()
                if err is not None:
                    raise err
                return
            yield item

    def close(self) -> None:
        """Stop the background thread (pending items are dropped)."""
        self._stop.set()
        self._thread.join()

    def __enter__(self) -> Prefetcher:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
